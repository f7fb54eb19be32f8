"""The actor on ONNX Runtime: the same outputs as torch for every kind of actor, a cache keyed by the file's bytes
that a start reads without importing torch, and a bad cache entry or export never used."""
from __future__ import annotations

import json
import logging
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from assist_policy import actor_runtime
from assist_policy.actor import build_actor, save_actor, validate_actor_meta
from assist_policy.actor_runtime import OnnxActor, TorchActor, load_actor_runtime, observation_size
from assist_policy.observation import history_steps, vector_dim

LATENT = 2


def write_actor(path, kind: str, seed: int = 0):
    """A randomly initialised actor file: 'mlp' (latent), 'memory' (a GRU window and a goal head), 'image'."""
    torch.manual_seed(seed)
    if kind == 'memory':
        steps = history_steps(1.0, 0.5)
        meta = {'vec_dim': vector_dim('latent', LATENT, n_history=steps), 'hidden': [16, 16], 'condition': 'latent',
                'latent_dim': LATENT, 'history_s': 1.0, 'history_step_s': 0.5, 'history_hidden': 6, 'goal_head': True}
    elif kind == 'image':
        meta = {'vec_dim': vector_dim('end_to_end', 0), 'hidden': [16], 'condition': 'end_to_end', 'image': True,
                'image_channels': [4, 4]}
    else:
        meta = {'vec_dim': vector_dim('latent', LATENT), 'hidden': [16, 16], 'condition': 'latent',
                'latent_dim': LATENT}
    meta = validate_actor_meta(meta)
    save_actor(build_actor(meta), meta, path)
    return path


@pytest.fixture
def cache(monkeypatch, tmp_path):
    folder = tmp_path / 'cache'
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(folder))
    return folder / actor_runtime.CACHE_FOLDER


@pytest.mark.parametrize('kind', ['mlp', 'memory', 'image'])
def test_onnxruntime_gives_torch_s_action_and_goal_for_every_kind_of_actor(tmp_path, cache, kind):
    path = write_actor(tmp_path / 'a.pt', kind)
    ort, ref = load_actor_runtime(path, 'onnxruntime'), load_actor_runtime(path, 'torch')
    assert isinstance(ort, OnnxActor) and isinstance(ref, TorchActor) and ort.meta == ref.meta
    rng = np.random.default_rng(3)
    for _ in range(10):
        obs = rng.normal(0.0, 2.0, observation_size(ort.meta)).astype(np.float32)
        pos = rng.normal(0.0, 3.0, 3)
        (a, goal), (b, goal_ref) = ort(obs, pos), ref(obs, pos)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-5)      # float32 kernels of two libraries: ~1e-6 apart
        assert (goal is None) == (goal_ref is None) == (kind != 'memory')
        if goal is not None:
            np.testing.assert_allclose(goal.mean, goal_ref.mean, rtol=0, atol=1e-4)
            assert goal.sigma_m == pytest.approx(goal_ref.sigma_m, rel=1e-4)
    assert sorted(p.suffix for p in cache.iterdir()) == ['.json', '.onnx']


def test_a_start_with_a_cached_export_imports_neither_torch_nor_onnx(tmp_path, cache):
    """policy_node's module and its core on the auto backend: with the export cached, no torch, no onnx."""
    path = write_actor(tmp_path / 'a.pt', 'memory')
    load_actor_runtime(path, 'onnxruntime')                       # fills the cache
    code = ('import sys, numpy as np\n'
            'import assist_policy.policy_node\n'
            'from assist_policy.actor_runtime import observation_size\n'
            'from assist_policy.policy_core import PolicyCore, PolicyCoreConfig\n'
            f'a = PolicyCore({str(path)!r}, PolicyCoreConfig(mode="latent"), "auto").actor\n'
            'raw, goal = a(np.zeros(observation_size(a.meta), np.float32), np.zeros(3))\n'
            'print(type(a).__name__, "torch" in sys.modules, "onnx" in sys.modules, raw.shape, goal is not None)')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, ASSIST_CACHE_DIR=str(cache.parent)))
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ['OnnxActor', 'False', 'False', '(3,)', 'True']


