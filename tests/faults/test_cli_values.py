"""Command-line values of train_td3, train_cmvae, make_dataset and evaluate_cmvae are checked before any work.

A bad value (out of range, NaN or infinite, not a number, not one of the choices, a run name that is a
path) ends the command with one `error:` line and exit status 2, as argparse reports a malformed flag:
no traceback, no file written. A resumed run refuses flags that differ from the settings it was started
with (naming them), a damaged checkpoint is one `error:` line (status 1), and a diverging CM-VAE run
stops before it writes non-finite weights.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import math
import os
import tempfile
import typing
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from assist_lab import cmvae_dataset as dataset, cmvae_evaluate as evaluate
from assist_lab import cmvae_train as ctrain
from assist_common.settings import RULE_KEY, SettingsError, flag
from assist_perception.model import load_model
from assist_lab import train as ptrain

# command -> (entry point, settings dataclass, module and name of the function that does the work)
CLIS = {
    'train_td3': (ptrain.main, ptrain.TrainArgs, ptrain, 'train'),
    'train_cmvae': (ctrain.main, ctrain.TrainConfig, ctrain, 'train'),
    'make_dataset': (dataset.main, dataset.DatasetConfig, dataset, 'make_dataset'),
    'evaluate_cmvae': (evaluate.main, evaluate.EvalConfig, evaluate, 'evaluate'),
}
BOOL_WORDS = {'1', 'true', 'yes', 'on', '0', 'false', 'no', 'off'}


@pytest.fixture
def no_work(monkeypatch):
    """Replace every command's work function: a bad value that got through fails fast instead of training."""
    for _, _, module, name in CLIS.values():
        def ran(*args, _name=name, **kwargs):
            raise AssertionError(f'{_name} ran with a bad value')
        monkeypatch.setattr(module, name, ran)


def run_cli(command: str, argv: list[str]) -> tuple[int | str | None, str]:
    """(exit status, stderr) of `command` run in-process on `argv` in the current directory."""
    main = CLIS[command][0]
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as stop:
            code = stop.code
    return code, err.getvalue()


def assert_refused(command: str, argv: list[str], status: int = 2) -> str:
    """Run `command` in an empty directory: `status`, one `<command>: error:` line, no traceback, no file."""
    with tempfile.TemporaryDirectory() as tmp:
        here = os.getcwd()
        os.chdir(tmp)
        try:
            code, err = run_cli(command, argv)
        finally:
            os.chdir(here)
        written = sorted(str(p.relative_to(tmp)) for p in Path(tmp).rglob('*'))
    errors = [line for line in err.splitlines() if 'error:' in line]
    assert code == status, (argv, code, err)
    assert len(errors) == 1 and errors[0].startswith(f'{command}: error: '), (argv, err)
    assert err.rstrip().splitlines()[-1] == errors[0] and 'Traceback' not in err, (argv, err)
    assert not written, (argv, written)
    return errors[0]


