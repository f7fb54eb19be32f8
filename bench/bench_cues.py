"""Pilot station bench: chase-view frame rate in headless Chromium with the assistant's intent cues drawn.

pilot_station runs as a console script on a private ROS domain; this process stands in for the rest of the
graph and publishes, at 20 Hz: a five-pad scene (/sim/scene, once, latched), the vehicle hovering (/odom), a
64x64 camera image (the inset), /assist/agent_cmd (assistance live), /assist/goal_estimate (its pad changing
every second, so the highlight moves), /assist/descent_ok and /cmd_vel (a push of 0.6 m/s). Headless Chromium
(Debian's chromium + chromedriver, driven by Selenium) loads the page; once it draws all three cues, frames are
counted for FPS_WINDOW_S seconds (window.stationStats.frames) with the cues on, then again after the station's
cue_goal, cue_descent and cue_push parameters are set false, in the same run and page.

    .venv/bin/python -m bench cues
"""
from __future__ import annotations

import os
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from assist_sim.testing import stop_process

from .bench_station import open_page, wait_until

FPS_WINDOW_S = 5.0
PADS = [((4.0, 1.0, 0.4), (1.2, 1.0, 0.8)), ((8.0, -0.8, 0.5), (1.0, 1.4, 1.0)), ((12.0, 0.6, 0.3), (1.4, 1.2, 0.6)),
        ((16.0, -1.0, 0.6), (1.0, 1.0, 1.2)), ((20.0, 0.2, 0.45), (1.2, 1.2, 0.9))]
HOVER = (0.5, 0.0, 3.0)