def test_another_file_is_another_entry_and_a_changed_file_is_never_served_the_old_export(tmp_path, cache):
    path = write_actor(tmp_path / 'a.pt', 'mlp', seed=0)
    obs = np.ones(observation_size(load_actor_runtime(path, 'onnxruntime').meta), np.float32)
    write_actor(path, 'mlp', seed=1)                              # same name, other weights
    ort, ref = load_actor_runtime(path, 'onnxruntime'), load_actor_runtime(path, 'torch')
    np.testing.assert_allclose(ort(obs, np.zeros(3))[0], ref(obs, np.zeros(3))[0], rtol=0, atol=1e-5)
    assert len(list(cache.glob('*.onnx'))) == 2


@pytest.mark.parametrize('damage', ['corrupt onnx', 'other probe', 'missing probe', 'bad metadata'])
def test_a_bad_cache_entry_is_exported_again_and_replaced(tmp_path, cache, caplog, damage):
    path = write_actor(tmp_path / 'a.pt', 'memory')
    load_actor_runtime(path, 'onnxruntime')
    onnx_file = next(cache.glob('*.onnx'))
    probe_file = onnx_file.with_suffix('.json')
    entry = json.loads(probe_file.read_text())
    if damage == 'corrupt onnx':
        onnx_file.write_bytes(b'\x00not an onnx model')
    elif damage == 'other probe':                               # an export that no longer gives what torch gave
        entry['action'] = (np.asarray(entry['action']) + 0.01).tolist()
        probe_file.write_text(json.dumps(entry))
    elif damage == 'missing probe':
        probe_file.unlink()
    else:
        entry['meta']['hidden'] = 'wide'
        probe_file.write_text(json.dumps(entry))
    with caplog.at_level(logging.WARNING, logger='assist_policy.actor_runtime'):
        ort = load_actor_runtime(path, 'onnxruntime')
    if damage != 'missing probe':                                # a missing probe is a plain miss
        assert 'not usable' in caplog.text and 'exporting it again' in caplog.text
    ref = load_actor_runtime(path, 'torch')
    obs = np.full(observation_size(ref.meta), 0.3, np.float32)
    np.testing.assert_allclose(ort(obs, np.zeros(3))[0], ref(obs, np.zeros(3))[0], rtol=0, atol=1e-5)
    assert onnx_file.read_bytes()[:4] != b'\x00not' and json.loads(probe_file.read_text())['meta']['hidden'] == [16, 16]


def test_cache_off_or_unwritable_still_runs_the_export(tmp_path, monkeypatch, caplog):
    path = write_actor(tmp_path / 'a.pt', 'mlp')
    monkeypatch.setenv('ASSIST_CACHE_DIR', 'off')
    assert isinstance(load_actor_runtime(path, 'onnxruntime'), OnnxActor)
    blocker = tmp_path / 'file'
    blocker.write_text('a file where the cache folder would be')
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(blocker))
    with caplog.at_level(logging.WARNING):
        assert isinstance(load_actor_runtime(path, 'onnxruntime'), OnnxActor)
    assert 'could not cache' in caplog.text


def test_an_export_that_disagrees_with_torch_is_never_flown(tmp_path, cache, monkeypatch, caplog):
    path = write_actor(tmp_path / 'a.pt', 'mlp')
    monkeypatch.setattr(actor_runtime, 'PROBE_TOL', -1.0)         # no export can pass: as if ORT computed otherwise
    with pytest.raises(ValueError, match='differs from torch'):
        load_actor_runtime(path, 'onnxruntime')
    with caplog.at_level(logging.WARNING):
        assert isinstance(load_actor_runtime(path, 'auto'), TorchActor)
    assert 'running it on torch' in caplog.text
    assert not list(cache.glob('*.onnx')) if cache.exists() else True


def test_bad_files_and_backends_are_one_line(tmp_path, cache):
    with pytest.raises(ValueError, match='unknown actor backend'):
        load_actor_runtime(write_actor(tmp_path / 'a.pt', 'mlp'), 'tensorrt')
    with pytest.raises(ValueError, match='actor file not found'):
        load_actor_runtime(tmp_path / 'missing.pt', 'onnxruntime')
    (tmp_path / 'junk.pt').write_bytes(b'not a torch file')
    for backend in ('onnxruntime', 'auto', 'torch'):
        with pytest.raises(ValueError, match='cannot load actor'):
            load_actor_runtime(tmp_path / 'junk.pt', backend)
