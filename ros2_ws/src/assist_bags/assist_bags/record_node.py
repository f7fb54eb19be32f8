"""bag_record: records topics (default: the contract's set) into a rosbag2 bag (MCAP or sqlite3).

    bag_record flights/run1                                  # default topics, MCAP, a new file every 30 s
    bag_record flights/run1 --topics /odom /cmd_vel --storage sqlite3 --split-size-mb 100
    ros2 run assist_bags bag_record --ros-args -p output:=flights/run1

Topics are subscribed as they appear (type and offered QoS taken from their publishers) and
written as received (CDR bytes, receive time of the node's clock: sim time with use_sim_time).
Ctrl-C / SIGTERM close the bag cleanly; a killed recorder loses at most the file it was writing
(metadata.yaml is rewritten after every finished file; see split_duration_s / split_size_mb).
A write error, or free space on the bag's filesystem falling below `min_free_mb` (kept so that the file
being written can still be closed), stops the recording: nothing more is written, the bag is closed with
every message written so far, and the recorder exits with one `error:` line and exit code 1.

The configuration that flew goes into the bag too: with `record_parameters` (default on) the recorder
asks each node named in `parameter_nodes` (encoder_node and policy_node by default, in any namespace)
for all its parameters over the node's parameter services once it appears, and writes them into
metadata.yaml's custom_data as ``assist.params.<node>`` (a JSON object; the node's name without the
leading slash), rewritten at once. replay_assist reads the flown mode, rules and models from there and
encoder_node's depth-noise settings (depth_noise, noise_seed: each frame's noise is a function of the
seed and the frame's stamp), so it can re-encode the frames through the noise they had. The values
are those the node held when the recorder reached it; ``assist.record_clock`` says whether receive
times are sim time (use_sim_time) or wall-clock time.
"""
from __future__ import annotations

import json
import logging
import sys
import time
from typing import Any

from rcl_interfaces.srv import GetParameters, ListParameters
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from assist_common.ros_io import Diagnostics
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import run_node

