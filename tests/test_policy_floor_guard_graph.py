"""policy_node's rules in a real graph, as plumbing: the floor guard reads depth images (32FC1, 16UC1, big-endian
16UC1) and climbs out on /cmd_vel and /assist/agent_cmd, counted on /diagnostics and turned off at run time; the
pilot override acts on a held key; every rule switch and sub-rule parameter reaches the running core; depth
frames are posed by their stamps and old or future inputs are refused. What each rule computes (override's
pushes, the pad recall and its scout, the damper, the wall rule) is pinned through PolicyCore, the core this
node runs, by the rules' own tests (assist_lab/test/test_policy_{override,recall,damper,walls}.py)."""
import threading
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from sensor_msgs.msg import Image
from std_msgs.msg import Float32MultiArray

from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS
from assist_policy.testing import LATENT, constant_actor

pytestmark = pytest.mark.graph

ALT = 0.8                      # odom z: low over the floor
FLOOR_DEPTH = ALT - 0.05       # camera 5 cm below base_link


def depth_msg(encoding: str, depth: np.ndarray | None = None) -> Image:
    """A 64x64 depth image (default: bare floor FLOOR_DEPTH away), as the sim (32FC1 m) or a RealSense (16UC1 mm)."""
    depth = np.full((64, 64), FLOOR_DEPTH, np.float32) if depth is None else depth.astype(np.float32)
    m = Image()
    m.height = m.width = 64
    m.encoding = encoding.removesuffix('be')          # '16UC1be': a big-endian 16UC1 image (is_bigendian set)
    m.is_bigendian = int(encoding.endswith('be'))
    if encoding == '32FC1':
        m.step, m.data = 64 * 4, depth.tobytes()
    else:
        m.step, m.data = 64 * 2, np.round(depth * 1000).astype('>u2' if m.is_bigendian else '<u2').tobytes()
    return m


