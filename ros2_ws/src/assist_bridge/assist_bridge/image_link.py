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

Decoding (the base station) trusts nothing in a payload: the `format` is parsed as image_transport writes it
(assist_common.images.parse_compressed_format), the data must start with the declared codec's signature,
and Pillow's reader for that codec alone reads the header (PNG's IHDR; JPEG's frame header, stray and fill
bytes skipped) and decodes. A payload of another codec (TIFF, BMP, WebP, a PNG labelled JPEG), over
DecodeLimits (8 MiB, 4096 px a side in its header) or whose header cannot be read is refused before a pixel
is decoded.

Shrinking: colour with area averaging (what the encoder does to a big frame), depth by nearest neighbour
(averaging would invent depths between a pad's top and the floor). Depth beyond 65.535 m, negative, NaN
or infinite becomes 0, the contract's "no reading".
"""
from __future__ import annotations

import io
import struct
from dataclasses import dataclass

import cv2
import numpy as np
from PIL import ImageFile, JpegImagePlugin, PngImagePlugin

from assist_common.images import BadFrame, CompressedFormat, parse_compressed_format

COLOR_FORMAT = 'rgb8; jpeg compressed bgr8'
DEPTH_FORMAT = '16UC1; compressedDepth png'
COLOR_SUFFIX = '/compressed'
DEPTH_SUFFIX = '/compressedDepth'
_DEPTH_HEADER = struct.Struct('<iff')          # compressed_depth_image_transport ConfigHeader
_PNG_FORMAT = 1                                 # its compressionFormat enum: INV_DEPTH 0, PNG 1, RVL 2
# the codecs a payload may be in: each one's signature, and Pillow's reader for it (never another codec's)
_MAGIC = {'png': b'\x89PNG\r\n\x1a\n', 'jpeg': b'\xff\xd8'}
_READERS = {'png': PngImagePlugin.PngImageFile, 'jpeg': JpegImagePlugin.JpegImageFile}
# the encodings a colour payload may say it came from ('' = a bare "jpeg"/"png" format)
COLOR_RAW_ENCODINGS = frozenset({'', 'rgb8', 'bgr8', 'rgba8', 'bgra8', 'mono8'})


class LinkError(ValueError):
    """A payload that cannot be made or read; `reason` is a short diagnostics key."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f'{reason}: {detail}')
        self.reason = reason


@dataclass(frozen=True)
class DecodeLimits:
    """What the base station decodes at most: bigger payloads are refused before a pixel is decoded."""

    max_side_px: int = 4096                     # image width or height in the codec's header
    max_payload_bytes: int = 8 * 1024 * 1024    # compressed size (a 64x64 pair is ~2 kB)


LIMITS = DecodeLimits()


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


def _parse(fmt: str, transport: str) -> CompressedFormat:
    """parse_compressed_format, its refusal as a LinkError."""
    try:
        return parse_compressed_format(fmt, transport)
    except BadFrame as exc:
        raise LinkError(exc.reason, exc.detail) from None


def _payload(data, what: str, limits: DecodeLimits) -> bytes:
    """The message's payload as bytes, refused unread (not even copied) when over the byte limit."""
    if len(data) > limits.max_payload_bytes:
        raise LinkError('too_large', f'{what}: {len(data)} bytes, more than {limits.max_payload_bytes}')
    return bytes(data)


def _open(data: bytes, codec: str, what: str, limits: DecodeLimits) -> ImageFile.ImageFile:
    """The header of a payload of the declared codec, read by that codec's parser alone; LinkError if unusable.

    Nothing is decoded here: Pillow's PNG / JPEG readers parse the signature and the headers up to the image
    data (PNG: IHDR and the chunks before IDAT; JPEG: every marker segment up to the first scan, skipping fill
    and stray bytes as libjpeg does), so a payload of another codec, or one announcing more than the size
    limit, is refused before a pixel buffer exists."""
    if not data:
        raise LinkError('bad_payload', f'{what}: empty payload')
    if not data.startswith(_MAGIC[codec]):
        kind = next((name for name, magic in _MAGIC.items() if data.startswith(magic)), 'neither PNG nor JPEG')
        raise LinkError('codec_mismatch', f'{what}: declared {codec}, the data is {kind} (starts {data[:8]!r})')
    try:
        img = _READERS[codec](io.BytesIO(data))
    except (SyntaxError, OSError, ValueError, EOFError) as exc:
        raise LinkError('bad_payload', f'{what}: unreadable {codec} header ({str(exc)[:120]})') from None
    width, height = img.size
    if width > limits.max_side_px or height > limits.max_side_px:
        img.close()
        raise LinkError('bad_size', f'{what}: {width}x{height} is larger than {limits.max_side_px} px a side')
    if not img.tile:
        img.close()
        raise LinkError('bad_payload', f'{what}: {codec} header with no image data after it')
    return img


def _pixels(img: ImageFile.ImageFile, what: str) -> np.ndarray:
    """Decode an opened payload (its header already checked) -> read-only array; LinkError if the data is bad."""
    try:
        with img:
            img.load()
            return np.asarray(img)
    except (SyntaxError, OSError, ValueError, EOFError) as exc:
        raise LinkError('bad_payload', f'{what}: {str(exc)[:120]}') from None


def decode_color(data: bytes, fmt: str, limits: DecodeLimits = LIMITS) -> np.ndarray:
    """Colour payload (format ``[<encoding>; ]<jpeg|png>[ compressed ...]``) -> (H,W,3) uint8 RGB, read-only.

    Only the codec `fmt` declares is decoded; a payload of another codec, one over the limits, or a format
    that is not image_transport's `compressed` one raises LinkError (reason bad_format, codec_mismatch,
    too_large, bad_size or bad_payload)."""
    parsed = _parse(fmt, 'compressed')
    if parsed.raw_encoding not in COLOR_RAW_ENCODINGS:
        raise LinkError('bad_format', f'colour format {fmt!r}: encoding {parsed.raw_encoding!r} is not a colour '
                                      f'one (want one of {sorted(e for e in COLOR_RAW_ENCODINGS if e)})')
    img = _open(_payload(data, 'colour', limits), parsed.codec, 'colour', limits)
    if img.mode not in ('RGB', 'L'):
        img.close()
        raise LinkError('bad_payload', f'colour: a {img.mode} {parsed.codec} image, want RGB or greyscale')
    rgb = _pixels(img, 'colour')
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
        rgb.flags.writeable = False
    return rgb


def decode_depth(data: bytes, fmt: str, limits: DecodeLimits = LIMITS) -> np.ndarray:
    """DEPTH_FORMAT payload -> (H,W) uint16 millimetres, read-only; LinkError (as decode_color) if unusable."""
    parsed = _parse(fmt, 'compressedDepth')
    if parsed.codec != 'png' or parsed.raw_encoding not in ('16UC1', ''):
        raise LinkError('bad_format', f'depth format {fmt!r} (want {DEPTH_FORMAT!r})')
    data = _payload(data, 'depth', limits)
    if len(data) <= _DEPTH_HEADER.size:
        raise LinkError('bad_payload', f'depth: {len(data)} bytes, no room for the header and an image')
    kind, _, _ = _DEPTH_HEADER.unpack_from(data)
    if kind != _PNG_FORMAT:
        raise LinkError('bad_format', f'depth compression format {kind} (want PNG = {_PNG_FORMAT})')
    img = _open(data[_DEPTH_HEADER.size:], 'png', 'depth', limits)
    if img.mode != 'I;16':
        img.close()
        raise LinkError('bad_payload', f'depth: a {img.mode} PNG, want 16-bit greyscale (one channel)')
    return _pixels(img, 'depth')


def pack_pair(rgb: np.ndarray, depth_m: np.ndarray, cfg: LinkConfig) -> tuple[bytes, bytes]:
    """One camera pair at the link's size: (JPEG colour, compressedDepth PNG)."""
    color = shrink_color(rgb, cfg.width, cfg.height)
    depth = depth_to_mm(shrink_depth(depth_m, cfg.width, cfg.height))
    return encode_color(color, cfg.jpeg_quality), encode_depth(depth, cfg.png_level)
