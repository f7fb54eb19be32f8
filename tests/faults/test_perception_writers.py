"""Kill-and-resume, assist_perception writers: train_cmvae (checkpoint.pt + metrics.csv) and make_dataset
(shards + meta.json). A run killed at any point resumes to what an uninterrupted run produces.
"""
from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from assist_lab import cmvae_train as train_mod
from assist_lab.cmvae_dataset import DatasetConfig, load_frames, make_dataset
from assist_lab.cmvae_train import TrainConfig, train

BIN = Path(sys.executable).parent


@pytest.fixture(scope='module')
def frames(tmp_path_factory):
    out = tmp_path_factory.mktemp('ds')
    make_dataset(DatasetConfig(out_dir=str(out), frames=120, frames_per_scene=40, scenes_per_shard=3, seed=3),
                 progress=False)
    return load_frames(out)


def _cfg(run_dir, **kw) -> TrainConfig:
    return TrainConfig(**{**dict(run_dir=str(run_dir), epochs=3, batch_size=32, lr=2e-3, warmup_steps=2,
                                 val_fraction=0.34, kl_warmup_epochs=1.0, seed=1), **kw})


def _epochs(run_dir):
    with open(run_dir / 'metrics.csv', newline='') as fh:
        return [int(r['epoch']) for r in csv.DictReader(fh)]


def test_crash_between_metrics_row_and_checkpoint_is_not_counted_twice(frames, tmp_path, monkeypatch):
    """metrics.csv rows written after the last checkpoint used to be duplicated on resume."""
    torch.set_num_threads(1)
    run = tmp_path / 'run'
    real_atomic, calls = train_mod.atomic_path, []

    def crashing(path):
        if Path(path).name == 'checkpoint.pt':
            calls.append(path)
            if len(calls) == 2:            # epoch 2: its metrics row is written, its checkpoint is not
                raise KeyboardInterrupt('killed before the checkpoint')
        return real_atomic(path)
    monkeypatch.setattr(train_mod, 'atomic_path', crashing)
    with pytest.raises(KeyboardInterrupt):
        train(_cfg(run), frames=frames, progress=False)
    assert _epochs(run) == [1, 2]
    assert torch.load(run / 'checkpoint.pt', weights_only=True)['epoch'] == 0      # epoch 1 (0-based)
    monkeypatch.setattr(train_mod, 'atomic_path', real_atomic)
    train(_cfg(run, resume=True), frames=frames, progress=False)
    assert _epochs(run) == [1, 2, 3]


@pytest.mark.slow
def test_make_dataset_killed_mid_shard_resumes_to_the_same_dataset(tmp_path):
    flags = ['--frames', '240', '--frames-per-scene', '40', '--scenes-per-shard', '1', '--seed', '11',
             '--no-progress']
    ref = tmp_path / 'ref'
    clean = subprocess.Popen([str(BIN / 'make_dataset'), '--out-dir', str(ref), *flags],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    out = tmp_path / 'ds'
    proc = subprocess.Popen([str(BIN / 'make_dataset'), '--out-dir', str(out), *flags],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        end = time.monotonic() + 300
        while not list(out.glob('shard_*.npz')) and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.05)
        time.sleep(0.1)                    # into the next shard
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    shards = sorted(p.name for p in out.glob('shard_*.npz'))
    assert 1 <= len(shards) < 6 and (out / 'meta.json').is_file()
    for p in out.glob('shard_*.npz'):      # every shard on disk is complete
        with np.load(p) as z:
            assert len(z['visible']) == 40
    done = subprocess.run([str(BIN / 'make_dataset'), '--out-dir', str(out), *flags], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert clean.wait(timeout=600) == 0
    assert not [p for p in out.iterdir() if p.name.startswith('.')]      # no temporaries left behind
    a, b = load_frames(out), load_frames(ref)
    assert len(a) == len(b) == 240
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.visible, b.visible)