class Probe:
    """Publishes odom, a descending pilot, the latent and depth; records cmd_vel, agent_cmd, diagnostics."""

    def __init__(self, node, pilot=(0.0, 0.0, -0.5)):
        self.node, self.lock, self.pilot = node, threading.Lock(), pilot
        self.velocity = (0.0, 0.0, 0.0)                  # odometry twist (base_link)
        self.cmd, self.agent, self.diag = [], [], []
        node.create_subscription(TwistStamped, '/cmd_vel', self._rec(self.cmd), RELIABLE_QOS)
        node.create_subscription(TwistStamped, '/assist/agent_cmd', self._rec(self.agent), RELIABLE_QOS)
        node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        self.pub_odom = node.create_publisher(Odometry, '/odom', SENSOR_QOS)
        self.pub_pilot = node.create_publisher(TwistStamped, '/pilot/cmd_vel', RELIABLE_QOS)
        self.pub_latent = node.create_publisher(Float32MultiArray, '/assist/latent', SENSOR_QOS)
        self.pub_depth = node.create_publisher(Image, '/camera/depth/image_raw', SENSOR_QOS)

    def _rec(self, store):
        def cb(msg):
            with self.lock:
                store.append((time.monotonic(), np.array([msg.twist.linear.x, msg.twist.linear.y,
                                                          msg.twist.linear.z])))
        return cb

    def _on_diag(self, msg):
        for st in msg.status:
            if 'policy_node' in st.name:
                with self.lock:
                    self.diag.append({kv.key: kv.value for kv in st.values})

    def since(self, store, t0):
        with self.lock:
            return [v for t, v in store if t >= t0]

    def until_first(self, store, node, limit_s=40.0, **inputs):
        """Publish the inputs (`run`'s keywords) until `store` records a message, the node exits or limit_s; it runs."""
        t0 = time.monotonic()
        while not self.since(store, t0) and time.monotonic() - t0 < limit_s and node.proc.poll() is None:
            self.run(0.2, **inputs)
        assert node.proc.poll() is None, node.log()

    def run(self, seconds, encoding='32FC1', position=(0.0, 0.0, ALT), depth=None, stamps=None):
        """Publish for `seconds`; `stamps(now_ns)` -> (odom, depth) header stamps in ns (default: none set)."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            od = Odometry()
            dm = depth_msg(encoding, depth)
            if stamps is not None:
                for msg, ns in zip((od, dm), stamps(self.node.get_clock().now().nanoseconds)):
                    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(ns), 1_000_000_000)
            od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z = position
            od.twist.twist.linear.x, od.twist.twist.linear.y, od.twist.twist.linear.z = self.velocity
            self.pub_odom.publish(od)
            tw = TwistStamped()
            tw.twist.linear.x, tw.twist.linear.y, tw.twist.linear.z = self.pilot
            self.pub_pilot.publish(tw)
            self.pub_latent.publish(Float32MultiArray(data=[0.0] * LATENT))
            self.pub_depth.publish(dm)
            time.sleep(0.05)
        return t0


def set_param(node, name, value: bool | float, wait):
    cli = node.create_client(SetParameters, '/policy_node/set_parameters')
    assert cli.wait_for_service(timeout_sec=20)
    req = SetParameters.Request()
    pv = (ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value) if isinstance(value, bool)
          else ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(value)))
    req.parameters = [ParameterMsg(name=name, value=pv)]
    fut = cli.call_async(req)
    assert wait(lambda: fut.done(), 20)
    assert fut.result().results[0].successful
    node.destroy_client(cli)


def test_floor_guard_blocks_descent_over_floor_and_can_be_turned_off(ros, start_node, wait, tmp_path):
    model = constant_actor(tmp_path / 'relinquish.pt', [0.0, 0.0, 0.0])     # a = 0: V = u
    probe = Probe(ros)
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'pad_recall': False})
    probe.until_first(probe.agent, node)
    for enc in ('32FC1', '16UC1', '16UC1be'):         # a big-endian image reads as the same floor
        t1 = probe.run(1.5, enc)
        cmds, agents = probe.since(probe.cmd, t1 + 0.7), probe.since(probe.agent, t1 + 0.7)
        assert cmds and agents, node.log()
        # V = (u + a') / 2 with a' = (0, 0, 2 * 0.15 + 0.5): a 0.15 m/s climb instead of the 0.5 m/s descent
        assert all(np.allclose(v, [0, 0, 0.15], atol=1e-5) for v in cmds), (enc, cmds[-3:])
        assert all(np.allclose(a, [0, 0, 0.8], atol=1e-5) for a in agents), (enc, agents[-3:])
    assert wait(lambda: any(int(d.get('floor_guard_engaged', 0)) > 20 for d in probe.diag), 5), probe.diag[-1:]
    assert probe.diag[-1].get('floor_guard') == 'on'
    set_param(ros, 'floor_guard', False, wait)
    t2 = probe.run(1.5)
    cmds = probe.since(probe.cmd, t2 + 0.5)
    assert cmds and all(np.allclose(v, [0, 0, -0.5], atol=1e-5) for v in cmds)       # descent passes
    agents = probe.since(probe.agent, t2 + 0.5)
    assert agents and all(np.allclose(a, 0, atol=1e-6) for a in agents)               # the actor's a = 0 again
    assert wait(lambda: probe.diag and probe.diag[-1].get('floor_guard') == 'off', 5)


def test_every_rule_acts_in_the_node_and_its_switches_reach_the_running_core(ros, start_node, wait, tmp_path):
    """One node, the plumbing of every rule: the override acts on a held key and reports it, each switch and
    sub-rule parameter is taken at run time and shown on /diagnostics, a rule switched on at run time acts. What
    each rule computes is pinned through PolicyCore (the core this node runs) by the rules' own tests."""
    model = constant_actor(tmp_path / 'down.pt', [0.0, 0.0, -0.9])        # the actor pushes down
    probe = Probe(ros, pilot=(1.0, 0.0, 0.0))                                     # the pilot holds a key forward
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'floor_guard': False})
    probe.until_first(probe.agent, node)
    t1 = probe.run(2.0)
    cmds, agents = probe.since(probe.cmd, t1 + 1.2), probe.since(probe.agent, t1 + 1.2)
    assert cmds and agents, node.log()
    # a' = (u_x, u_y, 2 * 0.3 - u_z): V = (1, 0, 0.3), the key passes and the vehicle rises instead of descending
    assert all(np.allclose(v, [1.0, 0, 0.3], atol=1e-5) for v in cmds), cmds[-3:]
    assert all(np.allclose(a, [1.0, 0, 0.6], atol=1e-5) for a in agents), agents[-3:]
    assert wait(lambda: any(int(d.get('pilot_override_engaged', 0)) > 10 for d in probe.diag), 5), probe.diag[-1:]
    last = probe.diag[-1]
    assert (last.get('floor_guard'), last.get('pilot_override'), last.get('pad_recall'),
            last.get('oscillation_damper')) == ('off', 'on', 'on', 'on'), last
    for name, value in (('pilot_override', False), ('pad_recall', False), ('oscillation_damper', False),
                        ('pilot_override_persist_s', 0.0), ('pilot_override_long_push_s', 0.0),
                        ('pad_recall_scout_max_m', 0.0), ('floor_guard_wall_radius_m', 0.0)):
        set_param(ros, name, value, wait)
    t2 = probe.run(1.5)
    cmds = probe.since(probe.cmd, t2 + 0.5)
    assert cmds and all(np.allclose(v, [0.5, 0, -0.27], atol=1e-5) for v in cmds), cmds[-3:]   # blend(u, a)
    assert wait(lambda: probe.diag and (probe.diag[-1].get('pilot_override'), probe.diag[-1].get('pad_recall'),
                                        probe.diag[-1].get('oscillation_damper')) == ('off', 'off', 'off'), 5)
    set_param(ros, 'floor_guard', True, wait)                # low over the floor: the descent becomes a climb
    t3 = probe.run(1.5)
    cmds = probe.since(probe.cmd, t3 + 0.7)
    assert cmds and all(np.allclose(v, [0.5, 0, 0.15], atol=1e-5) for v in cmds), cmds[-3:]
    assert wait(lambda: any(int(d.get('floor_guard_engaged', 0)) > 10 for d in probe.diag), 5), probe.diag[-1:]


