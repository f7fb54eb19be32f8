"""The pilot station with the MAVLink graph: sim_node as the ArduCopter vehicle + mavlink_bridge_node.

/odom now comes from the bridge (the vehicle's telemetry), not from sim_node; the chase view must
follow it and the browser's keys must fly the vehicle through the bridge (the test relays
/pilot/cmd_vel onto /cmd_vel, the unassisted condition).
"""
import re
import threading
import time

import numpy as np
import pytest
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from std_srvs.srv import Trigger

from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS
from assist_sim.testing import free_udp_port
from assist_station import testing

pytestmark = pytest.mark.graph


class Probe:
    """Relays /pilot/cmd_vel -> /cmd_vel, records /odom and pilot commands, calls /uav/*."""

    def __init__(self, node):
        self.node, self.lock = node, threading.Lock()
        self.pos, self.cmds = None, []
        self.relay = node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
        self.subs = [node.create_subscription(TwistStamped, '/pilot/cmd_vel', self._on_cmd, RELIABLE_QOS),
                     node.create_subscription(Odometry, '/odom', self._on_odom, SENSOR_QOS)]
        self.clients = {n: node.create_client(Trigger, f'/uav/{n}') for n in ('arm', 'takeoff')}

    def _on_cmd(self, msg):
        self.relay.publish(msg)
        with self.lock:
            self.cmds.append((time.monotonic(), msg.twist.linear.x))

    def _on_odom(self, msg):
        p = msg.pose.pose.position
        with self.lock:
            self.pos = np.array([p.x, p.y, p.z])

    def call(self, name, timeout=15.0):
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
        self.node.destroy_publisher(self.relay)
        for c in self.clients.values():
            self.node.destroy_client(c)


def test_chase_view_follows_the_bridge_odometry_and_keys_fly_the_mavlink_vehicle(ros, start_node, wait, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    port = free_udp_port()
    start_node('sim_node', {'mavlink_url': f'udpout:127.0.0.1:{port}', 'camera_rate_hz': 0.0, 'seed': 5,
                            'auto_reset': False})
    start_node('mavlink_bridge_node', {'connection': f'udpin:127.0.0.1:{port}'})
    station = start_node('pilot_station', {'port': 0})
    probe = Probe(ros)
    driver = None
    try:
        assert wait(lambda: 'open http://' in station.log(), 60), station.log()
        url = re.search(r'open (http://127\.0\.0\.1:\d+/)', station.log()).group(1)
        try:
            driver = testing.start_browser(tmp_path / 'chromium')
        except FileNotFoundError as exc:
            pytest.fail(str(exc))
        driver.get(url)
        stats = lambda: testing.page_stats(driver)  # noqa: E731
        assert wait(lambda: (s := stats())['pose'] is not None and s['scenePlatforms'] == 5, 90), stats()
        for _ in range(40):                         # the vehicle's EKF needs a moment before it arms
            if probe.call('arm').success:
                break
            time.sleep(0.5)
        else:
            raise AssertionError('never armed')
        assert probe.call('takeoff').success
        assert wait(lambda: probe.pos is not None and probe.pos[2] > 1.8, 40.0), probe.pos
        assert wait(lambda: stats()['pose']['p'][2] > 1.8, 5.0)             # the page sees the climb
        time.sleep(1.0)
        x_page, x_odom = stats()['pose']['p'][0], probe.pos[0]
        t0 = time.monotonic()
        ActionChains(driver).key_down('w').perform()
        time.sleep(1.5)
        ActionChains(driver).key_up('w').perform()
        with probe.lock:
            assert any(x == 1.0 for t, x in probe.cmds if t >= t0)
        assert probe.pos[0] - x_odom > 0.5, probe.pos
        assert wait(lambda: stats()['pose']['p'][0] - x_page > 0.5, 3.0)    # the chase view followed
        t1 = time.monotonic()
        assert wait(lambda: any(x == 0.0 for t, x in probe.cmds if t >= t1), 1.0)
    finally:
        if driver is not None:
            driver.quit()
        probe.close()
