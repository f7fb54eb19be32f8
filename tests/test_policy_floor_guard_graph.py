"""policy_node's floor guard in a real graph: depth image in (32FC1 and 16UC1), climb out on /cmd_vel and
/assist/agent_cmd, counted on /diagnostics, turned off at run time with the floor_guard parameter; and its
pilot override (a held key passes with a gentle climb; the pilot_override parameter turns it off; a persistent
push passes while descending, pilot_override_persist_s 0 turns that off; a slower long push passes over
a pad, pilot_override_long_push_s 0 turns that off); and its
pad recall (a pad seen, then a descent past it over bare floor is steered back, and low over it centred on
it; farther past it, it first looks beyond, pad_recall_scout_max_m 0 turns that off; pad_recall turns it
off); and its oscillation damper (a pilot swinging back and forth is slowed; oscillation_damper turns it
off); and the floor guard's wall rule (no command toward a wall in view; floor_guard_wall_radius_m 0 turns it
off)."""
import importlib.util
import threading
import time
from pathlib import Path

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

from assist_common.ros_common import RELIABLE_QOS, SENSOR_QOS

pytestmark = pytest.mark.graph

_spec = importlib.util.spec_from_file_location(
    'policy_core_helpers', Path(__file__).resolve().parents[1]
    / 'ros2_ws/src/assist_policy/test/test_policy_core.py')
_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_helpers)
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
            self.pub_latent.publish(Float32MultiArray(data=[0.0] * _helpers.LATENT))
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
    model = _helpers.constant_actor(tmp_path / 'relinquish.pt', [0.0, 0.0, 0.0])     # a = 0: V = u
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


def test_pilot_override_passes_a_held_key_and_can_be_turned_off(ros, start_node, wait, tmp_path):
    model = _helpers.constant_actor(tmp_path / 'down.pt', [0.0, 0.0, -0.9])        # the actor pushes down
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
    assert probe.diag[-1].get('pilot_override') == 'on'
    set_param(ros, 'pilot_override', False, wait)
    t2 = probe.run(1.5)
    cmds = probe.since(probe.cmd, t2 + 0.5)
    assert cmds and all(np.allclose(v, [0.5, 0, -0.27], atol=1e-5) for v in cmds), cmds[-3:]   # blend(u, a)
    assert wait(lambda: probe.diag and probe.diag[-1].get('pilot_override') == 'off', 5)


def test_pilot_override_passes_a_persistent_push_while_descending_and_can_be_turned_off(ros, start_node, wait,
                                                                                       tmp_path):
    model = _helpers.constant_actor(tmp_path / 'back.pt', [-0.9, 0.0, 0.0])        # the actor holds the pilot back
    probe = Probe(ros, pilot=(0.7, 0.0, -0.3))               # an analog stick: on and down along a glide path
    # the probe's vehicle stands still under a descending command: flight boundaries off, or it counts as landed
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'flight_boundaries': False})
    high = (0.0, 0.0, 3.0)
    floor = np.full((64, 64), 3.0 - 0.05, np.float32)       # bare floor 3 m below
    probe.until_first(probe.agent, node, position=high, depth=floor)
    t1 = probe.run(3.5, position=high, depth=floor)
    cmds, agents = probe.since(probe.cmd, t1 + 2.6), probe.since(probe.agent, t1 + 2.6)
    assert cmds and agents, node.log()
    # 3 m up the yield relinquishes: a' = 0, V = u (the actor alone gave V = (-0.1, 0, -0.15))
    assert all(np.allclose(v, [0.7, 0, -0.3], atol=1e-5) for v in cmds), cmds[-3:]
    assert all(np.allclose(a, 0.0, atol=1e-6) for a in agents), agents[-3:]
    assert wait(lambda: any(int(d.get('pilot_override_persistent_engaged', 0)) > 10 for d in probe.diag), 5), \
        probe.diag[-1:]
    set_param(ros, 'pilot_override_persist_s', 0.0, wait)
    t2 = probe.run(1.5, position=high, depth=floor)
    cmds = probe.since(probe.cmd, t2 + 0.5)
    assert cmds and all(np.allclose(v, [-0.1, 0, -0.15], atol=1e-5) for v in cmds), cmds[-3:]   # blend(u, a)


