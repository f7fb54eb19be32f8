"""Python logging of cores reaches the node's logger and /rosout (forward_logging / run_node)."""
import logging
import threading
import time

import rclpy
from rcl_interfaces.msg import Log
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from assist_common.ros_io import forward_logging
from assist_common.domains import private_domain_id


def test_core_log_records_reach_rosout_under_the_node_logger():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=private_domain_id())
    node = Node('log_test', context=ctx)
    got: list[Log] = []
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(Log, '/rosout', got.append, qos)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        handler = forward_logging(node)
        assert handler in root.handlers and root.level <= logging.INFO
        core = logging.getLogger('assist_sim.fake_core')
        core.info('MAVLink link up')
        core.warning('mode %s', 'GUIDED')
        core.debug('not shown at INFO')
        end = time.monotonic() + 20.0
        while time.monotonic() < end and len([m for m in got if m.name == 'log_test.assist_sim.fake_core']) < 2:
            time.sleep(0.05)
        mine = [(m.level, m.msg) for m in got if m.name == 'log_test.assist_sim.fake_core']
        assert mine == [(Log.INFO, 'MAVLink link up'), (Log.WARN, 'mode GUIDED')]
        stamp = [m.stamp for m in got if m.name == 'log_test.assist_sim.fake_core'][0]
        assert stamp.sec > 0                                  # rclpy stamped it
        handler.attach(None)                                  # node gone: console only, no error
        core.info('after the node')
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