def test_depth_frames_are_posed_by_their_header_stamps(ros, start_node, wait, tmp_path):
    """Stamped /odom and depth on one clock (the frame 25 ms old, odometry every >= 50 ms): every frame finds its
    pose (interpolated between the two around it); a frame no odometry stamp lies near (odometry 0.4 s behind: old
    but not stale) finds none and is counted (mapped from the latest odometry); depth_pose_match_s at run time.
    (A stamp of another clock is refused as stale or from the future before any lookup: rejected_depth_*.)"""
    model = constant_actor(tmp_path / 'still.pt', [0.0, 0.0, 0.0])
    probe = Probe(ros)
    # odometry 0.4 s old must stay "old but not stale" however late a loaded machine runs the node's tick
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'odom_timeout_s': 2.0})
    pad = np.full((64, 64), 3.0 - 0.05, np.float32)
    pad[22:42, 22:42] = 3.0 - 0.05 - 0.8
    same_clock = lambda now: (now, now - 25_000_000)          # noqa: E731
    probe.until_first(probe.cmd, node, position=(0.0, 0.0, 3.0), depth=pad, stamps=same_clock)
    probe.run(1.0, position=(0.0, 0.0, 3.0), depth=pad, stamps=same_clock)
    assert wait(lambda: probe.diag and probe.diag[-1].get('pad_recall_pads') == '1', 5), probe.diag[-1:]
    assert probe.diag[-1].get('depth_pose_unmatched') == '0'
    probe.run(1.0, position=(0.0, 0.0, 3.0), depth=pad, stamps=lambda now: (now - 400_000_000, now))
    assert wait(lambda: int(probe.diag[-1].get('depth_pose_unmatched', 0)) >= 5, 5), probe.diag[-1:]
    set_param(ros, 'depth_pose_match_s', 0.01, wait)        # >= 25 ms from either sample: counted too
    seen = int(probe.diag[-1]['depth_pose_unmatched'])
    probe.run(1.0, position=(0.0, 0.0, 3.0), depth=pad, stamps=same_clock)
    assert wait(lambda: int(probe.diag[-1].get('depth_pose_unmatched', 0)) >= seen + 5, 5), probe.diag[-1:]


def test_policy_node_dates_inputs_by_their_stamps_and_rejects_old_and_future_ones(ros, start_node, wait, tmp_path):
    model = constant_actor(tmp_path / 'relinquish.pt', [0.0, 0.0, 0.0])     # a = 0: V = u
    probe = Probe(ros)
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'pad_recall': False})
    now = lambda ns: (ns, ns)                                                       # noqa: E731
    probe.until_first(probe.agent, node, stamps=now)
    t1 = probe.run(1.5, stamps=now)                   # stamped now: the floor guard holds the descent
    assert all(np.allclose(v, [0, 0, 0.15], atol=1e-5) for v in probe.since(probe.cmd, t1 + 0.7))
    for offset_s, reason in ((-60.0, 'stale_stamp'), (60.0, 'future_stamp')):
        shifted = lambda ns, o=offset_s: (ns + int(o * 1e9),) * 2                  # noqa: E731
        t2 = probe.run(1.5, stamps=shifted)
        cmds = probe.since(probe.cmd, t2 + 0.8)
        # odometry and depth refused: no pose to guard by, the assistant relinquishes (V = u, the descent passes)
        assert cmds and all(np.allclose(v, [0, 0, -0.5], atol=1e-5) for v in cmds), (reason, cmds[-3:])
        assert wait(lambda r=reason: any(int(d.get(f'rejected_odom_{r}', 0)) > 0
                                         and int(d.get(f'rejected_depth_{r}', 0)) > 0 for d in probe.diag), 5), \
            probe.diag[-1:]
        assert node.proc.poll() is None
