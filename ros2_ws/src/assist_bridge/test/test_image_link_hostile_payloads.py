"""Hostile compressed payloads at the base station: only the declared codec is decoded, and a payload whose own
header announces an image over the limits (or whose header cannot be read) is refused before any decoding."""
import struct
import zlib

import cv2
import numpy as np
import PIL.ImageFile
import pytest

from assist_bridge import image_link
from assist_bridge.image_link import COLOR_FORMAT, DEPTH_FORMAT, LinkError, decode_color, decode_depth, encode_color
from assist_common.domains import private_domain_id

HUGE = 16000                                  # px a side: 768 MB as RGB, far over the 4096 px limit
DEPTH_HEADER = struct.pack('<iff', 1, 0.0, 0.0)   # compressedDepth ConfigHeader, PNG


@pytest.fixture
def no_decoding(monkeypatch):
    """Any pixel decoding (OpenCV's or Pillow's) fails the test: hostile payloads must be refused from headers."""
    def decoded(*args, **kwargs):
        raise AssertionError('a hostile payload reached a decoder')
    monkeypatch.setattr(cv2, 'imdecode', decoded)
    monkeypatch.setattr(PIL.ImageFile.ImageFile, 'load', decoded)


def gradient(h=16, w=16) -> np.ndarray:
    """A small RGB test picture with distinct channels."""
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 255 // (w - 1), y * 255 // (h - 1), np.full_like(x, 90)], axis=-1).astype(np.uint8)


def deflate_tiff(width: int, height: int) -> bytes:
    """A little-endian, deflate-compressed greyscale TIFF claiming width x height, its data a few kB."""
    strip = zlib.compress(bytes(width * 64), 9)           # the first 64 rows: zeros compress ~1000:1
    entries = [(256, 4, width), (257, 4, height), (258, 3, 8), (259, 3, 8), (262, 3, 1),
               (273, 4, 0), (277, 3, 1), (278, 4, height), (279, 4, len(strip))]
    ifd_size = 2 + 12 * len(entries) + 4
    entries[5] = (273, 4, 8 + ifd_size)                   # StripOffsets: right after the IFD
    ifd = struct.pack('<H', len(entries))
    for tag, kind, value in entries:
        ifd += struct.pack('<HHI', tag, kind, 1) + (struct.pack('<HH', value, 0) if kind == 3
                                                     else struct.pack('<I', value))
    return b'II*\x00' + struct.pack('<I', 8) + ifd + struct.pack('<I', 0) + strip


def jpeg_claiming(width: int, height: int, before_dqt: bytes = b'', before_sof: bytes = b'') -> bytes:
    """A real 16x16 JPEG whose frame header (SOF0) is rewritten to width x height, with bytes slipped in
    before its quantisation tables and before its frame header."""
    jpeg = encode_color(gradient(), 90)
    sof = jpeg.index(b'\xff\xc0')
    jpeg = jpeg[:sof + 5] + struct.pack('>HH', height, width) + jpeg[sof + 9:]
    sof, dqt = jpeg.index(b'\xff\xc0'), jpeg.index(b'\xff\xdb')
    assert dqt < sof
    return jpeg[:dqt] + before_dqt + jpeg[dqt:sof] + before_sof + jpeg[sof:]


