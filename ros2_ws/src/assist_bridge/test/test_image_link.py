"""The radio link's payloads: lossless depth, close colour, image_transport's formats, hostile payloads refused."""
import struct

import numpy as np
import pytest

from assist_bridge.image_link import (COLOR_FORMAT, DEPTH_FORMAT, LinkConfig, LinkError, decode_color, decode_depth,
                                      depth_to_mm, encode_color, encode_depth, pack_pair, shrink_depth)


def scene(h=480, w=640):
    """A camera pair like the sim's: textured floor at 3 m, a pad 0.8 m higher, a hole and a NaN."""
    rng = np.random.default_rng(3)
    rgb = (rng.random((h, w, 3)) * 12 + np.linspace(0, 150, w)[None, :, None]
           + np.linspace(0, 80, h)[:, None, None] * np.array([1.0, 0.3, 0.0])).astype(np.uint8)
    depth = np.full((h, w), 3.0, np.float32)
    depth[h // 3:2 * h // 3, w // 3:2 * w // 3] = 2.2
    depth[0, 0], depth[1, 1], depth[2, 2] = 0.0, np.nan, 70.0
    return rgb, depth


def test_depth_is_lossless_in_millimetres_and_shrinks_without_inventing_depths():
    rgb, depth = scene()
    _, png = pack_pair(rgb, depth, LinkConfig())
    mm = decode_depth(png, DEPTH_FORMAT)
    assert mm.shape == (64, 64) and mm.dtype == np.uint16
    assert set(np.unique(mm)) <= {0, 2200, 3000}             # nearest neighbour: only depths that were there
    expected = depth_to_mm(shrink_depth(depth, 64, 64))
    assert np.array_equal(mm, expected)
    assert list(depth_to_mm(np.array([0.0, np.nan, np.inf, -1.0, 65.535, 65.6, 1.2344]))) == \
        [0, 0, 0, 0, 65535, 0, 1234]
    assert png[:12] == struct.pack('<iff', 1, 0.0, 0.0) and png[12:16] == b'\x89PNG'


def test_colour_survives_jpeg_closely_and_size_follows_the_config():
    rgb, depth = scene(64, 64)
    jpeg, _ = pack_pair(rgb, depth, LinkConfig(jpeg_quality=90))
    back = decode_color(jpeg, COLOR_FORMAT)
    assert back.shape == (64, 64, 3)
    assert np.abs(back.astype(int) - rgb.astype(int)).mean() < 5.0
    assert back[..., 0].mean() == pytest.approx(rgb[..., 0].mean(), abs=3)     # channel order kept (RGB)
    small, _ = pack_pair(rgb, depth, LinkConfig(jpeg_quality=20))
    assert len(small) < len(jpeg)
    jpeg32, png32 = pack_pair(*scene(), LinkConfig(width=32, height=24))
    assert decode_color(jpeg32, COLOR_FORMAT).shape == (24, 32, 3)
    assert decode_depth(png32, DEPTH_FORMAT).shape == (24, 32)


@pytest.mark.parametrize('payload, fmt, reason', [
    (b'', COLOR_FORMAT, 'bad_payload'),
    (b'\xff\xd8garbage', COLOR_FORMAT, 'bad_payload'),
    (b'x' * 100, 'rgb8; raw', 'bad_format'),
    (b'\x01\x00\x00\x00' + b'\x00' * 8, DEPTH_FORMAT, 'bad_payload'),              # header only
    (struct.pack('<iff', 2, 0, 0) + b'\x89PNG....', DEPTH_FORMAT, 'bad_format'),  # RVL, not PNG
    (b'x' * 100, '32FC1; compressedDepth', 'bad_format'),
])
def test_bad_payloads_are_refused_with_a_reason(payload, fmt, reason):
    decode = decode_depth if 'Depth' in fmt else decode_color
    with pytest.raises(LinkError) as err:
        decode(payload, fmt)
    assert err.value.reason == reason


def test_oversized_images_are_refused_before_decoding():
    tall = encode_color(np.zeros((5000, 8, 3), np.uint8), 50)
    with pytest.raises(LinkError, match='5000') as err:
        decode_color(tall, COLOR_FORMAT)
    assert err.value.reason == 'bad_size'
    wide = encode_depth(np.zeros((4, 5000), np.uint16), 1)
    with pytest.raises(LinkError) as err:
        decode_depth(wide, DEPTH_FORMAT)
    assert err.value.reason == 'bad_size'
    # a colour PNG where depth is expected: 8-bit three channels, refused
    import cv2
    ok, buf = cv2.imencode('.png', np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(LinkError, match='16-bit'):
        decode_depth(struct.pack('<iff', 1, 0, 0) + buf.tobytes(), DEPTH_FORMAT)
