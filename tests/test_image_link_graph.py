"""image_relay (vehicle) -> image_decoder (base station) as two processes: the camera pair arrives at the
encoder's size with its own headers, depth exact to the millimetre; a corrupt payload is counted, not fatal."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytestmark = pytest.mark.graph


def _frames(stamp_ns: int, seq: int):
    from sensor_msgs.msg import Image
    h, w = 240, 320
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = np.linspace(0, 200, w, dtype=np.uint8)[None, :]
    rgb[..., 1] = 60
    depth = np.full((h, w), 3.0, np.float32)
    depth[80:160, 100 + seq % 40:200 + seq % 40] = 2.2 + 0.001 * (seq % 7)   # a pad that moves, 1 mm steps
    msgs = []
    for arr, enc in ((rgb, 'rgb8'), (depth, '32FC1')):
        m = Image()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        m.header.frame_id = 'camera_optical_frame'
        m.height, m.width, m.encoding = h, w, enc
        m.step = int(arr.strides[0])
        m.data = arr.tobytes()
        msgs.append(m)
    return msgs, depth


def test_relay_and_decoder_restore_the_pair_with_its_headers(ros, start_node, wait):
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import CompressedImage, Image

    from assist_bridge.image_link import depth_to_mm, shrink_depth
    start_node('image_relay', {'rate_hz': 20.0})
    start_node('image_decoder', {}, remaps={'/camera/color/image_raw': '/base/color/image_raw',
                                            '/camera/depth/image_raw': '/base/depth/image_raw'})
    pub_c = ros.create_publisher(Image, '/camera/color/image_raw', qos_profile_sensor_data)
    pub_d = ros.create_publisher(Image, '/camera/depth/image_raw', qos_profile_sensor_data)
    bad = ros.create_publisher(CompressedImage, '/camera/depth/image_raw/compressedDepth', qos_profile_sensor_data)
    got: dict[str, list] = {'color': [], 'depth': []}
    diag: dict[str, dict] = {}
    lock = threading.Lock()

    def keep(kind):
        def cb(msg):
            with lock:
                got[kind].append(msg)
        return cb
    ros.create_subscription(Image, '/base/color/image_raw', keep('color'), qos_profile_sensor_data)
    ros.create_subscription(Image, '/base/depth/image_raw', keep('depth'), qos_profile_sensor_data)
    ros.create_subscription(DiagnosticArray, '/diagnostics',
                            lambda m: diag.update({s.hardware_id: {kv.key: kv.value for kv in s.values}
                                                   for s in m.status}), 10)
    sent = {}
    seq = 0
    end = time.monotonic() + 60
    while time.monotonic() < end and len(got['depth']) < 10:
        stamp = time.time_ns()
        msgs, depth = _frames(stamp, seq)
        sent[stamp] = depth
        pub_c.publish(msgs[0])
        pub_d.publish(msgs[1])
        seq += 1
        time.sleep(1 / 30)                       # a 30 Hz camera; the relay sends at most 20 pairs a second
    with lock:
        colors, depths = list(got['color']), list(got['depth'])
    assert len(depths) >= 10 and colors, (len(colors), len(depths))
    for m in depths:
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        assert stamp in sent and m.header.frame_id == 'camera_optical_frame'
        assert (m.encoding, m.height, m.width) == ('16UC1', 64, 64)
        mm = np.frombuffer(bytes(m.data), '<u2').reshape(64, 64)
        assert np.array_equal(mm, depth_to_mm(shrink_depth(sent[stamp], 64, 64)))
    c = colors[-1]
    assert (c.encoding, c.height, c.width) == ('rgb8', 64, 64)
    rgb = np.frombuffer(bytes(c.data), np.uint8).reshape(64, 64, 3)
    assert abs(int(rgb[..., 1].mean()) - 60) <= 3 and rgb[:, -1, 0].mean() > rgb[:, 0, 0].mean() + 150
    # a corrupt payload: counted by the decoder, which goes on decoding
    junk = CompressedImage()
    junk.format = '16UC1; compressedDepth png'
    junk.data = b'\x01\x00\x00\x00' + bytes(8) + b'\x89PNG\r\n\x1a\n not really'   # a PNG signature, no IHDR
    for _ in range(3):
        bad.publish(junk)
        time.sleep(0.05)
    assert wait(lambda: int(diag.get('image_decoder', {}).get('rejected_depth_bad_payload', 0)) >= 1, 15), diag
    before = len(got['depth'])
    for k in range(30):
        msgs, depth = _frames(time.time_ns(), seq + k)
        pub_c.publish(msgs[0])
        pub_d.publish(msgs[1])
        time.sleep(1 / 30)
    assert wait(lambda: len(got['depth']) > before, 10)
    assert int(diag.get('image_relay', {}).get('pairs_sent', 0)) >= 10, diag
