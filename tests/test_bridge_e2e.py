"""End to end over UDP loopback: sim_node as the MAVLink vehicle + mavlink_bridge_node in a real graph."""
import math
import socket
import threading
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import Log, Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS, fill_twist
from assist_common.mavlink_io import mavlink
from assist_sim.testing import SilentAutopilot, free_udp_port

pytestmark = [pytest.mark.graph, pytest.mark.slow(seconds=60)]
# /rosout keeps the last 1000 lines for late joiners (transient local, 10 s lifespan): events logged
# before this probe matched still arrive
ROSOUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


class BridgeProbe:
    """Test-side view of the bridge: /odom, its /diagnostics, /cmd_vel publisher, /uav/* clients."""

    def __init__(self, node):
        self.node = node
        self.lock = threading.Lock()
        self.odom: list[Odometry] = []
        self.diag: dict[str, str] = {}
        self.rosout: list[Log] = []
        self.subs = [node.create_subscription(Odometry, '/odom', self._on_odom, SENSOR_QOS),
                     node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10),
                     node.create_subscription(Log, '/rosout', self._on_rosout, ROSOUT_QOS)]
        self.cmd = node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
        self.clients = {n: node.create_client(Trigger, f'/uav/{n}', qos_profile=QoSProfile(depth=100))
                        for n in ('arm', 'takeoff', 'land', 'disarm', 'guided')}
        self.answered: set[str] = set()

    def _on_odom(self, msg):
        with self.lock:
            self.odom.append(msg)

    def _on_rosout(self, msg):
        if msg.name.startswith('mavlink_bridge_node'):   # the node's logger or a child of it
            with self.lock:
                self.rosout.append(msg)

    def rosout_lines(self, text: str) -> list[Log]:
        with self.lock:
            return [m for m in self.rosout if text in m.msg]

    def _on_diag(self, msg):
        for st in msg.status:
            if st.name.endswith('mavlink_bridge_node'):
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in st.values}

    def pos(self) -> np.ndarray | None:
        with self.lock:
            if not self.odom:
                return None
            p = self.odom[-1].pose.pose.position
            return np.array([p.x, p.y, p.z])

    def vel(self) -> np.ndarray:
        with self.lock:
            v = self.odom[-1].twist.twist.linear
            return np.array([v.x, v.y, v.z])

    def n_odom(self) -> int:
        with self.lock:
            return len(self.odom)

    def diag_value(self, key):
        with self.lock:
            return self.diag.get(key)

    def call(self, name: str, timeout: float = 15.0):
        """Call /uav/<name>; a client's first call is retried once if its answer never came.

        wait_for_service sees the server's request reader, not that the server has matched this
        client's response reader yet: a first answer can be lost while DDS is still matching
        (seen in CI: the very first /uav/takeoff of a test never answered). Later calls are not
        retried, so a vehicle command is never sent twice once the pair is known to work.
        """
        client = self.clients[name]
        assert client.wait_for_service(timeout_sec=timeout), f'/uav/{name} not available'
        tries = 1 if name in self.answered else 2
        for attempt in range(tries):
            fut = client.call_async(Trigger.Request())
            end = time.monotonic() + (timeout if attempt == tries - 1 else 5.0)
            while not fut.done() and time.monotonic() < end:
                time.sleep(0.02)
            if fut.done():
                self.answered.add(name)
                return fut.result()
            client.remove_pending_request(fut)
        raise AssertionError(f'/uav/{name} did not answer')

    def send(self, v):
        msg = TwistStamped()
        msg.header.frame_id = 'base_link'
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.cmd.publish(fill_twist(msg, v))

    def close(self):
        for s in self.subs:
            self.node.destroy_subscription(s)
        self.node.destroy_publisher(self.cmd)
        for c in self.clients.values():
            self.node.destroy_client(c)


@pytest.fixture
def rig(ros, start_node):
    port = free_udp_port()
    sim_params = {'mavlink_url': f'udpout:127.0.0.1:{port}', 'camera_rate_hz': 0.0, 'seed': 5,
                  'auto_reset': False}
    sim = start_node('sim_node', sim_params)
    # 3 s: two missed 1 Hz heartbeats (1.5 s tripped on one late heartbeat on a loaded CI machine)
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}', 'link_timeout_s': 3.0})
    probe = BridgeProbe(ros)
    yield probe, sim, bridge, port, sim_params
    probe.close()


