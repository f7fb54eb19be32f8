"""assist_common.images.parse_compressed_format: CompressedImage `format` strings as ROS image_transport writes
them are read field by field; anything else is refused by name (never matched by substring)."""
import pytest

from assist_common.images import BadFrame, CompressedFormat, parse_compressed_format


@pytest.mark.parametrize('fmt, transport, expected', [
    ('rgb8; jpeg compressed bgr8', 'compressed', CompressedFormat('compressed', 'jpeg', 'rgb8', 'bgr8')),
    ('bgr8; png compressed bgr8', 'compressed', CompressedFormat('compressed', 'png', 'bgr8', 'bgr8')),
    ('mono8; jpeg compressed ', 'compressed', CompressedFormat('compressed', 'jpeg', 'mono8', '')),
    ('16UC1; png compressed', 'compressed', CompressedFormat('compressed', 'png', '16UC1', '')),
    ('jpeg', 'compressed', CompressedFormat('compressed', 'jpeg')),
    (' png\n', 'compressed', CompressedFormat('compressed', 'png')),
    ('16UC1; compressedDepth png', 'compressedDepth', CompressedFormat('compressedDepth', 'png', '16UC1')),
    ('32FC1; compressedDepth rvl', 'compressedDepth', CompressedFormat('compressedDepth', 'rvl', '32FC1')),
    ('16UC1; compressedDepth', 'compressedDepth', CompressedFormat('compressedDepth', 'png', '16UC1')),
    ('png', 'compressedDepth', CompressedFormat('compressedDepth', 'png')),
])
def test_image_transport_formats_parse_field_by_field(fmt, transport, expected):
    assert parse_compressed_format(fmt, transport) == expected


@pytest.mark.parametrize('fmt, transport', [
    ('', 'compressed'), ('tiff', 'compressed'), ('jpg', 'compressed'), ('JPEG', 'compressed'),
    ('jpegpng', 'compressed'), ('png jpeg', 'compressed'), ('rgb8; tiff compressed bgr8', 'compressed'),
    ('rgb8; jpeg png compressed bgr8', 'compressed'), ('rgb8; png', 'compressed'),
    ('rgb8; compressed png', 'compressed'),
    ('rgb8; jpeg compressed bgr8 png', 'compressed'), ('; jpeg compressed bgr8', 'compressed'),
    ('rgb 8; jpeg compressed bgr8', 'compressed'), ('rgb8; jpeg compressed bgr8;png', 'compressed'),
    ('16UC1; compressedDepth png', 'compressed'),          # another transport's format
    ('rgb8; jpeg compressed bgr8', 'compressedDepth'), ('jpeg', 'compressedDepth'), ('', 'compressedDepth'),
    ('16UC1; compressedDepth jpeg', 'compressedDepth'), ('16UC1; compressedDepth png rvl', 'compressedDepth'),
    ('16UC1; png compressedDepth', 'compressedDepth'), ('16UC1 compressedDepth png', 'compressedDepth'),
])
def test_unknown_or_ambiguous_formats_are_refused_with_a_reason(fmt, transport):
    with pytest.raises(BadFrame) as err:
        parse_compressed_format(fmt, transport)
    assert err.value.reason == 'bad_format'
    assert repr(fmt) in str(err.value)


def test_an_unknown_transport_is_a_programming_error():
    with pytest.raises(ValueError, match='theora'):
        parse_compressed_format('jpeg', 'theora')
