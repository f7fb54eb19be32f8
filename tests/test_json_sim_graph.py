"""sim_node with physics:=ardupilot_json in a real ROS 2 graph, fed by the SITL stand-in over UDP."""
from __future__ import annotations

import socket
import struct
import threading
import time

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from assist_common.ros_io import LATCHED_QOS, SENSOR_QOS
from assist_sim.testing_sitl import SitlStandIn

pytestmark = pytest.mark.graph


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class Probe:
    def __init__(self, node):
        self.node, self.lock = node, threading.Lock()
        self.msgs = {k: [] for k in ('rgb', 'goal', 'odom', 'clock', 'diag', 'scene')}
        subs = [(Image, '/camera/color/image_raw', 'rgb', SENSOR_QOS), (PointStamped, '/sim/goal', 'goal', LATCHED_QOS),
                (Odometry, '/odom', 'odom', SENSOR_QOS), (Clock, '/clock', 'clock', 10),
                (DiagnosticArray, '/diagnostics', 'diag', 10), (MarkerArray, '/sim/scene', 'scene', LATCHED_QOS)]
        self.subs = [node.create_subscription(t, n, self._cb(k), q) for t, n, k, q in subs]

    def _cb(self, key):
        def cb(msg):
            with self.lock:
                self.msgs[key].append(msg)
        return cb

    def count(self, key):
        with self.lock:
            return len(self.msgs[key])

    def last(self, key):
        with self.lock:
            return self.msgs[key][-1] if self.msgs[key] else None

    def sim_status(self):
        """Latest sim_node DiagnosticStatus as (level, message, {key: value}) or None."""
        with self.lock:
            for arr in reversed(self.msgs['diag']):
                for st in arr.status:
                    if st.hardware_id == 'sim_node':
                        return st.level[0] if isinstance(st.level, bytes) else st.level, st.message, \
                            {kv.key: kv.value for kv in st.values}
        return None

    def close(self):
        for s in self.subs:
            self.node.destroy_subscription(s)


@pytest.fixture
def probe(ros):
    p = Probe(ros)
    yield p
    p.close()