# ------------------------------------------------------------------ hand-picked values (audit examples)
AUDIT = [
    ('train_td3', ['--buffer-size', '0'], '--buffer-size'),
    ('train_td3', ['--checkpoint-every-steps', '0'], '--checkpoint-every-steps'),
    ('train_td3', ['--actor-lr', 'nan'], '--actor-lr'),
    ('train_td3', ['--eval-every-episodes', '0'], '--eval-every-episodes'),
    ('train_td3', ['--eval-episodes-per-beta', '0'], '--eval-episodes-per-beta'),
    ('train_td3', ['--ou-decay', '-0.5'], '--ou-decay'),
    ('train_td3', ['--updates-per-step', 'inf'], '--updates-per-step'),
    ('train_td3', ['--torch-threads', '0'], '--torch-threads'),
    ('train_td3', ['--seed', '-1'], '--seed'),
    ('train_td3', ['--max-episode-s', '0'], '--max-episode-s'),
    ('train_td3', ['--alpha', '1.5'], '--alpha'),
    ('train_td3', ['--hidden', '0'], '--hidden'),          # an actor load_actor refuses
    ('train_td3', ['--hidden'], '--hidden'),
    ('train_td3', ['--condition', 'latnet'], '--condition'),
    ('train_td3', ['--demo-policy', 'nobody'], '--demo-policy'),
    ('train_td3', ['--feature-lags-s', '-1'], '--feature-lags-s'),
    ('train_td3', ['--feature-lags-s', *['1'] * 9], '--feature-lags-s'),
    ('train_td3', ['--memory-displacement', 'true'], '--memory-displacement'),
    ('train_td3', ['--pilot', 'mix'], '--pilot'),
    ('train_td3', ['--dagger-rounds', '2'], '--dagger-rounds'),
    ('train_td3', ['--demo-policy', 'init_actor'], '--demo-policy'),
    ('train_td3', ['--name', '../../x'], '--name'),
    ('train_td3', ['--name', 'a/b'], '--name'),
    ('train_td3', ['--name', ''], '--name'),
    ('train_td3', ['--preload', 'missing.npz'], '--preload'),
    ('train_td3', ['--init-actor', 'missing.pt'], '--init-actor'),
    ('train_td3', ['--resume', 'no_such_run'], '--resume'),
    ('train_cmvae', ['--w-kl', 'nan'], '--w-kl'),
    ('train_cmvae', ['--lr', '0'], '--lr'),
    ('train_cmvae', ['--lr-min', '0.5', '--lr', '0.1'], '--lr-min'),
    ('train_cmvae', ['--batch-size', '0'], '--batch-size'),
    ('train_cmvae', ['--epochs', '0'], '--epochs'),
    ('train_cmvae', ['--latent-dim', '0'], '--latent-dim'),
    ('train_cmvae', ['--val-fraction', '1'], '--val-fraction'),
    ('train_cmvae', ['--depth-sigma-m', '-inf'], '--depth-sigma-m'),
    ('train_cmvae', ['--config', 'missing.yaml'], '--config'),
    ('make_dataset', ['--max-altitude-m', 'nan'], '--max-altitude-m'),
    ('make_dataset', ['--max-altitude-m', '0.2'], '--max-altitude-m'),
    ('make_dataset', ['--max-altitude-m', '1000'], '--max-altitude-m'),
    ('make_dataset', ['--frames', '0'], '--frames'),
    ('make_dataset', ['--frames-per-scene', '-5'], '--frames-per-scene'),
    ('make_dataset', ['--scenes-per-shard', '0'], '--scenes-per-shard'),
    ('make_dataset', ['--seed', '-1'], '--seed'),
    ('make_dataset', ['--min-pad-pixels', '0'], '--min-pad-pixels'),
    ('make_dataset', ['--min-clearance-m', '0'], '--min-clearance-m'),
    ('make_dataset', ['--surface-tol-m', 'nan'], '--surface-tol-m'),
    ('evaluate_cmvae', ['--steps', '1'], '--steps'),
    ('evaluate_cmvae', ['--pairs', '0'], '--pairs'),
    ('evaluate_cmvae', ['--split', 'test'], '--split'),
    ('evaluate_cmvae', ['--batch-size', '0'], '--batch-size'),
]


@pytest.mark.parametrize('command, argv, named', AUDIT, ids=[f'{c}{" ".join(a)[:40]}' for c, a, _ in AUDIT])
def test_a_bad_value_is_one_error_line_and_exit_2(no_work, command, argv, named):
    assert named in assert_refused(command, argv)


@pytest.mark.parametrize('command, text, named', [
    ('train_cmvae', 'w_kl: .nan\n', '--w-kl'),
    ('train_cmvae', 'epochs: many\n', '--epochs'),
    ('make_dataset', 'max_altitude_m: .nan\n', '--max-altitude-m'),
    ('make_dataset', 'frames: 0\n', '--frames'),
    ('evaluate_cmvae', 'split: [val]\n', '--split'),
    ('evaluate_cmvae', 'pairs: [\n', '--config'),                # not YAML
])
def test_a_bad_value_in_a_config_file_is_refused_the_same_way(no_work, tmp_path, command, text, named):
    config = tmp_path / 'settings.yaml'
    config.write_text(text)
    assert named in assert_refused(command, ['--config', str(config)])


# ------------------------------------------------------------------ property: random bad values of every rule
def _number_text(value) -> str:
    return str(value) if isinstance(value, int) else repr(float(value))


