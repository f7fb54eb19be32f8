"""sensor_msgs/Image payloads -> numpy, honouring encoding, row step and byte order (pure numpy, no rclpy, no torch).

Every consumer of camera images (encoder_node, policy_node's floor guard and rules) decodes through here, so
a big-endian 16UC1 frame or a padded row reads the same everywhere; what cannot be read raises ``BadFrame``
with a short reason key (counted by the node).

The `format` field of sensor_msgs/CompressedImage is read here too (``parse_compressed_format``), the one
parser every consumer of compressed images uses.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

COLOR_ENCODINGS = {'rgb8': (3, False), 'bgr8': (3, True), 'rgba8': (4, False), 'bgra8': (4, True)}
DEPTH_ENCODINGS = {'32FC1': np.float32, '16UC1': np.uint16}


class BadFrame(ValueError):
    """A frame that cannot be encoded; `reason` is a short diagnostics key, `detail` what was wrong."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f'{reason}: {detail}')
        self.reason, self.detail = reason, detail


def _as_array(data: Any, height: int, width: int, step: int, channels: int, dtype,
              big_endian: bool) -> np.ndarray:
    """Raw ROS image buffer -> (H, W[, C]) array honouring row padding and byte order.

    A view on the message's own buffer whenever possible (rclpy hands uint8[] fields over as
    array.array, which numpy reads in place): no copy for unpadded native-order images; a
    padded or foreign-endian image costs one copy. Callers must not write into the result."""
    itemsize = np.dtype(dtype).itemsize
    row = width * channels * itemsize
    if height <= 0 or width <= 0:
        raise BadFrame('bad_size', f'empty image {width}x{height}')
    if step < row:
        raise BadFrame('bad_size', f'step {step} < width*channels*bytes {row}')
    try:
        buf = np.frombuffer(data, dtype=np.uint8)
    except (TypeError, ValueError):      # not a buffer (e.g. a list of ints)
        buf = np.frombuffer(bytes(data), dtype=np.uint8)
    if buf.size < step * height:
        raise BadFrame('bad_size', f'{buf.size} bytes for {height} rows of {step}')
    rows = buf[:step * height].reshape(height, step)[:, :row]
    dt = np.dtype(dtype).newbyteorder('>' if big_endian else '<')
    arr = np.ascontiguousarray(rows).view(dt)
    if not arr.dtype.isnative:
        arr = arr.astype(arr.dtype.newbyteorder('='))
    return arr.reshape(height, width, channels) if channels > 1 else arr.reshape(height, width)


def decode_color(data: Any, encoding: str, height: int, width: int, step: int) -> np.ndarray:
    """sensor_msgs/Image colour payload -> (H,W,3) uint8 RGB (read-only; a view for rgb8)."""
    if encoding not in COLOR_ENCODINGS:
        raise BadFrame('bad_encoding', f'colour encoding {encoding!r} (want rgb8/bgr8)')
    ch, bgr = COLOR_ENCODINGS[encoding]
    img = _as_array(data, height, width, step, ch, np.uint8, False)[..., :3]
    img = img[..., ::-1] if bgr else img
    img.flags.writeable = False
    return img


def decode_depth(data: Any, encoding: str, height: int, width: int, step: int,
                 big_endian: bool = False) -> np.ndarray:
    """sensor_msgs/Image depth payload (32FC1 m or 16UC1 mm) -> (H,W) float32 metres, holes 0 (a new array)."""
    if encoding not in DEPTH_ENCODINGS:
        raise BadFrame('bad_encoding', f'depth encoding {encoding!r} (want 32FC1 or 16UC1)')
    arr = _as_array(data, height, width, step, 1, DEPTH_ENCODINGS[encoding], big_endian)
    if encoding == '16UC1':
        depth = arr * np.float32(0.001)                    # the one copy (uint16 -> float32 metres)
    else:
        depth = np.array(arr, dtype=np.float32)            # the one copy (holes are zeroed in place)
    with np.errstate(invalid='ignore'):
        depth[~(depth >= 0) | ~np.isfinite(depth)] = 0.0
    return depth


# ROS image_transport's compressed transports and the codecs each may name in a CompressedImage `format`
COMPRESSED_CODECS = {'compressed': ('jpeg', 'png'), 'compressedDepth': ('png', 'rvl')}
_TOKEN = re.compile(r'[A-Za-z0-9_]+')      # a sensor_msgs image encoding name (rgb8, 16UC1, bayer_rggb8, ...)


@dataclass(frozen=True)
class CompressedFormat:
    """A CompressedImage `format`, parsed: the transport, its codec and the image encodings it names."""

    transport: str                 # 'compressed' or 'compressedDepth'
    codec: str                     # 'jpeg' / 'png' (compressed), 'png' / 'rvl' (compressedDepth)
    raw_encoding: str = ''         # the image's encoding before compression ('rgb8', '16UC1'); '' if not named
    compressed_encoding: str = ''  # the pixel format inside the codec ('bgr8'); '' if not named


def parse_compressed_format(fmt: str, transport: str) -> CompressedFormat:
    """A CompressedImage `format` of `transport` as ROS image_transport writes it -> CompressedFormat.

    Accepted, exactly (surrounding blanks ignored): the bare codec of old publishers (``jpeg``, ``png``;
    ``png``, ``rvl`` for compressedDepth), ``<raw>; <jpeg|png> compressed[ <pixel format>]`` (compressed) and
    ``<raw>; compressedDepth[ <png|rvl>]`` (compressedDepth; no codec is PNG, as image_transport before RVL
    wrote it). Anything else (an empty or unknown codec, another transport, extra words) raises
    ``BadFrame('bad_format', ...)``: the codec decides which decoder may run, so it is never guessed."""
    if transport not in COMPRESSED_CODECS:
        raise ValueError(f'transport {transport!r} (want one of {sorted(COMPRESSED_CODECS)})')
    codecs = COMPRESSED_CODECS[transport]
    text = str(fmt).strip()
    if ';' not in text:
        if text in codecs:
            return CompressedFormat(transport, text)
        raise BadFrame('bad_format', f'{transport} format {fmt!r} names no known codec (want one of {codecs})')
    raw, rest = (part.strip() for part in text.split(';', 1))
    words = rest.split()
    if not _TOKEN.fullmatch(raw):
        raise BadFrame('bad_format', f'{transport} format {fmt!r}: {raw!r} is not an image encoding')
    if transport == 'compressed':
        if len(words) not in (2, 3) or words[1] != 'compressed' or words[0] not in codecs:
            raise BadFrame('bad_format', f'format {fmt!r} (want "<encoding>; <{"|".join(codecs)}> compressed'
                                         f'[ <encoding>]")')
        packed = words[2] if len(words) == 3 else ''
        if packed and not _TOKEN.fullmatch(packed):
            raise BadFrame('bad_format', f'format {fmt!r}: {packed!r} is not an image encoding')
        return CompressedFormat(transport, words[0], raw, packed)
    if not 1 <= len(words) <= 2 or words[0] != 'compressedDepth' or (len(words) == 2 and words[1] not in codecs):
        raise BadFrame('bad_format', f'format {fmt!r} (want "<encoding>; compressedDepth[ <{"|".join(codecs)}>]")')
    return CompressedFormat(transport, words[1] if len(words) == 2 else 'png', raw)