def test_pilot_override_passes_a_long_push_over_a_pad_and_can_be_turned_off(ros, start_node, wait, tmp_path):
    model = _helpers.constant_actor(tmp_path / 'back.pt', [-0.9, 0.0, 0.0])        # the actor holds the pilot back
    probe = Probe(ros, pilot=(0.45, 0.0, 0.0))              # a slow push on, level, 1 m over a pad's top
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0})
    low = (0.0, 0.0, 1.8)
    pad = np.full((64, 64), 1.0 - 0.05, np.float32)          # a 0.8 m pad top under the whole view
    probe.until_first(probe.agent, node, position=low, depth=pad)
    t1 = probe.run(7.0, position=low, depth=pad)
    early, late = probe.since(probe.cmd, t1 + 1.0), probe.since(probe.cmd, t1 + 6.0)
    assert early and late, node.log()
    # under 5 s (and slower than the persistent push's 0.6 m/s over a pad): the actor's V = (-0.225, 0, 0)
    assert np.allclose(early[0], [-0.225, 0, 0], atol=1e-5), early[:3]
    # then the long push: a' = (0.45, 0, 0.6), V = (0.45, 0, 0.3), on and rising gently
    assert all(np.allclose(v, [0.45, 0, 0.3], atol=1e-5) for v in late), late[-3:]
    assert wait(lambda: any(int(d.get('pilot_override_long_engaged', 0)) > 10 for d in probe.diag), 5), \
        probe.diag[-1:]
    assert int(probe.diag[-1].get('pilot_override_persistent_engaged', -1)) == 0
    set_param(ros, 'pilot_override_long_push_s', 0.0, wait)
    t2 = probe.run(1.5, position=low, depth=pad)
    cmds = probe.since(probe.cmd, t2 + 0.5)
    assert cmds and all(np.allclose(v, [-0.225, 0, 0], atol=1e-5) for v in cmds), cmds[-3:]   # blend(u, a)


def test_pad_recall_steers_a_descent_past_a_pad_back_and_can_be_turned_off(ros, start_node, wait, tmp_path):
    model = _helpers.constant_actor(tmp_path / 'relinquish.pt', [0.0, 0.0, 0.0])     # a = 0: V = u
    probe = Probe(ros)                                                               # the pilot descends
    # the probe moves its vehicle by jumps (and holds it still under a descent): flight boundaries off
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'flight_boundaries': False})
    pad = np.full((64, 64), 3.0 - 0.05, np.float32)                  # from 3 m: floor, and a 0.8 m pad below
    pad[22:42, 22:42] = 3.0 - 0.05 - 0.8
    probe.until_first(probe.cmd, node, position=(0.0, 0.0, 3.0), depth=pad)
    probe.run(0.5, position=(0.0, 0.0, 3.0), depth=pad)               # over the pad: mapped at (0, 0)
    # bare floor before moving: the first step at a new pose reads the depth image of the one before
    probe.run(0.3, position=(0.0, 0.0, 3.0), depth=np.full((64, 64), 3.0 - 0.05, np.float32))
    floor = np.full((64, 64), 2.5 - 0.05, np.float32)
    t1 = probe.run(1.5, position=(1.5, 0.0, 2.5), depth=floor)        # 1.5 m past it over bare floor
    cmds, agents = probe.since(probe.cmd, t1 + 0.5), probe.since(probe.agent, t1 + 0.5)
    assert cmds and agents, node.log()
    # a = (clip(2 * 4 * (0 - 1.5)), 0, 0) = (-1, 0, 0): V = (-0.5, 0, -0.25), back toward the pad, still descending
    assert all(np.allclose(a, [-1.0, 0, 0], atol=1e-5) for a in agents), agents[-3:]
    assert all(np.allclose(v, [-0.5, 0, -0.25], atol=1e-5) for v in cmds), cmds[-3:]
    assert wait(lambda: any(int(d.get('pad_recall_engaged', 0)) > 10 for d in probe.diag), 5), probe.diag[-1:]
    assert probe.diag[-1].get('pad_recall') == 'on' and probe.diag[-1].get('pad_recall_pads') == '1'
    # low over the pad (0.55 m over its top: it fills the view), 0.1 m off its centre: touchdown centring
    low = np.full((64, 64), 1.4 - 0.05 - 0.8, np.float32)
    probe.run(0.3, position=(0.1, 0.0, 1.4), depth=low)
    t3 = probe.run(1.5, position=(0.1, 0.0, 1.4), depth=low)
    cmds, agents = probe.since(probe.cmd, t3 + 0.5), probe.since(probe.agent, t3 + 0.5)
    # a = (2 * 4 * (0 - 0.1), 0, 0) = (-0.8, 0, 0): V = (-0.4, 0, -0.25), toward the centre seen from 3 m
    assert agents and all(np.allclose(a, [-0.8, 0, 0], atol=1e-5) for a in agents), agents[-3:]
    assert cmds and all(np.allclose(v, [-0.4, 0, -0.25], atol=1e-5) for v in cmds), cmds[-3:]
    assert wait(lambda: any(int(d.get('pad_recall_touchdown', 0)) > 10 for d in probe.diag), 5), probe.diag[-1:]
    # 2.4 m past it, 1.9 m up: the camera sees ~1 m on, a nearer pad could lie beyond: it looks (scout) first,
    # holding the height: a_x = 1 (clipped), V = (0.5, ., 0); pad_recall_scout_max_m 0: straight back
    beyond = np.full((64, 64), 1.9 - 0.05, np.float32)
    probe.run(0.3, position=(0.1, 0.0, 1.4), depth=beyond)          # (as above: read here, it shows no pad)
    probe.run(0.3, position=(2.4, 0.0, 1.9), depth=beyond)
    t4 = probe.run(1.5, position=(2.4, 0.0, 1.9), depth=beyond)
    cmds, agents = probe.since(probe.cmd, t4 + 0.5), probe.since(probe.agent, t4 + 0.5)
    assert agents and all(np.isclose(a[0], 1.0, atol=1e-5) for a in agents), agents[-3:]
    assert cmds and all(np.isclose(v[0], 0.5, atol=1e-5) and np.isclose(v[2], 0.0, atol=1e-5) for v in cmds), cmds[-3:]
    assert wait(lambda: any(int(d.get('pad_recall_scout', 0)) > 10 for d in probe.diag), 5), probe.diag[-1:]
    set_param(ros, 'pad_recall_scout_max_m', 0.0, wait)
    t5 = probe.run(1.5, position=(2.4, 0.0, 1.9), depth=beyond)
    cmds = probe.since(probe.cmd, t5 + 0.5)
    assert cmds and all(np.allclose(v, [-0.5, 0, -0.25], atol=1e-5) for v in cmds), cmds[-3:]
    set_param(ros, 'pad_recall', False, wait)
    t2 = probe.run(1.5, position=(1.5, 0.0, 2.5), depth=floor)
    cmds = probe.since(probe.cmd, t2 + 0.5)
    assert cmds and all(np.allclose(v, [0, 0, -0.5], atol=1e-5) for v in cmds), cmds[-3:]   # V = u again
    assert wait(lambda: probe.diag and probe.diag[-1].get('pad_recall') == 'off', 5)


