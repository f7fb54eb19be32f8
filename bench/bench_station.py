"""Pilot station bench: chase-view frame rate in headless Chromium and key-to-motion latency.

sim_node (wall clock) and pilot_station run as console scripts on a private ROS domain, the station's
/pilot/cmd_vel remapped onto /cmd_vel (the unassisted condition, V = u, as `station.launch.py
assisted:=false` runs it). Headless Chromium (Debian's chromium + chromedriver, driven by Selenium)
loads the page; W and S are held in turn from rest. Times: the browser's own keydown timestamp
(performance.timeOrigin + event.timeStamp, CLOCK_REALTIME) to this process receiving the first
/cmd_vel with that key's sign, and to the first /odom whose body velocity along x exceeds 0.15 m/s
in that direction (the vehicle moving); and, inside the page, keydown to the first state update
that shows that motion (what the pilot sees: also crosses the station -> page WebSocket).
"""
from __future__ import annotations

import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from assist_sim.testing import stop_process
from assist_station.testing import start_browser

N_TRIALS = 12
MOVING_MPS = 0.15
FPS_WINDOW_S = 5.0


def wait_until(pred, timeout: float) -> bool:
    """Poll `pred` every 20 ms until it is true (True) or `timeout` seconds pass (its last value)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.02)
    return bool(pred())


def open_page(log: Path, user_dir: Path):
    """Wait for the pilot_station writing `log` to print its URL, open it in headless Chromium; (driver, stats),
    stats() returning the page's window.stationStats."""
    if not wait_until(lambda: 'open http://' in log.read_text(), 60):
        raise RuntimeError('pilot_station did not start')
    url = re.search(r'open (http://\S+/)', log.read_text()).group(1)
    driver = start_browser(user_dir)
    driver.get(url)
    return driver, lambda: driver.execute_script('return window.stationStats')


def run() -> list[dict]:
    """Measure the station; rows of name/value/unit/target."""
    import rclpy
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from selenium.webdriver.common.action_chains import ActionChains

    from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS

    domain = random.Random(os.getpid() ^ time.monotonic_ns()).randint(200, 232)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    bindir = Path(sys.executable).parent
    tmp = Path(tempfile.mkdtemp(prefix='bench_station_'))
    log = open(tmp / 'station.log', 'w')
    procs = [subprocess.Popen([str(bindir / 'sim_node'), '--ros-args', '-p', 'seed:=3'], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True),
             subprocess.Popen([str(bindir / 'pilot_station'), '--ros-args', '-p', 'port:=0',
                               '-r', '/pilot/cmd_vel:=/cmd_vel'], env=env, stdout=log, stderr=subprocess.STDOUT,
                              start_new_session=True)]
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('bench_station', context=ctx)
    lock = threading.Lock()
    cmds: list[tuple[float, float]] = []
    odom: list[tuple[float, float]] = []

    def on_cmd(msg):
        t = time.time()
        with lock:
            cmds.append((t, msg.twist.linear.x))

    def on_odom(msg):
        t = time.time()
        with lock:
            odom.append((t, msg.twist.twist.linear.x))
    node.create_subscription(TwistStamped, '/cmd_vel', on_cmd, RELIABLE_QOS)
    node.create_subscription(Odometry, '/odom', on_odom, SENSOR_QOS)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    driver = None
    try:
        driver, stats = open_page(tmp / 'station.log', tmp / 'chromium')
        if not wait_until(lambda: (s := stats())['pose'] is not None and s['scenePlatforms'] == 5, 60):
            raise RuntimeError('page never showed the vehicle and scene')
        time.sleep(1.0)
        s0, t0 = stats(), time.monotonic()
        time.sleep(FPS_WINDOW_S)
        s1 = stats()
        fps = (s1['frames'] - s0['frames']) / (time.monotonic() - t0)
        draw_ms = (s1['renderMsTotal'] - s0['renderMsTotal']) / max(1, s1['frames'] - s0['frames'])
        canvas = stats()['canvas']
        to_cmd, to_move = [], []
        for i in range(N_TRIALS):
            key, sign = ('w', 1.0) if i % 2 == 0 else ('s', -1.0)
            wait_until(lambda: odom and abs(odom[-1][1]) < 0.05, 5.0)
            ActionChains(driver).key_down(key).perform()
            time.sleep(0.7)
            ActionChains(driver).key_up(key).perform()
            t_key = stats()['lastKey']['epochMs'] / 1000.0
            with lock:
                c = next((t for t, x in cmds if t >= t_key and x * sign > 0), None)
                m = next((t for t, v in odom if t >= t_key and v * sign > MOVING_MPS), None)
            if c is not None:
                to_cmd.append(1000 * (c - t_key))
            if m is not None:
                to_move.append(1000 * (m - t_key))
            time.sleep(1.2)
        seen = stats()['keyToMotionMs']
    finally:
        if driver is not None:
            driver.quit()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        for p in procs:
            stop_process(p, 10.0)
        log.close()
        shutil.rmtree(tmp, ignore_errors=True)
    rows = [{'name': 'chase view frame rate (headless Chromium, canvas 2D)', 'value': fps, 'unit': 'frames/s',
             'target': '>= 20'},
            {'name': 'chase view size', 'value': f'{canvas[0]}x{canvas[1]}', 'unit': 'px', 'target': '>= 480x360'},
            {'name': 'chase view draw time per frame (JavaScript)', 'value': draw_ms, 'unit': 'ms'}]
    for name, xs in (('key event -> /pilot/cmd_vel (remapped to /cmd_vel)', to_cmd),
                     ('key event -> /odom moving (|vx| > 0.15 m/s)', to_move),
                     ('key event -> page shows motion', seen)):
        if not xs:
            raise RuntimeError(f'no samples for {name}')
        rows.append({'name': f'{name}, median of {len(xs)}', 'value': float(np.median(xs)), 'unit': 'ms'})
        rows.append({'name': f'{name}, max', 'value': float(np.max(xs)), 'unit': 'ms'})
    return rows