def test_sim_node_serves_sitl_json_publishes_camera_goal_no_odom(probe, start_node, wait):
    port = free_udp_port()
    node = start_node('sim_node', {'physics': 'ardupilot_json', 'json_port': port, 'seed': 4,
                                   'json_silence_timeout_s': 0.5})
    assert wait(lambda: probe.count('goal') > 0, 60), node.log()
    g = probe.last('goal')
    # /sim/goal in the autopilot's odom frame: pad top minus base_link's resting height at the start spot
    assert g.header.frame_id == 'odom' and 0.4 - 0.13 < g.point.z < 1.2 - 0.11
    assert wait(lambda: probe.count('scene') > 0, 30), node.log()
    goal_box = next(m for m in probe.last('scene').markers if m.ns == 'goal')
    # the goal box's top centre is /sim/goal: the scene is in the same (autopilot odom) frame
    assert goal_box.pose.position.x == pytest.approx(g.point.x, abs=1e-6)
    assert goal_box.pose.position.z + goal_box.scale.z / 2 == pytest.approx(g.point.z, abs=1e-6)
    assert wait(lambda: (probe.sim_status() or (0, ''))[1].startswith('waiting for ArduPilot SITL'), 30), node.log()

    sitl = SitlStandIn(port=port)
    stop = threading.Event()
    replies = []
    pwm = [1000] * 4                     # disarmed: MOT_PWM_MIN

    def fly():   # SITL's loop: one frame, wait for its reply, next frame
        while not stop.is_set():
            r = sitl.exchange(list(pwm), timeout=0.5)
            if r is not None:
                replies.append(r)
    t = threading.Thread(target=fly, daemon=True)
    try:
        sitl.send_raw(struct.pack('<HHI16H', 4242, 400, 0, *[1000] * 16))     # wrong magic: dropped
        sitl.send_raw(b'\x00' * 7)                                               # wrong length: dropped
        assert wait(lambda: 'no valid SITL packet' in (probe.sim_status() or (0, ''))[1], 30), node.log()
        level, msg, _ = probe.sim_status()
        assert level == 2 and 'dropped 1 with a wrong magic, 1 with a wrong length, 0 with a frame rate' in msg
        t.start()
        assert wait(lambda: probe.count('rgb') >= 5, 60), node.log()
        assert wait(lambda: (probe.sim_status() or (0, ''))[1].startswith('SITL connected'), 30), node.log()
        level, msg, kv = probe.sim_status()
        assert level == 0 and kv['json_bad_magic'] == '1' and kv['json_bad_length'] == '1'
        assert int(kv['json_replies']) > 0 and kv['json_frame_rate_hz'] == '400'
        img = probe.last('rgb')
        assert (img.width, img.height, img.encoding) == (64, 64, 'rgb8')
        assert replies and abs(replies[-1]['position'][2] + 0.122) < 0.01       # resting at the start spot
        def sim_time():
            c = probe.last('clock').clock
            return c.sec + 1e-9 * c.nanosec
        assert wait(lambda: sim_time() > 0.5, 30), node.log()          # /clock follows SITL's frames
        # /sim/reset while the motors spin (armed idle, 1100 us) waits until SITL disarms
        pwm[:] = [1100] * 4
        n_rep = len(replies)
        assert wait(lambda: len(replies) > n_rep + 10, 30)
        n_goal = probe.count('goal')
        client = probe.node.create_client(Trigger, '/sim/reset')
        try:
            assert client.wait_for_service(timeout_sec=30)
            fut = client.call_async(Trigger.Request())
            assert wait(lambda: fut.done(), 30)
            assert fut.result().success and 'deferred' in fut.result().message
            time.sleep(0.5)
            assert probe.count("goal") == n_goal
            pwm[:] = [1000] * 4
            assert wait(lambda: probe.count('goal') > n_goal, 30), node.log()    # new episode once disarmed
        finally:
            probe.node.destroy_client(client)
    finally:
        stop.set()
        t.join(timeout=5)
        sitl.close()
    # SITL silent -> diagnostics error, physics paused (the clock stops)
    assert wait(lambda: (probe.sim_status() or (0, ''))[0] == 2, 30), node.log()
    assert 'physics paused' in probe.sim_status()[1]
    def clock():
        c = probe.last('clock').clock
        return c.sec, c.nanosec
    # /clock messages published just before the pause may still be on their way: the clock settles ...
    settled = [clock()]

    def still() -> bool:
        time.sleep(0.3)
        now = clock()
        same, settled[0] = now == settled[0], now
        return same
    assert wait(still, 10), node.log()
    c1 = clock()
    time.sleep(1.0)
    assert clock() == c1                                # ... and then stays where it is
    assert probe.count('odom') == 0                     # /odom comes from the bridge in this mode
    assert node.proc.poll() is None


def test_sim_node_json_bad_setup_exits_with_one_clear_line(start_node, wait):
    node = start_node('sim_node', {'physics': 'ardupilot_json', 'mavlink_url': 'udpin:127.0.0.1:14559'})
    assert wait(lambda: node.proc.poll() is not None, 60)
    assert node.proc.returncode == 1 and 'exclusive' in node.log()
    node = start_node('sim_node', {'physics': 'bullet'})
    assert wait(lambda: node.proc.poll() is not None, 60)
    assert node.proc.returncode == 1 and "must be one of velocity, ardupilot_json" in node.log()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(('127.0.0.1', 0))
        node = start_node('sim_node', {'physics': 'ardupilot_json', 'json_port': busy.getsockname()[1]})
        assert wait(lambda: node.proc.poll() is not None, 60)
    assert node.proc.returncode == 1 and 'cannot listen for SITL' in node.log()
    assert 'Traceback' not in node.log()