def test_oscillation_damper_slows_a_pilot_swinging_across_a_pad_and_can_be_turned_off(ros, start_node, wait,
                                                                                      tmp_path):
    model = _helpers.constant_actor(tmp_path / 'relinquish.pt', [0.0, 0.0, 0.0])     # a = 0: V = u
    probe = Probe(ros, pilot=(1.0, 0.0, 0.0))
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'floor_guard': False, 'pilot_override': False})
    floor = np.full((64, 64), 3.0 - 0.05, np.float32)
    pad = floor.copy()
    pad[22:42, 22:42] = 3.0 - 0.05 - 0.8                              # a 0.8 m pad right below, seen whole
    probe.until_first(probe.cmd, node, position=(0.0, 0.0, 3.0), depth=floor)

    def swing(seconds, depth):
        """The pilot holds +x then -x keys, 1.5 s each, the vehicle moving 0.4 m/s with it (odometry at 0, 0)."""
        t = time.monotonic()
        while time.monotonic() - t < seconds:
            sign = 1.0 if int((time.monotonic() - t) / 1.5) % 2 == 0 else -1.0
            probe.pilot, probe.velocity = (sign, 0.0, 0.0), (0.4 * sign, 0.0, 0.0)
            probe.run(0.05, position=(0.0, 0.0, 3.0), depth=depth)
        return t
    t1 = swing(6.0, floor)                  # swinging over bare floor: no pad in the map, not damped
    cmds = probe.since(probe.cmd, t1 + 0.5)
    assert cmds and all(abs(abs(v[0]) - 1.0) < 1e-5 for v in cmds), cmds[-5:]
    t2 = swing(6.0, pad)                    # the same swings across a pad
    agents = probe.since(probe.agent, t2 + 1.0)
    assert agents, node.log()
    # a_xy = -2 v_xy = -0.8 sign: V_x = (u + a) / 2 = 0.1 sign instead of the held key's 1 m/s
    assert any(np.allclose(a, [-0.8, 0, 0], atol=1e-5) for a in agents), agents[-3:]
    assert all(abs(abs(a[0]) - 0.8) < 1e-5 and a[1] == 0 for a in agents), agents[-3:]
    cmds = probe.since(probe.cmd, t2 + 1.0)
    assert sum(abs(abs(v[0]) - 0.1) < 1e-5 for v in cmds) > 0.7 * len(cmds), cmds[-5:]
    assert wait(lambda: any(int(d.get('oscillation_damper_engaged', 0)) > 10 for d in probe.diag), 5), \
        probe.diag[-1:]
    assert probe.diag[-1].get('oscillation_damper') == 'on' and probe.diag[-1].get('pad_recall_pads') == '1'
    set_param(ros, 'oscillation_damper', False, wait)
    t3 = swing(3.0, pad)
    cmds = probe.since(probe.cmd, t3 + 0.5)
    assert cmds and sum(abs(abs(v[0]) - 1.0) < 1e-5 for v in cmds) > 0.7 * len(cmds), cmds[-5:]   # V = u again
    assert wait(lambda: probe.diag and probe.diag[-1].get('oscillation_damper') == 'off', 5)