def _bad_items(hint, rule) -> list[st.SearchStrategy[str]]:
    """Strategies of command-line words that break type `hint` (int, float, str, bool) or `rule`."""
    out: list[st.SearchStrategy[str]] = []
    if hint in (int, float):
        out.append(st.sampled_from(['nan', 'inf', '-inf', 'NaN', 'abc', '', '1..2', '0x1g', '--']))
        if hint is int:
            out.append(st.floats(allow_nan=False, allow_infinity=False)
                       .filter(lambda x: not float(x).is_integer()).map(repr))
        if rule is not None:
            if rule.ge is not None:
                out.append(st.integers(max_value=math.ceil(rule.ge) - 1).map(str) if hint is int else
                           st.floats(max_value=rule.ge, exclude_max=True, allow_nan=False).map(_number_text))
            if rule.gt is not None:
                out.append(st.integers(max_value=math.floor(rule.gt)).map(str) if hint is int else
                           st.floats(max_value=rule.gt, allow_nan=False).map(_number_text))
            if rule.le is not None:
                out.append(st.integers(min_value=math.floor(rule.le) + 1).map(str) if hint is int else
                           st.floats(min_value=rule.le, exclude_min=True, allow_nan=False).map(_number_text))
            if rule.lt is not None:
                out.append(st.integers(min_value=math.ceil(rule.lt)).map(str) if hint is int else
                           st.floats(min_value=rule.lt, allow_nan=False).map(_number_text))
    elif hint is bool:
        out.append(st.text(max_size=8).filter(lambda t: t.strip().lower() not in BOOL_WORDS))
    elif hint is str and rule is not None:
        if rule.choices:
            out.append(st.text(max_size=12).filter(lambda t: t not in rule.choices))
        if rule.file_name:
            out.append(st.one_of(st.sampled_from(['', '.', '..', '../x', '/abs']),
                                 st.tuples(st.text(max_size=6), st.text(max_size=6)).map('/'.join)))
        elif rule.nonempty:
            out.append(st.just(''))
    return out


def bad_arguments(cls) -> st.SearchStrategy[list[str]]:
    """argv strategies giving one field of settings class `cls` a value its type or rule refuses."""
    hints = typing.get_type_hints(cls)
    options = []
    for f in dataclasses.fields(cls):
        hint, rule = hints[f.name], f.metadata.get(RULE_KEY)
        tuple_field = typing.get_origin(hint) is tuple
        item = typing.get_args(hint)[0] if tuple_field else hint
        name = flag(f.name)
        for words in _bad_items(item, rule):
            if tuple_field:
                options.append(st.lists(words, min_size=1, max_size=3).map(lambda w, n=name: [n, *w]))
            else:
                options.append(words.map(lambda w, n=name: [n, w]))
    return st.one_of(options)


