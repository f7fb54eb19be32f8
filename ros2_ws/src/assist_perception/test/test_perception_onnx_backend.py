"""The ONNX Runtime backend computes what the torch CM-VAE computes, on the shipped and a random model."""
import numpy as np
import pytest
import torch

from assist_perception.encoder_core import BadFrame, LatentEncoder, default_model_path
from assist_perception.model import CMVAE, CMVAEConfig, load_model, preprocess_tensor, save_model
from assist_perception import onnx_backend
from assist_perception.onnx_backend import OnnxCMVAE, export_depth, export_mu_xyz, resolve_backend


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
    # the depth decoder (on demand) runs on ONNX Runtime too and agrees
    np.testing.assert_allclose(ort_enc.encode(rgb[0], depth[0], want_depth=True).depth,
                               torch_enc.encode(rgb[0], depth[0], want_depth=True).depth, atol=1e-6)


def test_export_leaves_the_model_in_its_mode():
    model = load_model(default_model_path())
    model.train()
    export_mu_xyz(model)
    export_depth(model)
    assert model.training


def test_backend_choice():
    assert resolve_backend('auto', 'cpu') == 'onnxruntime'
    assert resolve_backend('torch', 'cpu') == 'torch'
    with pytest.raises(ValueError, match='unknown inference backend'):
        resolve_backend('tensorrt', 'cpu')
    with pytest.raises(ValueError, match='CPU only'):
        resolve_backend('onnxruntime', 'cuda')
    assert resolve_backend('auto', 'cuda') == 'torch'


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


def _small_file(path, seed: int):
    save_model(path, _small(seed))
    return path


def _loader(path):
    return lambda: load_model(path)


def _no_model():
    raise AssertionError('the torch model was loaded although the cache holds this file')


def test_export_cached_by_file_and_reused_without_the_torch_model(tmp_path, monkeypatch):
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path / 'cache'))
    path = _small_file(tmp_path / 'm.pt', 5)
    rgb, depth = _frames(2)
    first = OnnxCMVAE(path, _loader(path))
    key = onnx_backend.export_key(path)
    assert sorted(f.name for f in (tmp_path / 'cache' / 'onnx').iterdir()) == [f'{key}.depth.onnx', f'{key}.json',
                                                                              f'{key}.onnx']
    second = OnnxCMVAE(path, _no_model)
    assert (second.latent_dim, second.image_size) == (8, 64)
    np.testing.assert_array_equal(first(rgb, depth)[0], second(rgb, depth)[0])
    np.testing.assert_array_equal(first.decode_depth(first(rgb, depth)[0]), second.decode_depth(second(rgb, depth)[0]))
    # other weights in the same file: another key, so never the old export
    _small_file(path, 6)
    assert onnx_backend.export_key(path) != key
    with pytest.raises(AssertionError, match='torch model was loaded'):
        OnnxCMVAE(path, _no_model)


def test_a_start_with_a_cached_export_imports_neither_torch_nor_onnx(tmp_path):
    import os
    import subprocess
    import sys
    env = dict(os.environ, ASSIST_CACHE_DIR=str(tmp_path / 'cache'))
    code = ('import sys, numpy as np\n'
            'import assist_perception.encoder_node\n'
            'from assist_perception.encoder_core import LatentEncoder\n'
            'e = LatentEncoder(threads=1)\n'
            'out = e.encode(np.full((48, 64, 3), 100, np.uint8), np.full((48, 64), 2.0, np.float32), want_depth=True)\n'
            'print(e.backend, "torch" in sys.modules, "onnx" in sys.modules, out.mu.shape, out.depth.shape)')
    runs = [subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120, env=env)
            for _ in range(2)]
    assert all(r.returncode == 0 for r in runs), runs[-1].stderr
    assert runs[0].stdout.split()[:2] == ['onnxruntime', 'True']        # the first start exports
    assert runs[1].stdout.split() == ['onnxruntime', 'False', 'False', '(10,)', '(64,', '64)']


@pytest.mark.parametrize('damage', ['corrupt', 'other_model', 'bad_probe', 'no_depth'])
def test_a_bad_cache_entry_is_exported_again_and_replaced(damage, tmp_path, monkeypatch, caplog):
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path))
    path = _small_file(tmp_path / 'm.pt', 7)
    OnnxCMVAE(path, _loader(path))
    key = onnx_backend.export_key(path)
    onnx_file, probe = tmp_path / 'onnx' / f'{key}.onnx', tmp_path / 'onnx' / f'{key}.json'
    if damage == 'corrupt':
        onnx_file.write_bytes(b'\x00garbage')
    elif damage == 'other_model':
        onnx_file.write_bytes(export_mu_xyz(_small(8)))
    elif damage == 'bad_probe':
        probe.write_text('{"latent_dim": 8')
    else:
        (tmp_path / 'onnx' / f'{key}.depth.onnx').unlink()
    rgb, depth = _frames(3)
    enc = OnnxCMVAE(path, _loader(path))
    assert 'is not usable' in caplog.text
    model = load_model(path)
    with torch.no_grad():
        mu_t, _ = model.encode(preprocess_tensor(torch.from_numpy(rgb), torch.from_numpy(depth), model.cfg))
    np.testing.assert_allclose(enc(rgb, depth)[0], mu_t.numpy(), atol=2e-5, rtol=1e-5)
    caplog.clear()
    OnnxCMVAE(path, _no_model)                                  # the replaced entry is good
    assert 'is not usable' not in caplog.text


def test_an_export_that_disagrees_with_torch_is_never_run(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path / 'cache'))
    monkeypatch.setattr(onnx_backend, 'PROBE_TOL', -1.0)         # no export can pass: as if ORT computed otherwise
    path = _small_file(tmp_path / 'm.pt', 2)
    with pytest.raises(ValueError, match='differs from torch'):
        LatentEncoder(path, backend='onnxruntime')
    enc = LatentEncoder(path, backend='auto')
    assert enc.backend == 'torch' and 'running it on torch' in caplog.text
    assert not (tmp_path / 'cache' / 'onnx').exists()


def test_cache_off_unwritable_and_pruned(tmp_path, monkeypatch, caplog):
    paths = [_small_file(tmp_path / f'm{seed}.pt', seed) for seed in (1, 2, 3)]
    monkeypatch.setenv('ASSIST_CACHE_DIR', 'off')
    OnnxCMVAE(paths[0], _loader(paths[0]))
    assert onnx_backend.cache_dir() is None
    blocker = tmp_path / 'file'
    blocker.write_text('a file where the cache folder would be')
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(blocker))
    rgb, depth = _frames(1)
    assert OnnxCMVAE(paths[0], _loader(paths[0]))(rgb, depth)[0].shape == (1, 8)    # works, the failure only logged
    assert 'could not cache' in caplog.text
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path / 'c'))
    monkeypatch.setattr(onnx_backend, 'CACHE_KEEP', 2)
    for path in paths:
        OnnxCMVAE(path, _loader(path))
    kept = {f.name.split('.')[0] for f in (tmp_path / 'c' / 'onnx').iterdir()}
    assert kept == {onnx_backend.export_key(paths[1]), onnx_backend.export_key(paths[2])}
    assert len(list((tmp_path / 'c' / 'onnx').iterdir())) == 6          # whole entries: onnx, depth and probe
