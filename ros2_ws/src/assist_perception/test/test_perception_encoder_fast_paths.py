"""encoder_core fast paths: zero-copy message decoding, decoders on demand, batched mu."""
import array

import numpy as np
import pytest
import torch

from assist_perception.encoder_core import BadFrame, LatentEncoder, decode_color, decode_depth
from assist_perception.model import CMVAE, CMVAEConfig, save_model


@pytest.fixture(scope='module')
def encoder(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp('m') / 'cmvae_test.pt'
    save_model(path, CMVAE(CMVAEConfig(latent_dim=8)).eval())
    return LatentEncoder(path, threads=1)


def test_rgb8_from_an_rclpy_buffer_is_a_read_only_view():
    rgb = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    data = array.array('B', rgb.tobytes())               # what rclpy hands over for uint8[]
    img = decode_color(data, 'rgb8', 4, 5, 15)
    np.testing.assert_array_equal(img, rgb)
    assert np.shares_memory(img, np.frombuffer(data, np.uint8))   # no copy
    assert not img.flags.writeable
    np.testing.assert_array_equal(decode_color(data, 'bgr8', 4, 5, 15), rgb[..., ::-1])
    # a list of ints (not a buffer) still decodes
    np.testing.assert_array_equal(decode_color(list(rgb.tobytes()), 'rgb8', 4, 5, 15), rgb)


def test_depth_is_one_new_array_and_the_message_is_untouched():
    m = np.array([[1.5, np.nan], [-2.0, np.inf]], np.float32)
    data = array.array('B', m.tobytes())
    d = decode_depth(data, '32FC1', 2, 2, 8)
    np.testing.assert_array_equal(d, [[1.5, 0.0], [0.0, 0.0]])
    assert not np.shares_memory(d, np.frombuffer(data, np.uint8))
    assert np.isnan(np.frombuffer(data, np.float32)[1])   # the message keeps its NaN
    mm = np.array([[1500, 0]], np.uint16)
    np.testing.assert_allclose(decode_depth(array.array('B', mm.tobytes()), '16UC1', 1, 2, 4), [[1.5, 0.0]])


def _frames(n, rng):
    rgbs = [rng.integers(0, 255, (64, 64, 3), dtype=np.uint8) for _ in range(n)]
    depths = [rng.uniform(0.5, 4.0, (64, 64)).astype(np.float32) for _ in range(n)]
    return rgbs, depths


def test_decoders_run_only_when_asked(encoder):
    rgbs, depths = _frames(1, np.random.default_rng(0))
    full = encoder.encode(rgbs[0], depths[0], want_depth=True)
    lean = encoder.encode(rgbs[0], depths[0], want_xyz=False)
    np.testing.assert_allclose(lean.mu, full.mu, atol=1e-6)
    assert lean.depth is None and np.all(np.isnan(lean.pad_xyz)) and np.all(np.isfinite(full.pad_xyz))
    np.testing.assert_allclose(encoder.decode_depth(lean.mu), full.depth, atol=1e-5)


def test_batched_mu_equals_frame_by_frame(encoder):
    rgbs, depths = _frames(5, np.random.default_rng(1))
    batch = encoder.encode_mu_batch(rgbs, depths)
    assert batch.shape == (5, encoder.latent_dim) and batch.dtype == np.float32
    for i in range(5):
        np.testing.assert_allclose(batch[i], encoder.encode(rgbs[i], depths[i]).mu, atol=1e-5)
    assert encoder.encode_mu_batch([], []).shape == (0, encoder.latent_dim)
    depths[3] = np.zeros((64, 64), np.float32)          # no valid depth
    with pytest.raises(BadFrame, match='frame 3'):
        encoder.encode_mu_batch(rgbs, depths)
    with pytest.raises(ValueError):
        encoder.encode_mu_batch(rgbs, depths[:2])


def test_channels_last_inference_matches_the_plain_model(encoder, tmp_path):
    """The encoder runs NHWC weights and inputs for speed; outputs equal the NCHW model's."""
    from assist_perception.model import load_model, preprocess
    assert encoder.model.encoder.conv.weight.is_contiguous(memory_format=torch.channels_last)
    plain = load_model(encoder.model_path)
    assert not plain.encoder.conv.weight.is_contiguous(memory_format=torch.channels_last)
    rgbs, depths = _frames(4, np.random.default_rng(3))
    for rgb, depth in zip(rgbs, depths):
        out = encoder.encode(rgb, depth, want_depth=True)
        with torch.inference_mode():
            mu, _ = plain.encode(preprocess(rgb, depth, plain.cfg))
            np.testing.assert_allclose(out.mu, mu[0].numpy(), atol=1e-5)
            np.testing.assert_allclose(out.pad_xyz, plain.decode_xyz(mu)[0].numpy(), atol=1e-5)
            np.testing.assert_allclose(out.depth, plain.decode_depth(mu)[0].numpy(), atol=1e-4)


def test_construction_warms_every_network_up_once_unless_told_not_to(encoder, monkeypatch):
    """torch's first inference is ~15x slower than the next: the encoder pays it at start-up."""
    calls = {'encode': 0, 'decode_xyz': 0, 'decode_depth': 0}
    for name in calls:
        orig = getattr(CMVAE, name)

        def counting(self, z, _name=name, _orig=orig):
            calls[_name] += 1
            return _orig(self, z)
        monkeypatch.setattr(CMVAE, name, counting)
    LatentEncoder(encoder.model_path, threads=1, warm_up=False, backend='torch')
    assert calls == {'encode': 0, 'decode_xyz': 0, 'decode_depth': 0}
    LatentEncoder(encoder.model_path, threads=1, backend='torch')
    assert all(n >= 1 for n in calls.values()), calls
    # the onnxruntime backend: its sessions run at start-up too, beyond the one probe frame that checks an export
    from assist_perception.onnx_backend import OnnxCMVAE
    runs = []
    orig_call = OnnxCMVAE.__call__
    monkeypatch.setattr(OnnxCMVAE, '__call__', lambda self, rgb, d: runs.append(rgb.shape) or orig_call(self, rgb, d))
    LatentEncoder(encoder.model_path, threads=1, warm_up=False, backend='onnxruntime')
    assert runs == [(1, 64, 64, 3)]                       # the probe check only
    LatentEncoder(encoder.model_path, threads=1, backend='onnxruntime')
    assert len(runs) >= 3, runs                           # its probe check and the warm-up frames
