"""Camera images over a radio link: the encoder's input, compressed on the vehicle and restored on the base station.

Pure numpy + OpenCV, no rclpy. The vehicle sends the camera pair at the size and rate the encoder uses
(64x64 at 20 Hz), not the camera's own (a D435i's 640x480 at 30 Hz is ~30 MB/s raw): colour as JPEG,
depth as lossless 16-bit PNG in millimetres. The payloads follow ROS image_transport's plugins, so
`ros2 run image_transport republish` and rqt read them too:

* colour: sensor_msgs/CompressedImage on `<colour topic>/compressed`, format ``rgb8; jpeg compressed bgr8``
  (OpenCV's JPEG of the BGR image);
* depth: sensor_msgs/CompressedImage on `<depth topic>/compressedDepth`, format ``16UC1; compressedDepth png``:
  compressed_depth_image_transport's 12-byte ConfigHeader (int32 compression format, PNG = 1; float32
  depthParam[2], unused for 16UC1) followed by the PNG of the uint16 millimetre image.

Shrinking: colour with area averaging (what the encoder does to a big frame), depth by nearest neighbour
(averaging would invent depths between a pad's top and the floor). Depth beyond 65.535 m, negative, NaN
or infinite becomes 0, the contract's "no reading".
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

COLOR_FORMAT = 'rgb8; jpeg compressed bgr8'
DEPTH_FORMAT = '16UC1; compressedDepth png'
COLOR_SUFFIX = '/compressed'
DEPTH_SUFFIX = '/compressedDepth'
_DEPTH_HEADER = struct.Struct('<iff')          # compressed_depth_image_transport ConfigHeader
_PNG_FORMAT = 1                                 # its compressionFormat enum: INV_DEPTH 0, PNG 1, RVL 2
MAX_SIDE_PX = 4096                              # a decoded image larger than this is refused (a hostile payload)


class LinkError(ValueError):
    """A payload that cannot be made or read; `reason` is a short diagnostics key."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f'{reason}: {detail}')
        self.reason = reason


@dataclass
class LinkConfig:
    """What the vehicle sends: the encoder's input size, JPEG quality and PNG effort."""

    width: int = 64
    height: int = 64
    jpeg_quality: int = 90
    png_level: int = 1              # zlib effort 0-9: depth frames are small, 1 is ~as small as 9 and faster


def shrink_color(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H,W,3) uint8 -> (height,width,3), area-averaged (unchanged when already that size)."""
    if rgb.shape[:2] == (height, width):
        return rgb
    return cv2.resize(np.ascontiguousarray(rgb), (width, height), interpolation=cv2.INTER_AREA)


def shrink_depth(depth_m: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H,W) float metres -> (height,width) by nearest neighbour (no depth invented at edges)."""
    if depth_m.shape == (height, width):
        return depth_m
    return cv2.resize(np.ascontiguousarray(depth_m), (width, height), interpolation=cv2.INTER_NEAREST)


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """float metres -> uint16 millimetres, rounded; no reading (0, negative, non-finite, > 65.535 m) -> 0."""
    mm = np.rint(np.asarray(depth_m, dtype=np.float64) * 1000.0)
    with np.errstate(invalid='ignore'):
        bad = ~np.isfinite(mm) | (mm < 0) | (mm > 65535)
    mm[bad] = 0
    return mm.astype(np.uint16)


