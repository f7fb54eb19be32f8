"""mavlink_bridge_node in a real graph: /uav/landed_state follows the vehicle (the sim's ArduCopter stand-in) through a
flight; mocap poses that do not fit MAVLink or come from two publishers neither end the node nor reach the EKF as
resets; an EKF origin it cannot send stops the start with one line."""
import math
import threading
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.qos import QoSProfile
from std_msgs.msg import UInt8
from std_srvs.srv import Trigger

from assist_common.mavlink_io import mavlink
from assist_common.ros_io import LATCHED_QOS, SENSOR_QOS
from assist_sim.testing import SilentAutopilot, VehicleThread, free_udp_port

pytestmark = pytest.mark.graph
ON_GROUND, IN_AIR, TAKEOFF, LANDING = (mavlink.MAV_LANDED_STATE_ON_GROUND, mavlink.MAV_LANDED_STATE_IN_AIR,
                                       mavlink.MAV_LANDED_STATE_TAKEOFF, mavlink.MAV_LANDED_STATE_LANDING)


class Probe:
    """/uav/landed_state (as a late, latched subscriber would see it), the bridge's /diagnostics, /uav/* calls."""

    def __init__(self, node):
        self.node = node
        self.lock = threading.Lock()
        self.states: list[int] = []
        self.diag: dict[str, str] = {}
        self.subs = [node.create_subscription(UInt8, '/uav/landed_state', self._on_state, LATCHED_QOS),
                     node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)]
        self.clients = {n: node.create_client(Trigger, f'/uav/{n}', qos_profile=QoSProfile(depth=100))
                        for n in ('arm', 'takeoff', 'land')}

    def _on_state(self, msg):
        with self.lock:
            self.states.append(int(msg.data))

    def _on_diag(self, msg):
        for st in msg.status:
            if st.name.endswith('mavlink_bridge_node'):
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in st.values}

    def seen(self) -> list[int]:
        with self.lock:
            return list(self.states)

    def value(self, key: str) -> str | None:
        with self.lock:
            return self.diag.get(key)

    def call(self, name: str, timeout: float = 15.0):
        client = self.clients[name]
        assert client.wait_for_service(timeout_sec=timeout), f'/uav/{name} not available'
        fut = client.call_async(Trigger.Request())
        end = time.monotonic() + timeout
        while not fut.done() and time.monotonic() < end:
            time.sleep(0.02)
        assert fut.done(), f'/uav/{name} did not answer'
        return fut.result()

    def close(self):
        for s in self.subs:
            self.node.destroy_subscription(s)
        for c in self.clients.values():
            self.node.destroy_client(c)


def test_landed_state_topic_follows_the_vehicle_through_a_flight(ros, start_node, wait):
    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}', 'link_timeout_s': 3.0,
                                                'takeoff_altitude_m': 1.0, 'status_rate_hz': 10.0})
    vehicle = VehicleThread(port, ekf_ready_delay_s=0.5)
    probe = None
    try:
        # the stand-in starts landed; the bridge publishes the state once it is known, latched, so a
        # subscriber that joins afterwards still gets it
        assert wait(lambda: 'vehicle landed state ON_GROUND' in bridge.log(), 60.0), bridge.log()[-2000:]
        probe = Probe(ros)
        assert wait(lambda: probe.seen()[-1:] == [ON_GROUND], 60.0), (probe.seen(), bridge.log()[-2000:])
        for _ in range(40):                    # the stand-in refuses to arm until its EKF is ready
            res = probe.call('arm')
            if res.success:
                break
            time.sleep(0.25)
        assert res.success, res.message
        res = probe.call('takeoff')
        assert res.success, res.message
        assert wait(lambda: IN_AIR in probe.seen(), 30.0), probe.seen()
        res = probe.call('land')
        assert res.success, res.message
        assert wait(lambda: not vehicle.world.armed and probe.seen()[-1] == ON_GROUND, 40.0), probe.seen()
        reports = probe.seen()                                             # republished at every report
        seen = [s for k, s in enumerate(reports) if k == 0 or s != reports[k - 1]]
        airborne = seen.index(IN_AIR)
        assert seen[0] == ON_GROUND and set(seen[1:airborne]) <= {TAKEOFF}, seen
        assert LANDING in seen[airborne:], seen
        assert wait(lambda: probe.value('landed_state') == 'ON_GROUND', 10.0), probe.diag
        assert bridge.proc.poll() is None
    finally:
        if probe is not None:
            probe.close()
        vehicle.stop()


