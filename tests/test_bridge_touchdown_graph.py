"""mavlink_bridge_node in a real graph against the sim's ArduCopter stand-in: the vehicle's DISTANCE_SENSOR
reaches the touchdown envelope, so a pilot who keeps asking for sideways speed while descending is flown
straight down in the last decimetres, and the engagement shows on /diagnostics."""
import threading
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
from rclpy.qos import QoSProfile
from std_msgs.msg import UInt8
from std_srvs.srv import Trigger

from assist_common.mavlink_io import mavlink
from assist_common.ros_io import LATCHED_QOS, RELIABLE_QOS, fill_twist
from assist_common.touchdown import TouchdownConfig
from assist_sim.testing import RecordingWorld, VehicleThread, free_udp_port

pytestmark = pytest.mark.graph
ON_GROUND = mavlink.MAV_LANDED_STATE_ON_GROUND
COMMAND = [0.3, 0.2, -0.2]                  # body FLU: forward, left, slowly down


class Probe:
    """The bridge's /diagnostics and /uav/landed_state, a /cmd_vel publisher and /uav/* clients."""

    def __init__(self, node):
        self.node = node
        self.lock = threading.Lock()
        self.diag: dict[str, str] = {}
        self.states: list[int] = []
        self.subs = [node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10),
                     node.create_subscription(UInt8, '/uav/landed_state', self._on_state, LATCHED_QOS)]
        self.cmd = node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
        self.clients = {n: node.create_client(Trigger, f'/uav/{n}', qos_profile=QoSProfile(depth=100))
                        for n in ('arm', 'takeoff')}

    def _on_diag(self, msg):
        for st in msg.status:
            if st.name.endswith('mavlink_bridge_node'):
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in st.values}

    def _on_state(self, msg):
        with self.lock:
            self.states.append(int(msg.data))

    def value(self, key: str) -> str | None:
        with self.lock:
            return self.diag.get(key)

    def last_state(self) -> int | None:
        with self.lock:
            return self.states[-1] if self.states else None

    def call(self, name: str, timeout: float = 15.0):
        client = self.clients[name]
        assert client.wait_for_service(timeout_sec=timeout), f'/uav/{name} not available'
        fut = client.call_async(Trigger.Request())
        end = time.monotonic() + timeout
        while not fut.done() and time.monotonic() < end:
            time.sleep(0.02)
        assert fut.done(), f'/uav/{name} did not answer'
        return fut.result()

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


def test_a_sideways_descent_ends_vertical_and_shows_on_diagnostics(ros, start_node, wait):
    td = TouchdownConfig()
    port = free_udp_port()
    bridge = start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}', 'link_timeout_s': 3.0,
                                                'takeoff_altitude_m': 1.0})
    world = RecordingWorld()
    vehicle = VehicleThread(port, world=world, ekf_ready_delay_s=0.5)
    probe = Probe(ros)
    try:
        assert wait(lambda: probe.value('link') == 'up', 60.0), bridge.log()[-2000:]
        assert probe.value('touchdown') == 'idle' and probe.value('touchdown_engaged') == '0', probe.diag
        for _ in range(40):                    # the stand-in refuses to arm until its EKF is ready
            res = probe.call('arm')
            if res.success:
                break
            time.sleep(0.25)
        assert res.success, res.message
        assert probe.call('takeoff').success
        assert wait(lambda: 'takeoff complete' in bridge.log(), 40.0), bridge.log()[-2000:]
        assert wait(lambda: probe.value('range_m') not in (None, 'unknown'), 10.0), probe.diag
        deadline = time.monotonic() + 60.0     # bounds a hang only
        while world.pos[2] > 0.02:
            assert time.monotonic() < deadline, f'never came down: {world.pos}'
            probe.send(COMMAND)
            time.sleep(0.05)
        steps = world.flown()
        last_high = max(k for k, (z, _) in enumerate(steps) if z > td.release_range_m + 0.1)
        high = [cmd for z, cmd in steps[:last_high + 1] if z > td.release_range_m + 0.1]
        below = [(z, cmd) for z, cmd in steps[last_high:] if 0.06 < z < td.commit_range_m]   # legs about to touch
        assert high and below
        assert np.allclose(high[-1], COMMAND, atol=1e-6), high[-1]       # flown as commanded up there
        # straight down in the last decimetres: from the first setpoint after the bridge saw the commit range
        # (its range reading lags the vehicle by up to a DISTANCE_SENSOR period and the load of the machine),
        # and that before the legs touch
        first = next((k for k, (_, cmd) in enumerate(below) if np.allclose(cmd[:2], 0.0, atol=1e-6)), None)
        assert first is not None, below[-3:]
        for z, cmd in below[first:]:
            np.testing.assert_allclose(cmd, [0.0, 0.0, -td.descent_mps], atol=1e-6, err_msg=f'at {z:.3f} m')
        assert wait(lambda: probe.value('touchdown_engaged') == '1', 10.0), probe.diag
        assert wait(lambda: probe.last_state() == ON_GROUND, 10.0), probe.states[-5:]
        assert 'touchdown: range' in bridge.log()
        assert bridge.proc.poll() is None
    finally:
        probe.close()
        vehicle.stop()