def arm_when_ready(probe, wait):
    """Arm; before the EKF is ready the refusal must say why (PreArm / requires position)."""
    assert wait(lambda: probe.diag_value('link') == 'up', 90.0), 'bridge never saw the vehicle'
    for _ in range(20):
        res = probe.call('arm')
        if res.success:
            return res
        assert 'PreArm' in res.message or 'requires position' in res.message, res.message
        time.sleep(0.5)
    raise AssertionError('never armed')


def test_arm_takeoff_fly_stop_land_disarm(rig, wait):
    probe, sim, bridge, _, _ = rig
    res = probe.call('takeoff')                # disarmed: refused, honestly
    assert not res.success and ('FAILED' in res.message or 'no link' in res.message), res.message
    arm_when_ready(probe, wait)
    assert wait(lambda: probe.pos() is not None, 10.0), 'no /odom from the bridge'
    ground = probe.pos()
    assert ground[2] < 0.3                      # starts landed
    res = probe.call('takeoff')
    assert res.success, res.message
    assert wait(lambda: probe.pos()[2] > ground[2] + 1.8, 40.0), f'no climb: {probe.pos()}'
    # the bridge holds velocity setpoints back until it has seen the takeoff complete
    assert wait(lambda: 'takeoff complete' in bridge.log(), 20.0), bridge.log()[-2000:]
    time.sleep(0.5)
    p0 = probe.pos()
    end = time.monotonic() + 2.0
    while time.monotonic() < end:              # forward (FLU +x) 1 m/s, left 0.3 m/s at 20 Hz
        probe.send([1.0, 0.3, 0.0])
        time.sleep(0.05)
    p1 = probe.pos()
    d = p1 - p0
    assert d[0] > 0.8, f'did not fly forward (+x ENU): {d}'
    assert 0.05 < d[1] < 0.9, f'left is +y ENU: {d}'
    assert abs(d[2]) < 0.4
    assert probe.vel()[0] > 0.4                 # body-frame twist forward
    # command timeout: the bridge sends zero velocity and the vehicle stops
    assert wait(lambda: np.linalg.norm(probe.vel()) < 0.15, 15.0), f'did not stop: {probe.vel()}'
    p2 = probe.pos()
    time.sleep(1.0)
    assert np.linalg.norm(probe.pos()[:2] - p2[:2]) < 0.3
    res = probe.call('land')
    assert res.success, res.message
    assert wait(lambda: probe.pos()[2] < ground[2] + 0.05, 40.0), f'did not land: {probe.pos()}'
    assert wait(lambda: probe.diag_value('armed') == 'False', 10.0), 'not disarmed after landing'
    assert sim.proc.poll() is None and bridge.proc.poll() is None
    # vehicle events reach /rosout through the node logger, stamped
    # 'mode GUIDED': a mode change is logged as 'vehicle mode GUIDED (was ...)', or inside the
    # 'MAVLink link up ... mode GUIDED' line when it happened while the link was down
    for text in ('MAVLink link up', 'mode GUIDED', 'takeoff complete', 'vehicle mode LAND',
                 'vehicle disarmed'):
        lines = probe.rosout_lines(text)
        assert lines, f'{text!r} not on /rosout: {[m.msg for m in probe.rosout]}'
        assert lines[0].stamp.sec > 0 and lines[0].level >= Log.INFO


def test_link_loss_reported_and_recovered(rig, wait, start_node):
    probe, sim, bridge, port, sim_params = rig
    arm_when_ready(probe, wait)
    assert probe.call('takeoff').success
    assert wait(lambda: probe.pos() is not None and probe.pos()[2] > 1.0, 60.0)
    sim.stop()                                  # the vehicle endpoint dies mid-flight
    assert wait(lambda: probe.diag_value('link') == 'lost', 30.0), 'link loss not reported'
    assert 'link lost' in bridge.log()
    res = probe.call('arm')
    assert not res.success and 'no link' in res.message
    n = probe.n_odom()
    start_node('sim_node', sim_params)           # it comes back
    assert wait(lambda: probe.diag_value('link') == 'up', 90.0), 'no recovery'
    assert wait(lambda: probe.n_odom() > n + 5, 60.0), 'telemetry not resumed after recovery'
    assert bridge.proc.poll() is None