def encode_color(rgb: np.ndarray, quality: int) -> bytes:
    """(H,W,3) uint8 RGB -> JPEG bytes (COLOR_FORMAT)."""
    ok, buf = cv2.imencode('.jpg', np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise LinkError('encode_failed', 'OpenCV could not JPEG-encode the colour frame')
    return buf.tobytes()


def encode_depth(depth_mm: np.ndarray, png_level: int) -> bytes:
    """(H,W) uint16 millimetres -> ConfigHeader + PNG bytes (DEPTH_FORMAT)."""
    ok, buf = cv2.imencode('.png', np.ascontiguousarray(depth_mm, dtype=np.uint16),
                           [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    if not ok:
        raise LinkError('encode_failed', 'OpenCV could not PNG-encode the depth frame')
    return _DEPTH_HEADER.pack(_PNG_FORMAT, 0.0, 0.0) + buf.tobytes()


def _imdecode(data: bytes, flags: int, what: str) -> np.ndarray:
    """OpenCV's decode of a PNG/JPEG payload; LinkError for an empty, corrupt or oversized one."""
    if not data:
        raise LinkError('bad_payload', f'{what}: empty payload')
    _image_size(data, what)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:
        raise LinkError('bad_payload', f'{what}: {str(exc).strip().splitlines()[-1][:120]}') from None
    return _check_size(img, what)


def _check_size(img: np.ndarray | None, what: str) -> np.ndarray:
    if img is None:
        raise LinkError('bad_payload', f'{what}: not a readable image')
    if img.shape[0] > MAX_SIDE_PX or img.shape[1] > MAX_SIDE_PX:
        raise LinkError('bad_size', f'{what}: {img.shape[1]}x{img.shape[0]} is larger than {MAX_SIDE_PX} px a side')
    return img


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's start-of-frame segment, or None when there is none."""
    i = 2
    while i + 9 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:      # no length field
            i += 2
            continue
        length = struct.unpack('>H', data[i + 2:i + 4])[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            h, w = struct.unpack('>HH', data[i + 5:i + 9])
            return w, h
        i += 2 + length
    return None


def _image_size(data: bytes, what: str) -> None:
    """Refuse a PNG/JPEG whose header announces more than MAX_SIDE_PX a side, before decoding it."""
    size = None
    if data[:8] == b'\x89PNG\r\n\x1a\n' and len(data) >= 24:
        size = struct.unpack('>II', data[16:24])
    elif data[:2] == b'\xff\xd8':
        size = _jpeg_size(data)
    if size is not None and (size[0] > MAX_SIDE_PX or size[1] > MAX_SIDE_PX):
        raise LinkError('bad_size', f'{what}: {size[0]}x{size[1]} is larger than {MAX_SIDE_PX} px a side')


def decode_color(data: bytes, fmt: str) -> np.ndarray:
    """JPEG (or PNG) payload of COLOR_FORMAT -> (H,W,3) uint8 RGB."""
    if 'jpeg' not in fmt and 'png' not in fmt:
        raise LinkError('bad_format', f'colour format {fmt!r} (want {COLOR_FORMAT!r})')
    img = _imdecode(bytes(data), cv2.IMREAD_COLOR, 'colour')
    return img[..., ::-1].copy()


def decode_depth(data: bytes, fmt: str) -> np.ndarray:
    """DEPTH_FORMAT payload -> (H,W) uint16 millimetres."""
    if 'compressedDepth' not in fmt or not fmt.startswith('16UC1'):
        raise LinkError('bad_format', f'depth format {fmt!r} (want {DEPTH_FORMAT!r})')
    data = bytes(data)
    if len(data) <= _DEPTH_HEADER.size:
        raise LinkError('bad_payload', f'depth: {len(data)} bytes, no room for the header and an image')
    kind, _, _ = _DEPTH_HEADER.unpack_from(data)
    if kind != _PNG_FORMAT:
        raise LinkError('bad_format', f'depth compression format {kind} (want PNG = {_PNG_FORMAT})')
    img = _imdecode(data[_DEPTH_HEADER.size:], cv2.IMREAD_UNCHANGED, 'depth')
    if img.dtype != np.uint16 or img.ndim != 2:
        raise LinkError('bad_payload', f'depth: a {img.dtype} image with shape {img.shape}, want 16-bit, one channel')
    return img


def pack_pair(rgb: np.ndarray, depth_m: np.ndarray, cfg: LinkConfig) -> tuple[bytes, bytes]:
    """One camera pair at the link's size: (JPEG colour, compressedDepth PNG)."""
    color = shrink_color(rgb, cfg.width, cfg.height)
    depth = depth_to_mm(shrink_depth(depth_m, cfg.width, cfg.height))
    return encode_color(color, cfg.jpeg_quality), encode_depth(depth, cfg.png_level)