def test_depth_frames_are_posed_by_their_header_stamps(ros, start_node, wait, tmp_path):
    """Stamped /odom and depth on one clock (the frame 25 ms old, odometry every >= 50 ms): every frame finds its
    pose (interpolated between the two around it); a frame no odometry stamp lies near (odometry 0.4 s behind: old
    but not stale) finds none and is counted (mapped from the latest odometry); depth_pose_match_s at run time.
    (A stamp of another clock is refused as stale or from the future before any lookup: rejected_depth_*.)"""
    model = _helpers.constant_actor(tmp_path / 'still.pt', [0.0, 0.0, 0.0])
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


def test_wall_rule_stops_an_approach_to_a_wall_in_view_and_can_be_turned_off(ros, start_node, wait, tmp_path):
    """A rendered frame 1.2 m from the room's end wall at 4.5 m: pilot and actor both head for the wall."""
    from assist_sim.core.scene import PadSpec, SceneSpec
    from assist_sim.core.world import LandingWorld
    pad = PadSpec(center=(5.0, 0.0), length=1.0, width=1.0, height=0.6, yaw=0.0, material=3)
    scene = SceneSpec(seed=0, pads=(pad,), floor_material=1, wall_material=2, start_position=(0.0, 0.0, 3.0))
    position = (scene.room_max[0] - 1.2, 0.0, 4.5)
    world = LandingWorld()
    try:
        world.reset(scene=scene)
        wall = world.render_from(list(position)).depth.copy()
    finally:
        world.close()
    assert wall.shape == (64, 64)
    model = _helpers.constant_actor(tmp_path / 'east.pt', [0.9, 0.0, 0.0])         # the actor pushes +x
    probe = Probe(ros, pilot=(1.0, 0.0, 0.0))
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0})
    probe.until_first(probe.cmd, node, position=position, depth=wall)
    t1 = probe.run(1.5, position=position, depth=wall)
    cmds, agents = probe.since(probe.cmd, t1 + 0.7), probe.since(probe.agent, t1 + 0.7)
    assert cmds and agents, node.log()
    assert all(v[0] <= 1e-6 for v in cmds), cmds[-3:]                  # no longer toward the wall (was 0.95 m/s)
    assert all(a[0] < -0.9 for a in agents), agents[-3:]                # a' = 2 V' - u shows it
    assert wait(lambda: any(int(d.get('wall_guard_engaged', 0)) > 10 for d in probe.diag), 5), probe.diag[-1:]
    set_param(ros, 'floor_guard_wall_radius_m', 0.0, wait)
    t2 = probe.run(1.5, position=position, depth=wall)
    cmds = probe.since(probe.cmd, t2 + 0.5)
    assert cmds and all(v[0] > 0.9 for v in cmds), cmds[-3:]           # radius 0: the wall rule is off


def test_policy_node_dates_inputs_by_their_stamps_and_rejects_old_and_future_ones(ros, start_node, wait, tmp_path):
    model = _helpers.constant_actor(tmp_path / 'relinquish.pt', [0.0, 0.0, 0.0])     # a = 0: V = u
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