def test_garbage_on_the_bridge_port(rig, wait):
    probe, sim, bridge, port, _ = rig
    assert wait(lambda: probe.diag_value('link') == 'up', 90.0)
    rng = np.random.default_rng(11)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    payloads = [rng.bytes(int(n)) for n in rng.integers(1, 2000, 300)]
    payloads += [b'\xfd\x09\x00\x00\x00\x01\x01\x00\x00', b'\xfe' * 10000, rng.bytes(65000),
                 bytes([0xfd, 0xff]) + rng.bytes(30), b'']
    for i, pl in enumerate(payloads):
        s.sendto(pl, ('127.0.0.1', port))
        if i % 20 == 19:
            time.sleep(0.005)     # all at once would overflow the bridge socket's receive buffer
    s.close()
    time.sleep(1.0)
    assert bridge.proc.poll() is None, bridge.log()
    # the bridge is locked onto the vehicle's address: datagrams from anywhere else are dropped unparsed
    assert wait(lambda: int(probe.diag_value('rx_foreign_address') or 0) >= 100, 30.0)
    assert probe.diag_value('link') == 'up'
    arm_when_ready(probe, wait)                 # and it still commands the vehicle
    assert int(probe.diag_value('loop_errors') or 0) == 0


def test_cmd_vel_flows_while_a_service_waits_for_its_ack(ros, start_node, wait):
    """The services wait for COMMAND_ACK off the executor: /cmd_vel keeps reaching the vehicle meanwhile."""
    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}', 'ack_timeout_s': 6.0})
    vehicle = SilentAutopilot(port)               # heading north: FLU x = NED vx
    probe = BridgeProbe(ros)
    try:
        assert wait(lambda: probe.diag_value('link') == 'up', 60.0), bridge.log()
        # /cmd_vel must be matched (DDS discovery) before the timed part, or early commands are lost
        assert wait(lambda: probe.cmd.get_subscription_count() > 0, 30.0), 'bridge never subscribed /cmd_vel'
        client = probe.clients['disarm']
        assert client.wait_for_service(timeout_sec=15.0)
        def arrivals_of(vx: float) -> list[float]:
            return [t for t, v, _ in vehicle.setpoints() if abs(v - vx) < 1e-4]
        t_call = time.time()                       # the autopilot stamps arrivals with CLOCK_REALTIME
        fut = client.call_async(Trigger.Request())
        assert wait(lambda: vehicle.commands(), 5.0), 'the disarm command never went out'
        # the service is now waiting for an ACK that never comes; commands must still flow
        sent_at = time.monotonic()
        deadline = sent_at + 4.0
        while time.monotonic() < deadline and not arrivals_of(0.37):
            probe.send([0.37, 0.0, 0.0])
            time.sleep(0.05)
        arrivals = arrivals_of(0.37)
        assert arrivals, (f'no setpoint for /cmd_vel while the service waited: {vehicle.setpoints()[-5:]} '
                          f'{bridge.log()[-1500:]}')
        assert not fut.done(), 'the service answered before its ACK timeout'
        assert wait(fut.done, 10.0), 'service never answered'
        res = fut.result()
        assert not res.success and 'no COMMAND_ACK within 6.0 s' in res.message, res.message
        assert arrivals[0] < t_call + 6.0 and time.time() - t_call >= 6.0
        assert bridge.proc.poll() is None
    finally:
        probe.close()
        vehicle.close()


def _set_param(node, name: str, value) -> tuple[bool, str]:
    """`ros2 param set` from the probe: (successful, reason)."""
    client = node.create_client(SetParameters, '/mavlink_bridge_node/set_parameters')
    try:
        assert client.wait_for_service(timeout_sec=20.0)
        pv = ParameterValue()
        if isinstance(value, float):
            pv.type, pv.double_value = ParameterType.PARAMETER_DOUBLE, value
        else:
            pv.type, pv.integer_value = ParameterType.PARAMETER_INTEGER, value
        fut = client.call_async(SetParameters.Request(parameters=[Parameter(name=name, value=pv)]))
        end = time.monotonic() + 10.0
        while not fut.done() and time.monotonic() < end:
            time.sleep(0.02)
        res = fut.result().results[0]
        return res.successful, res.reason
    finally:
        node.destroy_client(client)


