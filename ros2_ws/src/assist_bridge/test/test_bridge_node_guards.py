"""mavlink_bridge_node in process: no message ends it (mocap poses that do not fit MAVLink are refused, every
timer and subscription that packs or sends MAVLink is guarded), parameters that reach MAVLink are range-checked
at start-up (one line, exit status 1), the landed state is published reliable + transient local, and mocap from
more than one source is said once on /diagnostics."""
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

rclpy = pytest.importorskip('rclpy')
from geometry_msgs.msg import PoseStamped, TwistStamped  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import UInt8  # noqa: E402

from assist_bridge import mavlink_bridge_node  # noqa: E402
from assist_bridge.mavlink_bridge_node import LANDED_STATE_TOPIC, MavlinkBridgeNode  # noqa: E402
from assist_bridge.vision import VisionEstimate  # noqa: E402
from assist_common.ros_io import LATCHED_QOS, release_logging  # noqa: E402
from assist_common.ros_params import StartupError  # noqa: E402
from assist_sim.testing import free_udp_port  # noqa: E402
from assist_common.domains import private_domain_id  # noqa: E402

BIN = Path(sys.executable).parent
MOCAP = '/bridge_guard_test/mocap'


def _domain() -> int:
    """ROS_DOMAIN_ID when the caller set one, else a private one."""
    return int(os.environ.get('ROS_DOMAIN_ID') or private_domain_id())


@pytest.fixture
def wall(monkeypatch):
    """The node's wall clock (pose ages), held still unless a test moves `wall.t`."""
    clock = SimpleNamespace(t=1_700_000_000.0)
    monkeypatch.setattr(mavlink_bridge_node, 'time', SimpleNamespace(time=lambda: clock.t))
    return clock


@pytest.fixture
def make_node(wall):
    """Factory: make_node(param=value, ...) -> MavlinkBridgeNode on its own context, listening on a free port."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=_domain())
    made = []

    def _make(**params) -> MavlinkBridgeNode:
        params.setdefault('connection', f'udpin:127.0.0.1:{free_udp_port()}')
        node = MavlinkBridgeNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        made.append(node)
        return node
    yield _make
    for node in made:
        node.close()
        node.destroy_node()
    release_logging()
    rclpy.shutdown(context=ctx)


def pose(x: float, stamp_s: float, frame: str = 'mocap') -> PoseStamped:
    m = PoseStamped()
    m.header.frame_id = frame
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(round(stamp_s * 1e9), 1_000_000_000)
    m.pose.position.x, m.pose.position.z = x, 1.0
    m.pose.orientation.w = 1.0
    return m


def callbacks(node):
    """The node's subscription callbacks by topic and its timer callbacks."""
    subs = {s.topic_name: s.callback for s in node.subscriptions}
    return subs, [t.callback for t in node.timers]


def test_a_mocap_pose_beyond_float32_is_refused_and_the_timers_go_on(make_node, wall):
    node = make_node(mocap_topic=MOCAP)
    node.bridge.status.link_up = True
    subs, timers = callbacks(node)
    subs[MOCAP](pose(1e39, wall.t))
    wall.t += 0.01
    subs[MOCAP](pose(1e30, wall.t))
    for timer in timers:                    # the vision timer packed 1e39 and raised OverflowError here
        timer()
    assert node.diag.get('mocap_rejected_out_of_range') == 2
    assert node.diag.get('callback_errors') == 0 and node.bridge.counters['tx_errors'] == 0
    wall.t += 0.01
    subs[MOCAP](pose(1.0, wall.t))
    assert node.diag.get('mocap_in') == 1