@pytest.mark.parametrize('command', sorted(CLIS))
@settings(max_examples=60, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_random_bad_values_are_one_error_line_and_exit_2(no_work, command, data):
    argv = data.draw(bad_arguments(CLIS[command][1]), label='argv')
    assert_refused(command, argv)


# ------------------------------------------------------------------ train_td3: resume and damaged checkpoints
TINY = dict(total_steps=0, hidden=(32, 32), buffer_size=1000, max_episode_s=4.0, eval_every_episodes=1000,
            eval_episodes_per_beta=1, start_steps=0)


@pytest.fixture(scope='module')
def td3_run(tmp_path_factory) -> Path:
    """A finished train_td3 run (no environment steps: a checkpoint and config.json in seconds)."""
    torch.set_num_threads(1)
    return ptrain.train(ptrain.TrainArgs(name='r', runs_dir=str(tmp_path_factory.mktemp('runs')), **TINY))


def test_resume_names_the_flags_that_differ_from_the_run(td3_run):
    before = (td3_run / 'config.json').read_text()
    code, err = run_cli('train_td3', ['--resume', str(td3_run), '--actor-lr', '0.01', '--hidden', '64', '64',
                                      '--condition', 'oracle', '--total-steps', '5'])
    assert code == 2 and 'Traceback' not in err, err
    line = err.strip().splitlines()[-1]
    assert line.startswith('train_td3: error: --resume') and '--actor-lr (run: 0.001, given: 0.01)' in line, line
    assert '--hidden (run: [32, 32], given: [64, 64])' in line and '--condition' not in line, line  # same value
    assert (td3_run / 'config.json').read_text() == before
    with pytest.raises(SettingsError, match='--bc-alpha'):           # called as a library: the same rule
        ptrain.train(ptrain.TrainArgs(resume=str(td3_run), bc_alpha=0.5))
    # the same values, and the flags a resumed run may change, are accepted
    args = ptrain.prepare_run(ptrain.TrainArgs(resume=str(td3_run), hidden=(32, 32), total_steps=7, torch_threads=2),
                              {'resume', 'hidden', 'total_steps', 'torch_threads'})
    assert (args.hidden, args.buffer_size, args.total_steps, args.torch_threads) == ((32, 32), 1000, 7, 2)
    assert args.resume == str(td3_run) and args.name == 'r'


def test_a_new_run_never_reuses_a_run_directory(td3_run, no_work):
    code, err = run_cli('train_td3', ['--name', td3_run.name, '--runs-dir', str(td3_run.parent)])
    assert code == 2 and 'already holds a run' in err and 'Traceback' not in err, err


def test_a_damaged_checkpoint_is_one_error_line(tmp_path):
    torch.set_num_threads(1)
    run = ptrain.train(ptrain.TrainArgs(name='d', runs_dir=str(tmp_path), **TINY))
    replay = run / ptrain.CHECKPOINT_DIR / 'replay.npz'
    replay.write_bytes(replay.read_bytes()[:40])                      # torn replay buffer
    code, err = run_cli('train_td3', ['--resume', str(run)])
    assert code == 1 and 'Traceback' not in err, err
    assert err.strip().splitlines()[-1].startswith(f'train_td3: error: damaged checkpoint {replay}'), err
    state = run / ptrain.CHECKPOINT_DIR / 'state.pt'
    state.write_bytes(b'not a checkpoint')
    code, err = run_cli('train_td3', ['--resume', str(run)])
    assert code == 1 and 'Traceback' not in err, err
    assert err.strip().splitlines()[-1].startswith(f'train_td3: error: damaged checkpoint {state}'), err


# ------------------------------------------------------------------ train_cmvae: resume, damage, divergence
def _frames(n: int = 48) -> dataset.FrameSet:
    """A small synthetic FrameSet (random depth, a pad label on every other frame, 8 frames per scene)."""
    rng = np.random.default_rng(0)
    visible = np.arange(n) % 2 == 0
    xyz = np.where(visible[:, None], rng.uniform(-1, 1, (n, 3)), np.nan).astype(np.float32)
    return dataset.FrameSet(rgb=rng.integers(0, 255, (n, 64, 64, 3), dtype=np.uint8),
                            depth=rng.uniform(0.5, 4.0, (n, 64, 64)).astype(np.float32), xyz=xyz,
                            visible=visible, scene=(np.arange(n) // 8).astype(np.int32),
                            pad_index=np.where(visible, 0, -1).astype(np.int8))


def _cmvae_cfg(run_dir: Path, **kw) -> ctrain.TrainConfig:
    return ctrain.TrainConfig(**{**dict(run_dir=str(run_dir), data_dir=str(run_dir / 'no_data'), epochs=1,
                                        batch_size=16, warmup_steps=1, val_fraction=0.2, seed=1), **kw})


def test_train_cmvae_resume_with_changed_settings_and_a_damaged_checkpoint(tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / 'cm'
    frames = _frames()
    ctrain.train(_cmvae_cfg(run), frames=frames, progress=False)
    with pytest.raises(SettingsError, match=r'--lr \(run: 0.001, now: 0.5\)'):
        ctrain.train(_cmvae_cfg(run, resume=True, lr=0.5), frames=frames, progress=False)
    ctrain.train(_cmvae_cfg(run, resume=True, epochs=2), frames=frames, progress=False)   # epochs may grow
    assert load_model(run / 'model.pt').metadata['epoch'] == 2
    code, err = run_cli('train_cmvae', ['--run-dir', str(run), '--resume'])   # the defaults differ from the run
    assert code == 2 and 'Traceback' not in err, err
    assert '--batch-size (run: 16, now: 128)' in err.strip().splitlines()[-1], err
    (run / 'checkpoint.pt').write_bytes(b'\x00' * 64)
    saved = json.loads((run / 'config.json').read_text())
    code, err = run_cli('train_cmvae', ['--config', str(run / 'config.json'), '--resume', '--epochs',
                                        str(saved['epochs'] + 1)])
    assert code == 1 and 'Traceback' not in err, err
    assert err.strip().splitlines()[-1].startswith(f'train_cmvae: error: damaged checkpoint {run / "checkpoint.pt"}')


def test_train_cmvae_stops_when_the_loss_turns_non_finite(tmp_path, monkeypatch):
    torch.set_num_threads(1)
    real, calls = ctrain.cmvae_loss, []

    def poisoned(*args, **kwargs):
        terms = real(*args, **kwargs)
        if not torch.is_grad_enabled():              # validation: left alone
            return terms
        calls.append(1)
        return terms._replace(total=terms.total * float('nan')) if len(calls) > 3 else terms
    monkeypatch.setattr(ctrain, 'cmvae_loss', poisoned)
    run = tmp_path / 'nan'
    with pytest.raises(ValueError, match='diverged'):
        ctrain.train(_cmvae_cfg(run, epochs=3), frames=_frames(), progress=False)   # 3 steps an epoch
    model = load_model(run / 'model.pt')                                   # epoch 1's, finite
    assert model.metadata['epoch'] == 1
    assert all(bool(torch.isfinite(t).all()) for t in model.state_dict().values() if t.is_floating_point())