def test_parameters_ranges_runtime_sets_and_startup_refusals(ros, start_node, wait):
    """Speed limits change at run time (validated); other parameters are read-only; bad values stop the start."""
    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}'})
    vehicle = SilentAutopilot(port)               # heading north: FLU x = NED vx
    probe = BridgeProbe(ros)
    try:
        assert wait(lambda: probe.diag_value('link') == 'up', 60.0), bridge.log()
        assert wait(lambda: probe.cmd.get_subscription_count() > 0, 30.0)
        assert _set_param(ros, 'velocity_scale', 0.5) == (True, '')
        assert wait(lambda: (probe.send([1.0, 0.0, 0.0]) or True) and any(
            abs(vx - 0.5) < 1e-6 for _, vx, _ in vehicle.setpoints()), 10.0), 'velocity_scale 0.5 not applied'
        ok, reason = _set_param(ros, 'velocity_scale', -1.0)
        assert not ok and 'velocity_scale' in reason
        ok, reason = _set_param(ros, 'max_speed_mps', 2)   # an integer for a float is accepted
        assert ok, reason
        ok, reason = _set_param(ros, 'setpoint_rate_hz', 20.0)
        assert not ok, 'a read-only parameter was accepted'
        assert bridge.proc.poll() is None
    finally:
        probe.close()
        vehicle.close()
    refused = [(start_node('mavlink_bridge_node', params), words)      # started together: each must refuse alone
               for params, words in (({'velocity_scale': 2.0}, "'velocity_scale' must be"),
                                     ({'connection': '/usr/bin/python3'}, 'serial device'),
                                     ({'connection': 'udp:0.0.0.0:14550'}, 'unsupported MAVLink endpoint'),
                                     ({'setpoint_rate_hz': -1.0}, "'setpoint_rate_hz' must be"),
                                     ({'auto_guided': True}, 'auto_guided was removed'))]
    for node, words in refused:
        assert node.proc.wait(60) == 1, node.log()
        errors = [line for line in node.log().splitlines() if line.startswith('error:')]
        assert len(errors) == 1 and words in errors[0], node.log()
        assert 'Traceback' not in node.log()


def test_every_service_request_is_answered(ros, start_node, wait):
    """50 calls at once: up to max_pending_commands wait for the vehicle, the rest are told 'busy' at once."""
    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}', 'ack_timeout_s': 1.0,
                                                'max_pending_commands': 4})
    vehicle = SilentAutopilot(port)               # never ACKs: each command waits ack_timeout_s
    probe = BridgeProbe(ros)
    try:
        assert wait(lambda: probe.diag_value('link') == 'up', 60.0), bridge.log()
        client = probe.clients['guided']
        assert client.wait_for_service(timeout_sec=15.0)
        t0 = time.monotonic()
        futs = [client.call_async(Trigger.Request()) for _ in range(50)]
        assert wait(lambda: all(f.done() for f in futs), 30.0), \
            f'{sum(f.done() for f in futs)}/50 answered; {bridge.log()[-1500:]}'
        elapsed = time.monotonic() - t0
        msgs = [f.result().message for f in futs]
        busy = [m for m in msgs if 'busy' in m]
        waited = [m for m in msgs if 'no COMMAND_ACK within 1.0 s' in m]
        assert len(busy) + len(waited) == 50 and 1 <= len(waited) <= 5 + 4, msgs
        assert not any(f.result().success for f in futs)
        assert elapsed < 20.0
        assert bridge.proc.poll() is None
    finally:
        probe.close()
        vehicle.close()


