"""The ONNX Runtime backend computes what the torch CM-VAE computes, on the shipped and a random model."""
import numpy as np
import pytest
import torch

from assist_perception.encoder_core import BadFrame, LatentEncoder, default_model_path
from assist_perception.model import CMVAE, CMVAEConfig, load_model, preprocess_tensor, save_model
from assist_perception.onnx_backend import OnnxMuXyz, resolve_backend


def _frames(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rgb = rng.integers(0, 256, (n, 64, 64, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 6.0, (n, 64, 64)).astype(np.float32)
    depth[:, :5, :5] = 0.0                                  # a hole, as real depth has
    return rgb, depth


@pytest.mark.parametrize('which', ['shipped', 'random'])
def test_mu_and_xyz_match_torch(which, tmp_path):
    if which == 'shipped':
        path = default_model_path()
    else:
        torch.manual_seed(3)
        path = tmp_path / 'm.pt'
        save_model(path, CMVAE(CMVAEConfig(latent_dim=8)).eval())
    ort_enc = LatentEncoder(path, threads=1, backend='onnxruntime')
    torch_enc = LatentEncoder(path, threads=1, backend='torch')
    assert (ort_enc.backend, torch_enc.backend) == ('onnxruntime', 'torch')
    rgb, depth = _frames(6)
    for i in range(6):
        a, b = ort_enc.encode(rgb[i], depth[i]), torch_enc.encode(rgb[i], depth[i])
        np.testing.assert_allclose(a.mu, b.mu, atol=2e-5, rtol=1e-5)
        np.testing.assert_allclose(a.pad_xyz, b.pad_xyz, atol=2e-5, rtol=1e-5)
        assert a.mu.dtype == np.float32 and a.mu.shape == (ort_enc.latent_dim,)
    # batched (vectorised envs): one ORT run with a dynamic batch axis
    np.testing.assert_allclose(ort_enc.encode_mu_batch(list(rgb), list(depth)),
                               torch_enc.encode_mu_batch(list(rgb), list(depth)), atol=2e-5, rtol=1e-5)
    # the depth decoder (on demand) still runs on torch and agrees
    np.testing.assert_allclose(ort_enc.encode(rgb[0], depth[0], want_depth=True).depth,
                               torch_enc.encode(rgb[0], depth[0], want_depth=True).depth, atol=1e-6)


def test_export_leaves_the_model_in_its_mode():
    model = load_model(default_model_path())
    model.train()
    OnnxMuXyz(model)
    assert model.training


def test_backend_choice():
    cpu = torch.device('cpu')
    assert resolve_backend('auto', cpu) == 'onnxruntime'
    assert resolve_backend('torch', cpu) == 'torch'
    with pytest.raises(ValueError, match='unknown inference backend'):
        resolve_backend('tensorrt', cpu)
    with pytest.raises(ValueError, match='CPU only'):
        resolve_backend('onnxruntime', torch.device('cuda'))
    assert resolve_backend('auto', torch.device('cuda')) == 'torch'


def test_onnx_backend_rejects_what_torch_rejects():
    enc = LatentEncoder(threads=1, backend='onnxruntime')
    rgb, depth = _frames(1)
    with pytest.raises(BadFrame, match='no_valid_depth'):
        enc.encode(rgb[0], np.zeros((64, 64), np.float32))
    with pytest.raises(BadFrame, match='frame 1'):
        enc.encode_mu_batch([rgb[0], rgb[0]], [depth[0], np.zeros((64, 64), np.float32)])


def test_preprocess_is_the_documented_scaling_bit_for_bit():
    """preprocess (torch ops, exported into the ONNX graph) == the numpy formula training always used."""
    from assist_perception.model import preprocess
    cfg = CMVAEConfig()
    rgb, depth = _frames(3, seed=5)
    depth = depth * 3.0
    depth[0, 0, :6] = [np.nan, np.inf, -np.inf, -1.0, 0.0, cfg.max_input_depth_m]
    d = np.where(np.isfinite(depth) & (depth > 0) & (depth <= cfg.max_input_depth_m), depth, 0.0)
    ref = np.empty((3, 4, 64, 64), np.float32)
    ref[:, :3] = np.moveaxis(rgb, -1, 1).astype(np.float32) / 255.0
    ref[:, 3] = d / cfg.depth_scale_m
    out = preprocess(rgb, depth, cfg).numpy()
    assert out.dtype == np.float32 and np.array_equal(out, ref)


def _small(seed: int) -> CMVAE:
    torch.manual_seed(seed)
    return CMVAE(CMVAEConfig(latent_dim=8)).eval()


def test_export_cached_by_weights_and_reused(tmp_path, monkeypatch):
    from assist_perception import onnx_backend
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path / 'cache'))
    model = _small(5)
    rgb, depth = _frames(2)
    first = OnnxMuXyz(model)
    files = list((tmp_path / 'cache' / 'onnx').glob('*.onnx'))
    assert [f.stem for f in files] == [onnx_backend.export_key(model)]

    def no_export(_model):
        raise AssertionError('exported although the cache holds this model')
    monkeypatch.setattr(onnx_backend, 'export_mu_xyz', no_export)
    second = OnnxMuXyz(model)
    np.testing.assert_array_equal(first(rgb, depth)[0], second(rgb, depth)[0])
    # other weights: another key (here refused because exporting is patched out)
    other = _small(6)
    assert onnx_backend.export_key(other) != onnx_backend.export_key(model)
    with pytest.raises(AssertionError, match='exported although'):
        OnnxMuXyz(other)


@pytest.mark.parametrize('damage', ['corrupt', 'other_model'])
def test_a_bad_cache_file_is_exported_again_and_replaced(damage, tmp_path, monkeypatch, caplog):
    from assist_perception import onnx_backend
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path))
    model = _small(7)
    path = tmp_path / 'onnx' / f'{onnx_backend.export_key(model)}.onnx'
    path.parent.mkdir()
    path.write_bytes(b'\x00garbage' if damage == 'corrupt' else onnx_backend.export_mu_xyz(_small(8)))
    rgb, depth = _frames(3)
    enc = OnnxMuXyz(model)
    assert 'is not usable' in caplog.text
    with torch.no_grad():
        mu_t, _ = model.encode(preprocess_tensor(torch.from_numpy(rgb), torch.from_numpy(depth), model.cfg))
    np.testing.assert_allclose(enc(rgb, depth)[0], mu_t.numpy(), atol=2e-5, rtol=1e-5)
    caplog.clear()
    OnnxMuXyz(model)                                            # the replaced file is good
    assert 'is not usable' not in caplog.text


def test_cache_off_unwritable_and_pruned(tmp_path, monkeypatch, caplog):
    from assist_perception import onnx_backend
    monkeypatch.setenv('ASSIST_CACHE_DIR', 'off')
    OnnxMuXyz(_small(1))
    assert onnx_backend.cache_dir() is None
    blocker = tmp_path / 'file'
    blocker.write_text('a file where the cache folder would be')
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(blocker))
    rgb, depth = _frames(1)
    assert OnnxMuXyz(_small(1))(rgb, depth)[0].shape == (1, 8)      # works, the failure only logged
    assert 'could not cache' in caplog.text
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path / 'c'))
    monkeypatch.setattr(onnx_backend, 'CACHE_KEEP', 2)
    for seed in (1, 2, 3):
        OnnxMuXyz(_small(seed))
    kept = {f.stem for f in (tmp_path / 'c' / 'onnx').glob('*.onnx')}
    assert kept == {onnx_backend.export_key(_small(2)), onnx_backend.export_key(_small(3))}
