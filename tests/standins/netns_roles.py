"""The two ends of tests/test_netns_split.py, each run inside its network namespace (tests only).

    netns_roles.py vehicle OUT PORT SECONDS   ArduCopter stand-in (SilentAutopilot, position too) on UDP
                                              loopback PORT for a bridge, plus a 30 Hz camera on the contract's
                                              raw topics; writes {"setpoints": [[arrival_s, vx], ...]} to OUT
    netns_roles.py pilot OUT SECONDS          the base station: /cmd_vel at 20 Hz whose vx changes every 0.25 s
                                              (vx encodes the change's number), and counts /odom and relayed depth
                                              frames; writes {"sent": [[k, first_send_s, vx], ...], "odom": n,
                                              "frames": [[stamp_s, arrival_s], ...]} to OUT
Both stop at SECONDS or on SIGINT/SIGTERM, and write OUT then.
"""
from __future__ import annotations

import json
import signal
import sys
import threading
import time

import numpy as np


def _stop_event() -> threading.Event:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def vx_of(k: int) -> float:
    """The commanded forward speed of change number k (distinct for 100 changes in a row)."""
    return round(0.2 + 0.01 * (k % 100), 4)


def vehicle(out: str, port: int, seconds: float) -> None:
    import rclpy
    from sensor_msgs.msg import Image

    from assist_common.ros_io import SENSOR_QOS
    from assist_sim.testing import SilentAutopilot
    stop = _stop_event()
    ap = SilentAutopilot(port, send_position=True)
    rclpy.init()
    node = rclpy.create_node('netns_camera')
    pubs = {enc: node.create_publisher(Image, topic, SENSOR_QOS)
            for enc, topic in (('rgb8', '/camera/color/image_raw'), ('32FC1', '/camera/depth/image_raw'))}
    frames = {'rgb8': np.full((64, 64, 3), 90, np.uint8), '32FC1': np.full((64, 64), 3.0, np.float32)}
    end = time.monotonic() + seconds
    try:
        while not stop.is_set() and time.monotonic() < end:
            now = time.time_ns()
            for enc, pub in pubs.items():
                m = Image()
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(now, 1_000_000_000)
                m.header.frame_id = 'camera_optical_frame'
                m.height, m.width, m.encoding = 64, 64, enc
                m.step = int(frames[enc].strides[0])
                m.data = frames[enc].tobytes()
                pub.publish(m)
            time.sleep(1 / 30)
    finally:
        with open(out, 'w') as f:
            json.dump({'setpoints': [[t, vx] for t, vx, _ in ap.setpoints()]}, f)
        ap.close()
        node.destroy_node()
        rclpy.try_shutdown()


def pilot(out: str, seconds: float) -> None:
    import rclpy
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import CompressedImage

    from assist_common.ros_io import RELIABLE_QOS, SENSOR_QOS
    stop = _stop_event()
    rclpy.init()
    node = rclpy.create_node('netns_pilot')
    pub = node.create_publisher(TwistStamped, '/cmd_vel', RELIABLE_QOS)
    seen = {'odom': 0, 'frames': []}
    lock = threading.Lock()

    def on_odom(_):
        with lock:
            seen['odom'] += 1

    def on_frame(m):                  # (camera stamp, arrival): the relay keeps the camera's header
        with lock:
            seen['frames'].append([m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, time.time()])
    node.create_subscription(Odometry, '/odom', on_odom, SENSOR_QOS)
    node.create_subscription(CompressedImage, '/camera/depth/image_raw/compressedDepth', on_frame, SENSOR_QOS)
    spin = threading.Thread(target=rclpy.spin, args=(node,), daemon=True)
    spin.start()
    sent = []
    t0 = time.monotonic()
    try:
        while not stop.is_set() and time.monotonic() - t0 < seconds:
            k = int((time.monotonic() - t0) / 0.25)
            msg = TwistStamped()
            msg.header.frame_id = 'base_link'
            msg.twist.linear.x = vx_of(k)
            if not sent or sent[-1][0] != k:
                sent.append([k, time.time(), vx_of(k)])
            pub.publish(msg)
            time.sleep(0.05)
    finally:
        with lock, open(out, 'w') as f:
            json.dump({'sent': sent, 'odom': seen['odom'], 'frames': seen['frames']}, f)
        rclpy.try_shutdown()


if __name__ == '__main__':
    role, rest = sys.argv[1], sys.argv[2:]
    if role == 'vehicle':
        vehicle(rest[0], int(rest[1]), float(rest[2]))
    else:
        pilot(rest[0], float(rest[1]))