class _Feed:
    """The graph around the station: scene, odometry, camera and the assistant's topics, from one thread."""

    def __init__(self, node):
        from geometry_msgs.msg import PoseWithCovarianceStamped, TwistStamped
        from nav_msgs.msg import Odometry
        from sensor_msgs.msg import Image
        from std_msgs.msg import Bool
        from visualization_msgs.msg import Marker, MarkerArray

        from assist_common.ros_io import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, sec_to_stamp
        self.node, self.sec_to_stamp = node, sec_to_stamp
        self.types = {'pose': PoseWithCovarianceStamped, 'twist': TwistStamped, 'odom': Odometry, 'bool': Bool}
        self.pubs = {'odom': node.create_publisher(Odometry, '/odom', SENSOR_QOS),
                     'image': node.create_publisher(Image, '/camera/color/image_raw', SENSOR_QOS),
                     'agent': node.create_publisher(TwistStamped, '/assist/agent_cmd', RELIABLE_QOS),
                     'goal': node.create_publisher(PoseWithCovarianceStamped, '/assist/goal_estimate', RELIABLE_QOS),
                     'descent': node.create_publisher(Bool, '/assist/descent_ok', RELIABLE_QOS),
                     'blended': node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)}
        scene = MarkerArray()
        for i, (c, s) in enumerate(PADS):
            m = Marker(ns='platforms', id=i, type=Marker.CUBE, action=Marker.ADD)
            m.header.frame_id = 'odom'
            m.pose.position.x, m.pose.position.y, m.pose.position.z = c
            m.pose.orientation.w = 1.0
            m.scale.x, m.scale.y, m.scale.z = s
            m.color.r, m.color.g, m.color.b, m.color.a = 0.3 + 0.12 * i, 0.6, 0.9 - 0.15 * i, 1.0
            scene.markers.append(m)
        self.scene_pub = node.create_publisher(MarkerArray, '/sim/scene', LATCHED_QOS)
        self.scene_pub.publish(scene)
        img = bytearray(64 * 64 * 3)
        for i in range(64 * 64):
            img[3 * i:3 * i + 3] = bytes(((i % 64) * 4, (i // 64) * 4, 90))
        self.image = Image(height=64, width=64, encoding='rgb8', step=192, data=bytes(img))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _stamp(self, msg, frame: str):
        msg.header.frame_id = frame
        self.sec_to_stamp(self.node.get_clock().now().nanoseconds * 1e-9, msg.header.stamp)
        return msg

    def _run(self) -> None:
        t0, tick = time.monotonic(), 0
        while not self.stop.is_set():
            od = self._stamp(self.types['odom'](), 'odom')
            od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z = HOVER
            od.pose.pose.orientation.w = 1.0
            self.pubs['odom'].publish(od)
            if tick % 4 != 3:
                self.pubs['image'].publish(self._stamp(self.image, 'camera_optical_frame'))
            a = self._stamp(self.types['twist'](), 'base_link')
            a.twist.linear.y = 0.6
            self.pubs['agent'].publish(a)
            c, s = PADS[int(time.monotonic() - t0) % 2]          # the estimate moves between pads 0 and 1
            g = self._stamp(self.types['pose'](), 'odom')
            g.pose.pose.position.x, g.pose.pose.position.y, g.pose.pose.position.z = c[0], c[1], c[2] + s[2] / 2
            g.pose.pose.orientation.w = 1.0
            cov = [0.0] * 36
            cov[0] = cov[7] = cov[14] = 0.04
            cov[21] = cov[28] = cov[35] = 1e6
            g.pose.covariance = cov
            self.pubs['goal'].publish(g)
            self.pubs['descent'].publish(self.types['bool'](data=tick % 40 < 20))
            v = self._stamp(self.types['twist'](), 'base_link')
            v.twist.linear.y = 0.3                                 # V = (u + a) / 2 with u = 0: a push of 0.3 m/s
            self.pubs['blended'].publish(v)
            tick += 1
            time.sleep(0.05)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)


def _frames(stats) -> tuple[float, float]:
    """(frames per second, JavaScript draw ms per frame) over FPS_WINDOW_S."""
    s0, t0 = stats(), time.monotonic()
    time.sleep(FPS_WINDOW_S)
    s1, t1 = stats(), time.monotonic()
    n = s1['frames'] - s0['frames']
    return n / (t1 - t0), (s1['renderMsTotal'] - s0['renderMsTotal']) / max(1, n)


def run() -> list[dict]:
    """Measure the page with and without the cues; rows of name/value/unit/target."""
    import rclpy
    from rcl_interfaces.srv import SetParameters
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    domain = random.Random(os.getpid() ^ time.monotonic_ns()).randint(200, 232)
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    tmp = Path(tempfile.mkdtemp(prefix='bench_cues_'))
    log = open(tmp / 'station.log', 'w')
    station = subprocess.Popen([str(Path(sys.executable).parent / 'pilot_station'), '--ros-args', '-p', 'port:=0',
                                '-p', 'mode:=free'], env=env, stdout=log, stderr=subprocess.STDOUT,
                               start_new_session=True)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain)
    node = Node('bench_cues', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    feed = _Feed(node)
    driver = None
    try:
        driver, stats = open_page(tmp / 'station.log', tmp / 'chromium')

        def all_cues():
            s = stats()
            d = s['cueDrawn']
            return (d['goal'] is not None and d['goal']['state'] == 'sure' and d['push'] is not None
                    and d['descent'] in ('ok', 'hold') and s['cameraFrames'] > 0)
        if not wait_until(all_cues, 60):
            raise RuntimeError(f'page never drew the three cues: {stats()["cueDrawn"]}')
        time.sleep(1.0)
        fps_on, ms_on = _frames(stats)
        drew_all = all_cues()
        client = node.create_client(SetParameters, '/pilot_station/set_parameters')
        if not client.wait_for_service(timeout_sec=20):
            raise RuntimeError('no parameter service on pilot_station')
        req = SetParameters.Request(parameters=[Parameter(f'cue_{k}', value=False).to_parameter_msg()
                                                for k in ('goal', 'descent', 'push')])
        future = client.call_async(req)
        if not wait_until(future.done, 20) or not all(r.successful for r in future.result().results):
            raise RuntimeError('setting cue_* false failed')
        if not wait_until(lambda: stats()['cueDrawn'] == {'goal': None, 'push': None, 'descent': None}, 20):
            raise RuntimeError('cues still drawn with cue_* false')
        time.sleep(1.0)
        fps_off, ms_off = _frames(stats)
        canvas = stats()['canvas']
    finally:
        if driver is not None:
            driver.quit()
        feed.close()
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        stop_process(station, 10.0)
        log.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return [{'name': 'chase view + inset frame rate, all three cues drawn (headless Chromium)', 'value': fps_on,
             'unit': 'frames/s', 'target': '>= 20'},
            {'name': 'cues still drawn at the end of the window', 'value': 'yes' if drew_all else 'no', 'unit': ''},
            {'name': 'chase view + inset frame rate, cues switched off', 'value': fps_off, 'unit': 'frames/s'},
            {'name': 'draw time per frame (JavaScript), cues on', 'value': ms_on, 'unit': 'ms'},
            {'name': 'draw time per frame (JavaScript), cues off', 'value': ms_off, 'unit': 'ms'},
            {'name': 'chase view size', 'value': f'{canvas[0]}x{canvas[1]}', 'unit': 'px'}]
