"""bag_record: records topics (default: the contract's set) into a rosbag2 bag (MCAP or sqlite3).

    bag_record flights/run1                                  # default topics, MCAP, a new file every 30 s
    bag_record flights/run1 --topics /odom /cmd_vel --storage sqlite3 --split-size-mb 100
    ros2 run assist_policy bag_record --ros-args -p output:=flights/run1

Topics are subscribed as they appear (type and offered QoS taken from their publishers) and
written as received (CDR bytes, receive time of the node's clock: sim time with use_sim_time).
Ctrl-C / SIGTERM close the bag cleanly; a killed recorder loses at most the file it was writing
(metadata.yaml is rewritten after every finished file; see split_duration_s / split_size_mb).
"""
from __future__ import annotations

import logging
import sys
import time

from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from assist_sim.ros_common import Diagnostics, Param, StartupError, declare_parameters, run_node

from .bagio import CONTRACT_TOPICS, BagError, BagWriter, typestore
from .rosutil import bag_qos, cli_to_ros_args, message_class

log = logging.getLogger('bag_record')

PARAMS = {
    'output': Param('', 'Bag directory to create (must not exist); empty: rosbag2_<UTC date-time> here.'),
    'topics': Param(Parameter.Type.STRING_ARRAY, 'Topics to record; empty or unset: the contract set '
                    '(camera, odom, pilot, assistant, cmd_vel, goal, landing, scene, diagnostics).'),
    'storage': Param('mcap', 'Storage format of the data files.', choices=('mcap', 'sqlite3')),
    'split_duration_s': Param(30.0, 'Start a new data file after this many seconds (0: never).', min=0.0,
                              max=86400.0),
    'split_size_mb': Param(0.0, 'Start a new data file after this many MB of messages (0: never).', min=0.0,
                           max=1e6),
    'discovery_period_s': Param(0.5, 'How often to look for new publishers of the wanted topics.', min=0.05,
                                max=60.0),
}


class BagRecordNode(Node):
    """Subscribes (raw) to the wanted topics as they appear and appends every message to a BagWriter."""

    def __init__(self, **kwargs):
        super().__init__('bag_record', **kwargs)
        self.p = declare_parameters(self, PARAMS)
        self.diag = Diagnostics(self)
        topics = [t for t in (self.p['topics'] or []) if t]
        if self.p['topics'] is not None and list(self.p['topics']) and not topics:
            raise StartupError('bag_record: the topic selection is empty')
        self.wanted = topics or list(CONTRACT_TOPICS)
        out = self.p['output'] or time.strftime('rosbag2_%Y_%m_%d-%H_%M_%S', time.gmtime())
        try:
            self.writer = BagWriter(out, storage=self.p['storage'],
                                    split_size_bytes=int(self.p['split_size_mb'] * 1e6),
                                    split_duration_ns=int(self.p['split_duration_s'] * 1e9))
        except BagError as exc:
            raise StartupError(f'bag_record: {exc}') from exc
        self.output = out
        self.subs: dict[str, object] = {}
        self.warned: set[str] = set()
        self.count = 0
        self.write_errors = 0
        self.create_timer(float(self.p['discovery_period_s']), self._discover)
        self._discover()
        self.get_logger().info(f'bag_record: recording {len(self.wanted)} topics into {out} '
                               f'({self.p["storage"]})')

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self.warned:
            self.warned.add(key)
            self.get_logger().warning(text)

    def _discover(self) -> None:
        types = dict(self.get_topic_names_and_types())
        for topic in self.wanted:
            if topic in self.subs or topic not in types:
                continue
            msgtype = types[topic][0]
            cls = message_class(msgtype)
            if cls is None or msgtype not in typestore().types:
                self._warn_once(topic, f'bag_record: not recording {topic}: type {msgtype} unknown to this install')
                continue
            infos = self.get_publishers_info_by_topic(topic)
            if not infos:
                continue
            offered = [i.qos_profile for i in infos]
            best_effort = any(q.reliability == ReliabilityPolicy.BEST_EFFORT for q in offered)
            latched = all(q.durability == DurabilityPolicy.TRANSIENT_LOCAL for q in offered)
            qos = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            try:
                self.writer.add_topic(topic, msgtype, [bag_qos(q) for q in offered])
            except BagError as exc:
                self._warn_once(topic, f'bag_record: not recording {topic}: {exc}')
                continue
            self.subs[topic] = self.create_subscription(cls, topic, lambda raw, t=topic: self._on_msg(t, raw),
                                                        qos, raw=True)
            self.get_logger().info(f'bag_record: recording {topic} [{msgtype}]')

    def _on_msg(self, topic: str, raw: bytes) -> None:
        try:
            self.writer.write(topic, self.get_clock().now().nanoseconds, raw)
            self.count += 1
        except BagError as exc:
            self.write_errors += 1
            self.diag.count('write_errors')
            self.get_logger().error(f'bag_record: {exc}', throttle_duration_sec=5.0)

    def close(self) -> None:
        """Finish the bag (called by run_node on Ctrl-C, SIGTERM and normal exit)."""
        # plain logging: after SIGTERM the rclpy context (and /rosout) is already gone
        try:
            self.writer.close()
            log.info('bag_record: wrote %d messages to %s', self.count, self.output)
        except BagError as exc:
            log.error('bag_record: %s', exc)


def main(args=None):
    """Console entry point (flags map to the node parameters; --help lists them)."""
    argv = sys.argv[1:] if args is None else list(args)
    ros_args = cli_to_ros_args('bag_record', __doc__, PARAMS, argv, positional='output')
    sys.exit(run_node(lambda: BagRecordNode(), ros_args))


if __name__ == '__main__':
    main()