def _pose(x: float, stamp_s: float, frame: str = 'mocap') -> PoseStamped:
    m = PoseStamped()
    m.header.frame_id = frame
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(round(stamp_s * 1e9), 1_000_000_000)
    m.pose.position.x, m.pose.position.z = x, 1.0
    m.pose.orientation.w = 1.0
    return m


def test_mocap_that_does_not_fit_or_comes_twice_never_ends_the_bridge(ros, start_node, wait):
    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}', 'mocap_topic': '/mocap/pose',
                                                'vision_rate_hz': 50.0, 'vision_max_age_s': 1.0,
                                                # best-effort delivery may drop a pose of the first driver now
                                                # and then; ten of its poses in a row never are
                                                'vision_reset_confirm_poses': 10})
    vehicle = SilentAutopilot(port)
    probe = Probe(ros)
    first = ros.create_publisher(PoseStamped, '/mocap/pose', SENSOR_QOS)
    second = ros.create_publisher(PoseStamped, '/mocap/pose', SENSOR_QOS)
    try:
        assert wait(lambda: probe.value('link') == 'up', 60.0), bridge.log()
        assert wait(lambda: first.get_subscription_count() > 0 and second.get_subscription_count() > 0, 30.0)
        for x in (1e39, 1e30):                 # 1e39 ended the node (OverflowError packing the estimate)
            first.publish(_pose(x, time.time()))
            time.sleep(0.05)
        assert wait(lambda: int(probe.value('mocap_rejected_out_of_range') or 0) == 2, 10.0), probe.diag
        end = time.monotonic() + 2.0
        while time.monotonic() < end:          # two drivers 2 m apart on one topic, 50 Hz each
            first.publish(_pose(0.5, time.time()))
            time.sleep(0.01)
            second.publish(_pose(2.5, time.time()))
            time.sleep(0.01)
        assert wait(lambda: probe.value('mocap_publishers') == '2' and probe.value('mocap_warning'), 10.0), probe.diag
        got = [m for _, m in vehicle.received('VISION_POSITION_ESTIMATE')]
        assert len(got) > 20, bridge.log()[-2000:]
        assert all(m.reset_counter == 0 for m in got)              # no reset for each pose
        assert all(math.isclose(m.y, 0.5, abs_tol=1e-6) for m in got)   # the first track only (ENU x = NED y)
        assert int(probe.value('mocap_rejected_jump_unconfirmed') or 0) > 20
        assert 'more than one' in bridge.log() or 'publishers on /mocap/pose' in bridge.log()
        assert bridge.proc.poll() is None and int(probe.value('callback_errors') or 0) == 0
    finally:
        ros.destroy_publisher(first)
        ros.destroy_publisher(second)
        probe.close()
        vehicle.close()


@pytest.mark.parametrize('origin, words', [([47.4, 8.5, 1e10], 'altitude_m must be <= 10000'),
                                           ([47.4, 8.5, -1e6], 'altitude_m must be >= -500')])
def test_an_ekf_origin_that_cannot_be_sent_stops_the_start(start_node, origin, words):
    node = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{free_udp_port()}',
                                              'ekf_origin': origin})
    assert node.proc.wait(30) == 1, node.log()
    errors = [line for line in node.log().splitlines() if line.startswith('error:')]
    assert len(errors) == 1 and 'ekf_origin' in errors[0] and words in errors[0], node.log()
    assert 'Traceback' not in node.log()