from .bagio import CLOCK_KEY, CONTRACT_TOPICS, PARAMS_KEY, BagError, BagWriter, typestore
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
    'min_free_mb': Param(8.0, 'Stop recording (error, exit 1) when less than this many MB would stay free on the '
                         'bag\'s filesystem: room to close the file being written.', min=0.0, max=1e6),
    'discovery_period_s': Param(0.5, 'How often to look for new publishers of the wanted topics.', min=0.05,
                                max=60.0),
    'record_parameters': Param(True, 'Write the parameters of the nodes in parameter_nodes into the bag\'s '
                                     'custom_data (assist.params.<node>, JSON) once they appear.'),
    'parameter_nodes': Param(Parameter.Type.STRING_ARRAY, 'Names of the nodes (any namespace) whose parameters '
                             'record_parameters stores; empty or unset: encoder_node and policy_node.'),
}
PARAMETER_NODES = ('encoder_node', 'policy_node')


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
                                    split_duration_ns=int(self.p['split_duration_s'] * 1e9),
                                    min_free_bytes=int(self.p['min_free_mb'] * 1e6))
        except BagError as exc:
            raise StartupError(f'bag_record: {exc}') from exc
        self.output = out
        use_sim_time = bool(self.get_parameter('use_sim_time').value)
        try:
            self.writer.set_custom_data(CLOCK_KEY, 'sim' if use_sim_time else 'wall')
        except BagError as exc:
            raise StartupError(f'bag_record: {exc}') from exc
        nodes = [n for n in (self.p['parameter_nodes'] or []) if n] or PARAMETER_NODES
        self.param_nodes = set(nodes) if self.p['record_parameters'] else set()
        self.param_clients: dict[str, tuple[Any, Any]] = {}   # node -> (list, get) parameter service clients
        self.param_pending: set[str] = set()
        self.params_done: set[str] = set()
        self.subs: dict[str, object] = {}
        self.warned: set[str] = set()
        self.count = 0
        self.write_errors = 0
        self.failure: str | None = None      # why the recording stopped early (exit code 1)
        # on the steady clock: with use_sim_time a sim-time timer would wait for /clock, and nodes and topics that
        # appear before the sim starts would go unrecorded until it does
        self.create_timer(float(self.p['discovery_period_s']), self._discover,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._discover()
        self.get_logger().info(f'bag_record: recording {len(self.wanted)} topics into {out} '
                               f'({self.p["storage"]})')

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self.warned:
            self.warned.add(key)
            self.get_logger().warning(text)

    def _discover(self) -> None:
        if self.failure is not None:
            return
        self._discover_parameters()
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

    def _discover_parameters(self) -> None:
        """Ask each wanted node that has appeared (once its parameter services are up) for its parameters, once."""
        if not self.param_nodes:
            return
        for name, ns in self.get_node_names_and_namespaces():
            fqn = (ns.rstrip('/') + '/' + name).lstrip('/')
            if name not in self.param_nodes or fqn in self.params_done or fqn in self.param_pending:
                continue
            if fqn not in self.param_clients:
                self.param_clients[fqn] = (self.create_client(ListParameters, f'/{fqn}/list_parameters'),
                                           self.create_client(GetParameters, f'/{fqn}/get_parameters'))
            lister, getter = self.param_clients[fqn]
            if not (lister.service_is_ready() and getter.service_is_ready()):
                continue
            self.param_pending.add(fqn)
            lister.call_async(ListParameters.Request()).add_done_callback(
                lambda fut, n=fqn: self._on_param_names(n, fut))

    def _param_failed(self, fqn: str, what: str) -> None:
        """Forget the pending request: the next discovery asks again."""
        self.param_pending.discard(fqn)
        self._warn_once(f'params:{fqn}:{what}', f'bag_record: asking /{fqn} for its parameters failed ({what}); '
                                                'retrying')

    def _on_param_names(self, fqn: str, fut: Any) -> None:
        res = fut.result() if fut.exception() is None else None
        if res is None:
            self._param_failed(fqn, 'list_parameters')
            return
        names = sorted(res.result.names)
        req = GetParameters.Request()
        req.names = names
        self.param_clients[fqn][1].call_async(req).add_done_callback(
            lambda f, n=fqn, k=names: self._on_param_values(n, k, f))

    def _on_param_values(self, fqn: str, names: list[str], fut: Any) -> None:
        res = fut.result() if fut.exception() is None else None
        if res is None or len(res.values) != len(names):
            self._param_failed(fqn, 'get_parameters')
            return
        values = {}
        for name, value in zip(names, res.values):
            v = parameter_value_to_python(value)
            values[name] = list(v) if not isinstance(v, (str, bytes)) and hasattr(v, '__len__') else v
        try:
            self.writer.set_custom_data(PARAMS_KEY + fqn, json.dumps(values, sort_keys=True, default=str))
        except BagError as exc:
            if self.writer.failed is not None:
                self._stop_recording(exc)
            else:
                self.get_logger().error(f'bag_record: {exc}')
        self.params_done.add(fqn)
        self.param_pending.discard(fqn)
        self.get_logger().info(f'bag_record: recorded the {len(values)} parameters of /{fqn}')

    def _on_msg(self, topic: str, raw: bytes) -> None:
        if self.failure is not None:
            return                      # stopped: messages already queued are not taken any more
        try:
            self.writer.write(topic, self.get_clock().now().nanoseconds, raw)
            self.count += 1
        except BagError as exc:
            self._stop_recording(exc)

    # a write error ends the process (bag_record); a recorder inside another node's process clears this
    exit_on_write_error = True

    def _stop_recording(self, exc: BagError) -> None:
        """A write error ends the recording: nothing more is written, the node exits (close() keeps what was)."""
        if self.failure is not None:
            return
        self.failure = str(exc)
        self.write_errors += 1
        self.diag.count('write_errors')
        self.get_logger().error(f'bag_record: {exc}; stopping after {self.count} messages')
        if self.exit_on_write_error:
            raise SystemExit(1)         # ends the spin (nothing more is taken); run_node then calls close()

    def close(self) -> None:
        """Finish the bag (called by run_node on Ctrl-C, SIGTERM, normal exit and after a write error)."""
        # plain logging: after SIGTERM the rclpy context (and /rosout) is already gone
        try:
            self.writer.close()
            log.info('bag_record: wrote %d messages to %s', self.count, self.output)
        except BagError as exc:
            log.error('bag_record: %s', exc)
            if self.failure is None:
                self.failure = str(exc)
            else:
                self.failure += f'; {exc}'.replace(f'{self.writer.path}: ', '', 1)


def main(args=None):
    """Console entry point (flags map to the node parameters; --help lists them); exit 1 after a write error."""
    argv = sys.argv[1:] if args is None else list(args)
    ros_args = cli_to_ros_args('bag_record', __doc__, PARAMS, argv, positional='output')
    nodes: list[BagRecordNode] = []

    def make() -> BagRecordNode:
        nodes.append(BagRecordNode())
        return nodes[-1]
    try:
        code = run_node(make, ros_args)
    except SystemExit as exc:           # raised by _stop_recording inside the spin
        code = int(exc.code or 0)
    if nodes and nodes[0].failure is not None:
        sys.stderr.write(f'error: bag_record: {nodes[0].failure} ({nodes[0].count} messages kept in '
                         f'{nodes[0].output})\n')
        code = code or 1
    sys.exit(code)


if __name__ == '__main__':
    main()