def test_signed_link_end_to_end(ros, start_node, wait, tmp_path):
    """sim_node and the bridge share a signing key file: the flight works; the key is refused if world-readable."""
    key = tmp_path / 'mavlink.key'
    key.write_text(bytes(range(40, 72)).hex() + '\n')
    key.chmod(0o644)
    port = free_udp_port()
    refused = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}',
                                                 'signing_key_file': str(key)})
    assert refused.proc.wait(30) == 1 and 'chmod 600' in refused.log(), refused.log()
    key.chmod(0o600)
    sim = start_node('sim_node', {'mavlink_url': f'udpout:127.0.0.1:{port}', 'camera_rate_hz': 0.0, 'seed': 5,
                                  'auto_reset': False, 'mavlink_signing_key_file': str(key)})
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}',
                                                'signing_key_file': str(key)})
    probe = BridgeProbe(ros)
    try:
        arm_when_ready(probe, wait)
        assert probe.diag_value('signing') == 'True'
        assert probe.call('takeoff').success
        assert wait(lambda: probe.pos() is not None and probe.pos()[2] > 1.0, 60.0), 'no climb on the signed link'
        # an unsigned sender on the vehicle's host gets nowhere
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        m = mavlink.MAVLink(None, 1, 1)
        for _ in range(5):
            s.sendto(m.heartbeat_encode(2, 3, 0, 9, 3).pack(m), ('127.0.0.1', port))
        s.close()
        time.sleep(1.5)
        assert probe.diag_value('mode') == 'GUIDED'
        assert sim.proc.poll() is None and bridge.proc.poll() is None
    finally:
        probe.close()


def test_mocap_poses_reach_the_autopilot_as_vision_estimates(ros, start_node, wait):
    """PoseStamped (ENU) on mocap_topic -> VISION_POSITION_ESTIMATE (NED) at vision_rate_hz with the pose's
    stamp; SET_GPS_GLOBAL_ORIGIN once the link is up; stale poses are refused and never sent."""
    from geometry_msgs.msg import PoseStamped
    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}', 'mocap_topic': '/mocap/pose',
                                                'vision_rate_hz': 20.0, 'ekf_origin': [47.3977, 8.5456, 488.0]})
    vehicle = SilentAutopilot(port)
    probe = BridgeProbe(ros)
    pub = ros.create_publisher(PoseStamped, '/mocap/pose', SENSOR_QOS)
    try:
        assert wait(lambda: probe.diag_value('link') == 'up', 60.0), bridge.log()
        assert wait(lambda: pub.get_subscription_count() > 0, 30.0), 'bridge never subscribed the mocap topic'
        assert wait(lambda: vehicle.received('SET_GPS_GLOBAL_ORIGIN'), 10.0), bridge.log()[-2000:]
        origin = vehicle.received('SET_GPS_GLOBAL_ORIGIN')[0][1]
        assert (origin.latitude, origin.longitude, origin.altitude) == (473977000, 85456000, 488000)
        stamps = set()

        def pose(stamp_s: float) -> PoseStamped:
            m = PoseStamped()
            m.header.frame_id = 'mocap'
            m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_s * 1e9), 1_000_000_000)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = 1.0, 2.0, 0.5   # 1 m east, 2 m north
            m.pose.orientation.z, m.pose.orientation.w = math.sin(math.pi / 4), math.cos(math.pi / 4)  # north
            return m
        t0 = time.monotonic()
        while time.monotonic() - t0 < 2.0:        # a 100 Hz mocap for 2 s
            now = time.time()
            stamps.add(round(now * 1e6))
            pub.publish(pose(now))
            time.sleep(0.01)
        assert wait(lambda: len(vehicle.received('VISION_POSITION_ESTIMATE')) >= 20, 10.0), bridge.log()[-2000:]
        got = [m for _, m in vehicle.received('VISION_POSITION_ESTIMATE')]
        assert len(got) <= 2.0 * 20 + 3                       # paced at vision_rate_hz, not the mocap's 100 Hz
        m = got[-1]
        assert (m.x, m.y, m.z) == pytest.approx((2.0, 1.0, -0.5), abs=1e-5)
        assert abs(m.yaw) < 1e-5 and abs(m.roll) < 1e-5 and abs(m.pitch) < 1e-5
        assert all(abs(g.usec - min(stamps, key=lambda s: abs(s - g.usec))) <= 1 for g in got)
        assert m.covariance[0] == pytest.approx(1e-4) and m.reset_counter == 0
        # stale poses (a mocap stream 1 s behind) are refused and counted; nothing more is sent
        n = len(vehicle.received('VISION_POSITION_ESTIMATE'))
        for _ in range(30):
            pub.publish(pose(time.time() - 1.0))
            time.sleep(0.01)
        assert wait(lambda: int(probe.diag_value('mocap_rejected_stale') or 0) >= 10, 10.0), probe.diag
        time.sleep(0.5)
        assert len(vehicle.received('VISION_POSITION_ESTIMATE')) <= n + 1      # at most the last good one
        assert bridge.proc.poll() is None
    finally:
        probe.close()
        vehicle.close()