@pytest.mark.parametrize('payload, fmt, reason', [
    # other codecs under a PNG label: OpenCV would decode each of them whatever the format said
    (deflate_tiff(HUGE, HUGE), 'rgb8; png compressed bgr8', 'codec_mismatch'),
    (deflate_tiff(HUGE, HUGE), 'png', 'codec_mismatch'),
    (cv2.imencode('.bmp', gradient())[1].tobytes(), 'rgb8; png compressed bgr8', 'codec_mismatch'),
    (cv2.imencode('.webp', gradient())[1].tobytes(), 'rgb8; png compressed bgr8', 'codec_mismatch'),
    # PNG and JPEG swapped
    (cv2.imencode('.png', gradient())[1].tobytes(), COLOR_FORMAT, 'codec_mismatch'),
    (encode_color(gradient(), 90), 'rgb8; png compressed bgr8', 'codec_mismatch'),
    # JPEG frame headers announcing 16000 px, behind a stray byte or 0xFF fill bytes a naive scan trips on
    (jpeg_claiming(HUGE, HUGE, before_dqt=b'\x00'), COLOR_FORMAT, 'bad_size'),
    (jpeg_claiming(64, HUGE, before_dqt=b'\x13\x37'), COLOR_FORMAT, 'bad_size'),
    (jpeg_claiming(HUGE, 64, before_sof=b'\xff\xff\xff'), COLOR_FORMAT, 'bad_size'),
    # a JPEG whose frame header cannot be found is refused, not decoded blind
    (encode_color(gradient(), 90).replace(b'\xff\xc0', b'\xff\x02', 1), COLOR_FORMAT, 'bad_payload'),
    (encode_color(gradient(), 90).split(b'\xff\xda')[0], COLOR_FORMAT, 'bad_payload'),   # headers, no scan
])
def test_colour_payloads_of_another_codec_or_too_large_are_refused_undecoded(no_decoding, payload, fmt, reason):
    with pytest.raises(LinkError) as err:
        decode_color(payload, fmt)
    assert err.value.reason == reason, err.value


def test_depth_payloads_of_another_codec_or_too_large_are_refused_undecoded(no_decoding):
    for payload, reason in [(deflate_tiff(HUGE, HUGE), 'codec_mismatch'),
                            (cv2.imencode('.bmp', np.zeros((8, 8), np.uint8))[1].tobytes(), 'codec_mismatch'),
                            (jpeg_claiming(HUGE, HUGE), 'codec_mismatch')]:
        with pytest.raises(LinkError) as err:
            decode_depth(DEPTH_HEADER + payload, DEPTH_FORMAT)
        assert err.value.reason == reason, err.value
    # a PNG whose IHDR announces 16000 x 16000 (CRC fixed up, a few bytes of data): refused from the IHDR
    png = bytearray(cv2.imencode('.png', np.zeros((4, 4), np.uint16))[1].tobytes())
    png[16:24] = struct.pack('>II', HUGE, HUGE)
    png[29:33] = struct.pack('>I', zlib.crc32(bytes(png[12:29])))
    with pytest.raises(LinkError, match='16000x16000') as err:
        decode_depth(DEPTH_HEADER + bytes(png), DEPTH_FORMAT)
    assert err.value.reason == 'bad_size'


def test_payloads_over_the_byte_limit_are_refused_unread(no_decoding):
    limit = image_link.LIMITS.max_payload_bytes
    big = b'\x89PNG\r\n\x1a\n' + bytes(limit)
    with pytest.raises(LinkError) as err:
        decode_color(big, 'rgb8; png compressed bgr8')
    assert err.value.reason == 'too_large'
    with pytest.raises(LinkError) as err:
        decode_depth(DEPTH_HEADER + big, DEPTH_FORMAT)
    assert err.value.reason == 'too_large'


@pytest.mark.parametrize('fmt', [
    '16UC1; compressedDepth png',         # the depth transport's format on the colour topic
    'tiff', 'rgb8; tiff compressed bgr8', 'bmp', 'webp',
    'jpegpng', 'png jpeg', 'rgb8; jpeg png compressed bgr8', 'rgb8; png', 'rgb8; jpeg compressed bgr8 extra',
    '', 'PNG?', 'rgb8; compressed jpeg',
    '16UC1; png compressed',              # a 16-bit image is not a colour frame
])
def test_colour_formats_other_than_image_transports_are_refused_by_name(no_decoding, fmt):
    png = cv2.imencode('.png', gradient())[1].tobytes()
    with pytest.raises(LinkError) as err:
        decode_color(png, fmt)
    assert err.value.reason == 'bad_format', err.value


