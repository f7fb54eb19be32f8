"""sim_node in a real ROS 2 graph (subprocess, private domain): commands in, odometry/images out."""
import json
import math
import threading

import numpy as np
import pytest
from geometry_msgs.msg import PointStamped, TwistStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from assist_common.ros_io import LANDING_QOS, LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, fill_twist

pytestmark = pytest.mark.graph


class Probe:
    """Collects messages of the sim_node topics."""

    def __init__(self, node):
        self.node = node
        self.lock = threading.Lock()
        self.msgs = {k: [] for k in ('odom', 'rgb', 'depth', 'info', 'clock', 'goal', 'landing')}
        subs = [(Odometry, '/odom', 'odom', SENSOR_QOS), (Image, '/camera/color/image_raw', 'rgb', SENSOR_QOS),
                (Image, '/camera/depth/image_raw', 'depth', SENSOR_QOS),
                (CameraInfo, '/camera/color/camera_info', 'info', SENSOR_QOS), (Clock, '/clock', 'clock', 10),
                (PointStamped, '/sim/goal', 'goal', LATCHED_QOS), (String, '/sim/landing', 'landing', LANDING_QOS)]
        self.subs = [node.create_subscription(t, n, self._cb(k), q) for t, n, k, q in subs]
        self.cmd = node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
        self.reset = node.create_client(Trigger, '/sim/reset')

    def _cb(self, key):
        def cb(msg):
            with self.lock:
                self.msgs[key].append(msg)
        return cb

    def last(self, key):
        with self.lock:
            return self.msgs[key][-1] if self.msgs[key] else None

    def count(self, key):
        with self.lock:
            return len(self.msgs[key])

    def send(self, v, frame='base_link'):
        msg = TwistStamped()
        msg.header.frame_id = frame
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.cmd.publish(fill_twist(msg, v))

    def close(self):
        for s in self.subs:
            self.node.destroy_subscription(s)
        self.node.destroy_publisher(self.cmd)
        self.node.destroy_client(self.reset)


@pytest.fixture
def probe(ros):
    p = Probe(ros)
    yield p
    p.close()


def _sim_now(probe) -> float:
    od = probe.last('odom')
    return od.header.stamp.sec + 1e-9 * od.header.stamp.nanosec


def _fly(probe, v, sim_seconds, wall_limit=60.0):
    """Send `v` at 20 Hz (wall) until the sim clock (odometry stamps) has advanced `sim_seconds`.

    Sim time, not wall time: on a loaded machine the sim may run slower than its real_time_factor.
    """
    import time
    t0 = _sim_now(probe)
    end = time.monotonic() + wall_limit
    while _sim_now(probe) - t0 < sim_seconds and time.monotonic() < end:
        probe.send(v)
        time.sleep(0.05)


def test_sim_node_command_in_odometry_and_images_out(probe, start_node, wait):
    sim = start_node('sim_node', {'seed': 3, 'real_time_factor': 1.0, 'camera_width': 48, 'camera_height': 40})
    assert wait(lambda: probe.count('odom') > 5 and probe.count('rgb') > 2, 30), sim.log()
    goal = probe.last('goal')
    assert wait(lambda: probe.last('goal') is not None, 5)
    goal = probe.last('goal')
    assert goal.header.frame_id == 'odom' and 0.3 < goal.point.z < 1.5

    x0 = probe.last('odom').pose.pose.position.x
    # 4 s of sim time (at rtf 1 a command stays fresh for 0.5 s of wall time)
    _fly(probe, (1.0, 0.0, 0.0), 4.0)
    od = probe.last('odom')
    assert od.header.frame_id == 'odom' and od.child_frame_id == 'base_link'
    assert od.pose.pose.position.x - x0 > 2.0             # moved forward (+x ENU)
    assert od.twist.twist.linear.x == pytest.approx(1.0, abs=0.35)

    rgb, depth, info = probe.last('rgb'), probe.last('depth'), probe.last('info')
    assert (rgb.encoding, rgb.width, rgb.height, rgb.step) == ('rgb8', 48, 40, 48 * 3)
    assert (depth.encoding, depth.width, depth.height) == ('32FC1', 48, 40)
    assert rgb.header.frame_id == depth.header.frame_id == info.header.frame_id == 'camera_optical_frame'
    d = np.frombuffer(bytes(depth.data), dtype=np.float32).reshape(40, 48)
    z = od.pose.pose.position.z
    assert np.all(np.isfinite(d)) and 0.5 < d.max() <= z + 0.1  # metres, not a normalised buffer
    assert info.k[0] > 0 and info.width == 48
    # sim time advances with /clock and stamps use it
    c = probe.last('clock').clock
    assert c.sec + c.nanosec * 1e-9 > 3.0

    # a NaN command is rejected: the vehicle stops (stale command -> hover), it does not fly NaN
    _fly(probe, (math.nan, 0.0, 0.0), 3.0)
    od = probe.last('odom')
    assert abs(od.twist.twist.linear.x) < 0.3 and math.isfinite(od.pose.pose.position.x)
    assert sim.proc.poll() is None and 'rejected' in sim.log()

    # the reset service starts a new episode and re-publishes the goal
    assert probe.reset.wait_for_service(5.0)
    fut = probe.reset.call_async(Trigger.Request())
    assert wait(fut.done, 10) and fut.result().success, fut.result()
    assert 'episode 1' in fut.result().message


def test_sim_node_reports_landings(probe, start_node, wait):
    start_node('sim_node', {'seed': 5, 'real_time_factor': 8.0, 'camera_rate_hz': 5.0})
    assert wait(lambda: probe.last('goal') is not None and probe.last('odom') is not None, 30)
    goal = probe.last('goal').point
    import time
    end = time.monotonic() + 60
    while probe.count('landing') == 0 and time.monotonic() < end:
        p = probe.last('odom').pose.pose.position
        d = np.array([goal.x - p.x, goal.y - p.y])
        v = np.clip(1.2 * d, -2.0, 2.0)
        vz = -0.8 if np.linalg.norm(d) < 0.15 else 0.0
        probe.send((v[0], v[1], vz))
        time.sleep(0.02)
    assert probe.count('landing') == 1
    result = json.loads(probe.last('landing').data)
    keys = {'episode', 'goal_index', 'landed_index', 'nearest_index', 'error_m', 'nearest_error_m', 'success',
            'crash', 'duration_s', 'assisted'}
    assert keys <= set(result)
    # the test's own P controller in ground-effect turbulence
    assert result['success'] and result['landed_index'] == result['goal_index'] and result['error_m'] < 0.4
    assert result['assisted'] is False
    # auto_reset: a new goal follows
    assert wait(lambda: probe.count('goal') >= 2, 10)


def test_sim_node_bad_parameter_exits_with_one_clear_line(start_node, wait):
    sim = start_node('sim_node', {'world_config': '/nonexistent/world.yaml'})
    assert wait(lambda: sim.proc.poll() is not None, 20)
    assert sim.proc.returncode == 1
    log = sim.log()
    assert 'cannot load world_config' in log and 'Traceback' not in log


def test_sim_node_sigint_exits_cleanly(probe, start_node, wait):
    sim = start_node('sim_node', {'seed': 1, 'real_time_factor': 0.0})   # as fast as possible
    assert wait(lambda: probe.count('clock') > 20, 30), sim.log()
    assert sim.stop() == 0
    log = sim.log()
    assert 'Traceback' not in log and 'RCLError' not in log, log[-2000:]