def test_every_callback_that_sends_mavlink_survives_a_failing_send(make_node, wall):
    node = make_node(mocap_topic=MOCAP, ekf_origin=[47.4, 8.5, 488.0])
    node.bridge.status.link_up = True
    subs, timers = callbacks(node)
    # a value that cannot be packed reaches the core: counted there, not raised
    subs[MOCAP](pose(0.0, wall.t))
    node.vision.latest = (node.vision.latest[0], VisionEstimate(1, 1e39, 0.0, 0.0, 0.0, 0.0, 0.0, (0.0,) * 21, 0))
    for timer in timers:
        timer()
    assert node.bridge.counters['tx_errors'] == 1 and node.origin_sent

    def broken(*_args, **_kwargs):
        raise RuntimeError('the link broke')
    for name in ('send_vision', 'set_ekf_origin', 'set_command', 'snapshot'):
        setattr(node.bridge, name, broken)
    node.origin_sent = False
    cmd = TwistStamped()
    cmd.header.frame_id = 'base_link'
    subs['/cmd_vel'](cmd)
    wall.t += 0.1
    subs[MOCAP](pose(0.01, wall.t))
    for timer in timers:
        timer()
    assert node.diag.get('callback_errors') == 3       # /cmd_vel, the vision timer, the diagnostics timer
    assert node.diag.get('mocap_in') == 2


@pytest.mark.parametrize('params, words', [
    (dict(ekf_origin=[47.4, 8.5, 1e10]), "parameter 'ekf_origin' altitude_m must be <= 10000"),
    (dict(ekf_origin=[47.4, 8.5, -1e6]), "parameter 'ekf_origin' altitude_m must be >= -500"),
    (dict(ekf_origin=[47.4, 8.5]), "parameter 'ekf_origin' must be [latitude deg, longitude deg, altitude m]"),
    (dict(mocap_topic=MOCAP, vision_reset_jump_m=5.0, vision_max_jump_m=1.0),
     'vision_max_jump_m (1) must be >= reset_jump_m (5)'),
])
def test_parameters_that_reach_mavlink_are_checked_at_start_up(make_node, params, words):
    with pytest.raises(StartupError) as err:
        make_node(**params)
    assert words in str(err.value) and '\n' not in str(err.value)


@pytest.mark.parametrize('param, value, words', [
    ('ekf_origin', '[47.4, 8.5, 10000000000.0]', "'ekf_origin' altitude_m must be <= 10000"),
    ('vision_max_position_m', '1e39', "'vision_max_position_m' must be"),
    ('odom_rate_hz', '1000000.0', "'odom_rate_hz' must be"),
])
def test_the_node_exits_1_with_one_error_line(param, value, words):
    proc = subprocess.run([str(BIN / 'mavlink_bridge_node'), '--ros-args', '-p', f'{param}:={value}', '-p',
                           f'connection:=udpin:127.0.0.1:{free_udp_port()}'], capture_output=True, text=True,
                          timeout=60, env=dict(os.environ, ROS_DOMAIN_ID=str(_domain())))
    out = proc.stdout + proc.stderr
    errors = [line for line in out.splitlines() if line.startswith('error:')]
    assert proc.returncode == 1 and len(errors) == 1 and words in errors[0], out
    assert 'Traceback' not in out


def test_landed_state_is_latched_for_late_subscribers(make_node):
    node = make_node()
    qos = node.pub_landed.qos_profile
    assert (qos.reliability, qos.durability) == (ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)
    node._on_landed_state(1)
    node._on_landed_state(2)                # what the core hands on: the first report, then each change
    probe = Node('landed_state_probe', context=node.context)
    got = []
    probe.create_subscription(UInt8, LANDED_STATE_TOPIC, lambda m: got.append(m.data), LATCHED_QOS)
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(probe)
    try:
        deadline = time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        assert got == [2]                   # the late joiner gets the latest state
        assert node.diag.get('landed_state_published') == 2
    finally:
        executor.shutdown()
        probe.destroy_node()


def test_two_mocap_sources_are_said_once_and_do_not_bump_the_reset_counter(make_node, wall):
    node = make_node(mocap_topic=MOCAP)
    subs, _ = callbacks(node)
    for k in range(20):                     # two drivers 2 m apart, interleaved at 100 Hz each
        wall.t += 0.005
        subs[MOCAP](pose(0.0 if k % 2 == 0 else 2.0, wall.t))
    assert node.vision.reset_counter == 0
    assert node.diag.get('mocap_in') == 10 and node.diag.get('mocap_rejected_jump_unconfirmed') == 10
    assert node._mocap_warned == {'interleaved'}
    wall.t += 0.005
    subs[MOCAP](pose(0.01, wall.t, frame='vicon'))
    assert node.diag.get('mocap_rejected_other_source') == 1 and node._mocap_warned == {'interleaved'}
