"""Kill-and-resume, assist_policy writers: train_td3 checkpoints (+ metrics.csv, eval.csv) and evaluate's
landings.csv. A run killed at any point resumes to the state a run that was never killed reaches:
no transition lost, no landing counted twice, earlier results never wiped.
"""
from __future__ import annotations

import csv
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from assist_lab.td3 import ReplayBuffer
from assist_lab.train import TrainArgs, load_checkpoint, train

BIN = Path(sys.executable).parent
TINY = dict(start_steps=100, checkpoint_every_steps=100, eval_every_episodes=1000, eval_episodes_per_beta=1,
            hidden=(32, 32), max_episode_s=4.0, buffer_size=5000)


def assert_consistent(run: Path, min_step: int) -> None:
    """The last checkpoint's buffer holds exactly its steps; metrics episodes are 1..N, each once."""
    state, replay = load_checkpoint(run)
    assert state['step'] >= min_step
    with np.load(replay) as data:
        assert len(data['obs']) == state['step'] == state['buffer_size'], (len(data['obs']), state['step'])
    episodes = [int(r['episode']) for r in csv.DictReader(open(run / 'metrics.csv'))]
    assert episodes == list(range(1, len(episodes) + 1)), episodes
    assert len(episodes) >= state['episode']


def test_crash_between_checkpoint_files_loses_no_transitions(tmp_path, monkeypatch):
    """A crash between replacing ckpt.pt and replay.npz used to resume 'at step 400 ... buffer 200',
    and the metrics rows after the checkpoint were written twice."""
    torch.set_num_threads(1)
    real_save, calls = ReplayBuffer.save, []

    def crashing_save(self, path):
        calls.append(path)
        if len(calls) == 2:                 # the second checkpoint dies after its state file
            raise KeyboardInterrupt('killed while writing replay.npz')
        real_save(self, path)
    monkeypatch.setattr(ReplayBuffer, 'save', crashing_save)
    with pytest.raises(KeyboardInterrupt):
        train(TrainArgs(name='crash', runs_dir=str(tmp_path), total_steps=300, **TINY))
    run = tmp_path / 'crash'
    state, _ = load_checkpoint(run)
    assert state['step'] == 100                                 # the first, complete checkpoint
    monkeypatch.setattr(ReplayBuffer, 'save', real_save)
    train(TrainArgs(resume=str(run), total_steps=300))
    assert_consistent(run, 300)


def _train_cmd(*args):
    return [str(BIN / 'train_td3'), *args]


@pytest.mark.slow
def test_sigkill_at_a_random_moment_then_resume(tmp_path):
    flags = ['--start-steps', '100', '--checkpoint-every-steps', '100', '--eval-every-episodes', '3',
             '--eval-episodes-per-beta', '1', '--hidden', '32', '32', '--max-episode-s', '4',
             '--buffer-size', '5000', '--torch-threads', '1']
    run = tmp_path / 'k'
    env = dict(os.environ, PYTHONUNBUFFERED='1')
    proc = subprocess.Popen(_train_cmd('--name', 'k', '--runs-dir', str(tmp_path), '--total-steps', '500', *flags),
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        end = time.monotonic() + 300
        while not (run / 'checkpoint').is_dir() and proc.poll() is None and time.monotonic() < end:
            time.sleep(0.1)
        time.sleep(random.uniform(0.0, 1.0))
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    done = subprocess.run(_train_cmd('--resume', str(run), '--total-steps', '500'), env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert_consistent(run, 500)
    evals = [(int(r['episode']), int(r['step'])) for r in csv.DictReader(open(run / 'eval.csv'))]
    assert len(set(evals)) == len(evals) and evals == sorted(evals), evals


# ------------------------------------------------------------------ evaluate
EVAL = ['--conditions', 'scripted_oracle', '--betas', '0', '1', '--landings', '3', '--max-episode-s', '20',
        '--plot', 'false']


def _evaluate(out, **kw):
    return subprocess.Popen([str(BIN / 'evaluate'), '--out', str(out), *EVAL], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True, **kw)


def _rows(path):
    return [{k: v for k, v in r.items()} for r in csv.DictReader(open(path))]


@pytest.mark.slow
def test_evaluate_killed_keeps_earlier_results_and_resumes(tmp_path):
    clean = _evaluate(tmp_path / 'clean')
    out = tmp_path / 'out'
    out.mkdir()
    earlier = 'condition,beta,seed\nunassisted,0.0,1\n'
    (out / 'landings.csv').write_text(earlier)                # results of an earlier run
    proc = _evaluate(out)
    try:
        partial = out / 'landings.partial.csv'
        end = time.monotonic() + 300
        while (not partial.exists() or len(partial.read_text().splitlines()) < 3) and proc.poll() is None \
                and time.monotonic() < end:
            time.sleep(0.05)
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        # killed mid-run: the earlier results are still there, untouched
        assert (out / 'landings.csv').read_text() == earlier
        flown = partial.read_text().count('\n') - 1          # complete rows (a torn one is dropped)
        assert 2 <= flown < 6
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    again = subprocess.run([str(BIN / 'evaluate'), '--out', str(out), *EVAL], capture_output=True, text=True,
                           timeout=600)
    assert again.returncode == 0, again.stderr[-2000:]
    assert f'resuming: {flown} landings already flown' in again.stderr
    assert clean.wait(timeout=600) == 0, clean.stderr.read().decode()[-2000:]
    # the resumed run's table has the uninterrupted run's landings, each once, in order; the ones flown
    # before the kill are kept exactly as flown. (The landings flown after the resume are not compared
    # number for number: a landing's outcome also depends on what its process flew before.)
    resumed, ref = _rows(out / 'landings.csv'), _rows(tmp_path / 'clean' / 'landings.csv')
    pairing = ('condition', 'beta', 'seed', 'scene_seed', 'goal_index')
    assert [[r[k] for k in pairing] for r in resumed] == [[r[k] for k in pairing] for r in ref]
    assert resumed[:flown] == ref[:flown]
    assert not (out / 'landings.partial.csv').exists() and not (out / 'landings.partial.json').exists()


def test_evaluate_with_nothing_to_fly_keeps_earlier_results(tmp_path):
    from assist_lab.evaluate import EvalArgs, evaluate
    (tmp_path / 'landings.csv').write_text('earlier results\n')
    assert evaluate(EvalArgs(out=str(tmp_path), conditions=('latent',), latent_model=str(tmp_path / 'no.pt'),
                             betas=(0.0,), landings=1)) == {}
    assert (tmp_path / 'landings.csv').read_text() == 'earlier results\n'