@pytest.mark.parametrize('fmt', [COLOR_FORMAT, '16UC1; compressedDepth rvl', '32FC1; compressedDepth png', 'jpeg',
                                 '16UC1; png compressed', '16UC1 compressedDepth png', '16UC1; compressedDepth tiff'])
def test_depth_formats_other_than_16_bit_png_compressed_depth_are_refused(no_decoding, fmt):
    png = cv2.imencode('.png', np.zeros((4, 4), np.uint16))[1].tobytes()
    with pytest.raises(LinkError) as err:
        decode_depth(DEPTH_HEADER + png, fmt)
    assert err.value.reason == 'bad_format', err.value


def test_valid_images_in_every_accepted_form_still_decode():
    rgb = gradient()
    clean = decode_color(encode_color(rgb, 95), COLOR_FORMAT)
    assert clean.shape == (16, 16, 3) and np.abs(clean.astype(int) - rgb).max() < 16
    # stray and fill bytes between segments are skipped as libjpeg does; the picture is the same
    for odd in (jpeg_claiming(16, 16, before_dqt=b'\x00'), jpeg_claiming(16, 16, before_sof=b'\xff\xff')):
        assert np.array_equal(decode_color(odd, COLOR_FORMAT), decode_color(jpeg_claiming(16, 16), COLOR_FORMAT))
    png = cv2.imencode('.png', np.ascontiguousarray(rgb[..., ::-1]))[1].tobytes()     # lossless: exact
    for fmt in ('rgb8; png compressed bgr8', 'bgr8; png compressed bgr8', ' png '):
        assert np.array_equal(decode_color(png, fmt), rgb)
    for fmt in ('jpeg', 'bgr8; jpeg compressed bgr8', 'mono8; jpeg compressed '):
        assert np.array_equal(decode_color(encode_color(rgb, 95), fmt), clean)
    grey = cv2.imencode('.jpg', rgb[..., 1].copy(), [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
    out = decode_color(grey, 'mono8; jpeg compressed ')
    assert out.shape == (16, 16, 3) and np.array_equal(out[..., 0], out[..., 2])
    assert np.abs(out[..., 0].astype(int) - rgb[..., 1]).max() < 4
    mm = (np.arange(48, dtype=np.uint16).reshape(6, 8) * 1300)
    payload = DEPTH_HEADER + cv2.imencode('.png', mm)[1].tobytes()
    for fmt in (DEPTH_FORMAT, '16UC1; compressedDepth', 'png'):
        out = decode_depth(payload, fmt)
        assert out.dtype == np.uint16 and np.array_equal(out, mm)
    # the largest image the limit allows is still read (a flat 4096 x 8 strip: tiny to store and decode)
    side = image_link.LIMITS.max_side_px
    assert decode_color(encode_color(np.zeros((8, side, 3), np.uint8), 50), COLOR_FORMAT).shape == (8, side, 3)


def test_image_decoder_node_counts_each_refusal_by_reason_and_still_publishes():
    """The node: a BMP labelled PNG and a mislabelled format are counted by reason; a good frame goes out."""
    import rclpy
    from rclpy.context import Context
    from sensor_msgs.msg import CompressedImage

    from assist_bridge.image_decoder import ImageDecoder

    ctx = Context()
    rclpy.init(context=ctx, domain_id=private_domain_id())
    try:
        node = ImageDecoder(context=ctx)
        try:
            for data, fmt in [(cv2.imencode('.bmp', gradient())[1].tobytes(), 'rgb8; png compressed bgr8'),
                              (encode_color(gradient(), 90), DEPTH_FORMAT),
                              (encode_color(gradient(), 90), COLOR_FORMAT)]:
                msg = CompressedImage()
                msg.format, msg.data = fmt, data
                node._on_color(msg)
            assert node.diag.get('rejected_color_codec_mismatch') == 1
            assert node.diag.get('rejected_color_bad_format') == 1
            assert node.diag.get('color_out') == 1
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
