"""encoder_core: message decoding, resizing, inference, latest-only buffer, stamp pairing."""
import threading

import numpy as np
import pytest
import torch

from assist_perception.encoder_core import (BadFrame, LatentEncoder, LatestOnly, StampPairer,
                                            decode_color, decode_depth, resize_pair)
from assist_perception.model import CMVAE, CMVAEConfig, ModelLoadError, preprocess, save_model


@pytest.fixture(scope='module')
def model_file(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp('m') / 'cmvae_test.pt'
    save_model(path, CMVAE(CMVAEConfig(latent_dim=8)).eval())
    return path


def test_decode_color_rgb_bgr_with_row_padding():
    rgb = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    padded = np.zeros((2, 12), np.uint8)          # step 12 > 9 bytes per row
    padded[:, :9] = rgb.reshape(2, 9)
    np.testing.assert_array_equal(decode_color(padded.tobytes(), 'rgb8', 2, 3, 12), rgb)
    bgr = rgb[..., ::-1].copy()
    np.testing.assert_array_equal(decode_color(bgr.tobytes(), 'bgr8', 2, 3, 9), rgb)
    with pytest.raises(BadFrame) as e:
        decode_color(rgb.tobytes(), 'mono8', 2, 3, 9)
    assert e.value.reason == 'bad_encoding'
    with pytest.raises(BadFrame) as e:
        decode_color(rgb.tobytes()[:10], 'rgb8', 2, 3, 9)
    assert e.value.reason == 'bad_size'


def test_decode_depth_units_endianness_and_invalid():
    m = np.array([[1.5, np.nan], [-1.0, 0.25]], np.float32)
    np.testing.assert_allclose(decode_depth(m.tobytes(), '32FC1', 2, 2, 8), [[1.5, 0], [0, 0.25]])
    np.testing.assert_allclose(decode_depth(m.astype('>f4').tobytes(), '32FC1', 2, 2, 8, True),
                               [[1.5, 0], [0, 0.25]])
    mm = np.array([[1500, 0], [250, 65535]], np.uint16)
    np.testing.assert_allclose(decode_depth(mm.tobytes(), '16UC1', 2, 2, 4), [[1.5, 0], [0.25, 65.535]],
                               rtol=1e-6)
    with pytest.raises(BadFrame):
        decode_depth(mm.tobytes(), '8UC1', 2, 2, 4)


def test_resize_crops_centre_square_and_keeps_holes():
    rgb = np.zeros((480, 640, 3), np.uint8)
    rgb[:, :80] = 255            # outside the central 480x480 square
    depth = np.full((480, 640), 2.0, np.float32)
    depth[:240, 80:320] = 0.0    # a hole covering the top-left quarter of the square
    r, d = resize_pair(rgb, depth, 64)
    assert r.shape == (64, 64, 3) and d.shape == (64, 64)
    assert r.max() == 0                              # the white side band was cropped away
    assert set(np.unique(d)) == {0.0, 2.0}           # nearest: no invented depths
    assert (d[:32, :32] == 0).all() and (d[32:, 32:] == 2.0).all()


def test_encoder_matches_model_and_any_resolution(model_file):
    enc = LatentEncoder(model_file)
    assert enc.latent_dim == 8
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 255, (64, 64, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 4.0, (64, 64)).astype(np.float32)
    out = enc.encode(rgb, depth, want_depth=True)
    with torch.no_grad():
        ref = enc.model(preprocess(rgb, depth, enc.model.cfg), sample=False)
    np.testing.assert_allclose(out.mu, ref.mu[0].numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out.pad_xyz, ref.xyz[0].numpy(), rtol=1e-5, atol=1e-6)
    assert out.depth.shape == (64, 64) and out.mu.dtype == np.float32
    big = enc.encode(np.repeat(np.repeat(rgb, 5, 0), 5, 1), np.repeat(np.repeat(depth, 5, 0), 5, 1))
    assert big.depth is None and big.mu.shape == (8,)


def test_bad_frames_are_refused(model_file):
    enc = LatentEncoder(model_file)
    rgb = np.zeros((64, 64, 3), np.uint8)
    with pytest.raises(BadFrame) as e:
        enc.encode(rgb, np.full((64, 64), np.nan, np.float32))
    assert e.value.reason == 'no_valid_depth'
    with pytest.raises(BadFrame) as e:
        enc.encode(rgb, np.ones((48, 64), np.float32))
    assert e.value.reason == 'size_mismatch'


def test_missing_and_corrupt_model_files(tmp_path):
    with pytest.raises(ModelLoadError, match='not found'):
        LatentEncoder(tmp_path / 'nope.pt')
    bad = tmp_path / 'bad.pt'
    bad.write_bytes(b'not a zip file')
    with pytest.raises(ModelLoadError, match='cannot read'):
        LatentEncoder(bad)


def test_latest_only_keeps_newest_and_counts_dropped():
    box = LatestOnly()
    box.put(1)
    box.put(2)
    box.put(3)
    assert box.take(0.1) == 3 and box.replaced == 2
    assert box.take(0.01) is None
    got = []
    t = threading.Thread(target=lambda: got.append(box.take(5.0)))
    t.start()
    box.put(7)
    t.join(5.0)
    assert got == [7]
    box.close()
    assert box.take(5.0) is None and box.closed


def test_stamp_pairer_pairs_within_slop_once():
    p = StampPairer(0.01)
    assert p.add('color', 1.000, 'c1') is None
    assert p.add('depth', 1.005, 'd1') == ('c1', 'd1')
    assert p.add('depth', 1.050, 'd2') is None          # no colour left to pair with
    assert p.add('color', 1.100, 'c2') is None          # 50 ms apart: beyond the slop
    assert p.add('depth', 1.095, 'd3') == ('c2', 'd3')
    assert p.unpaired == 1                              # d2 never found a colour partner
    p.add('color', 2.0, 'c3')
    p.add('color', 2.1, 'c4')                           # nor did c3
    assert p.unpaired == 2
    assert p.add('depth', 2.1, 'd4') == ('c4', 'd4')


@pytest.mark.parametrize('h, w', [(1, 1), (2, 4096), (4096, 2), (8, 8), (16, 80)])
def test_degenerate_frames_are_refused_not_encoded(model_file, h, w):
    enc = LatentEncoder(model_file)
    with pytest.raises(BadFrame) as e:
        enc.encode(np.zeros((h, w, 3), np.uint8), np.ones((h, w), np.float32))
    assert e.value.reason == 'bad_size'
    assert enc.encode(np.zeros((16, 64, 3), np.uint8), np.ones((16, 64), np.float32)).mu.shape == (8,)   # 4:1 is
