"""Fault injection, TD3 actor files: mutated metadata, non-finite weights, wrong shapes, corrupt and
hostile files. Contract: a file loads (weights_only) and is then fully usable, or it is refused with
one line naming the file (no traceback text, no advice to drop weights_only); no file runs code.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from assist_policy.observation import vector_dim
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_lab.td3 import Actor, load_actor

SETTINGS = settings(max_examples=120, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
JUNK = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12), st.floats(allow_nan=True),
                 st.sampled_from([math.nan, math.inf, -1.0, 0, 5, 1e39, 'five', '', [], [1.0], [1.0, 2.0],
                                  [1.0, 1.0, 0.6], [1.0, math.nan, 0.6], [1.0, -1.0, 0.6], [8], [8, 8], (8,),
                                  [0], [-8], {'a': 1}, 'latent', 'oracle', 'end_to_end', 10, 23, 16, 13]),
                 st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4))
KEYS = ['vec_dim', 'act_dim', 'hidden', 'image', 'image_channels', 'condition', 'latent_dim', 'max_speed',
        'window_s', 'blend_threshold']


def good_meta(condition='latent', latent_dim=10):
    return {'vec_dim': vector_dim(condition, latent_dim), 'act_dim': 3, 'hidden': [8], 'image': False,
            'image_channels': [32, 32, 64, 64], 'condition': condition, 'latent_dim': latent_dim,
            'max_speed': [1.0, 1.0, 0.6], 'window_s': 1.0, 'blend_threshold': 0.25}


def write(path, meta, weights=None):
    meta_ok = good_meta()
    actor = Actor(meta_ok['vec_dim'], 3, hidden=(8,))
    torch.save({'actor': weights if weights is not None else actor.state_dict(), 'meta': meta}, path)
    return path


def assert_one_clear_line(exc: BaseException, path) -> None:
    text = str(exc)
    assert '\n' not in text and str(path) in text, text
    assert 'weights_only=False' not in text and 'Traceback' not in text and len(text) < 400, text


@SETTINGS
@given(changes=st.dictionaries(st.sampled_from(KEYS), JUNK, min_size=1, max_size=3),
       drop=st.lists(st.sampled_from(KEYS), max_size=2))
def test_mutated_metadata_loads_usably_or_fails_with_one_line(tmp_path_factory, changes, drop):
    path = tmp_path_factory.mktemp('m') / 'actor.pt'
    meta = {**good_meta(), **changes}
    for k in drop:
        meta.pop(k, None)
    write(path, meta)
    try:
        actor, loaded = load_actor(path)
    except ValueError as exc:
        assert_one_clear_line(exc, path)
        return
    # accepted: everything the policy core relies on holds, and the core runs
    assert all(math.isfinite(v) and v > 0 for v in loaded['max_speed']) and len(loaded['max_speed']) == 3
    assert math.isfinite(loaded['window_s']) and loaded['window_s'] > 0
    out = actor(torch.zeros(1, loaded['vec_dim']))
    assert out.shape == (1, 3) and torch.isfinite(out).all()
    if loaded.get('condition') == 'latent':
        core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
        core.set_odom(1.0, [0, 0, 2], [0, 0, 0])
        core.set_latent(1.0, np.zeros(loaded['latent_dim']))
        assert np.all(np.isfinite(core.step(1.0).velocity))


@pytest.mark.parametrize('max_speed', [[math.nan, 1.0, 0.6], 5, [1.0, 1.0], [1.0, -1.0, 0.6], [0.0, 1.0, 0.6],
                                       'fast', [1.0, 1.0, math.inf]])
def test_bad_max_speed_is_refused_at_load(tmp_path, max_speed):
    """NaN max_speed used to load and crash the node on its first tick; 5 (not a triple) gave a traceback."""
    path = write(tmp_path / 'a.pt', {**good_meta(), 'max_speed': max_speed})
    with pytest.raises(ValueError, match='max_speed') as info:
        load_actor(path)
    assert_one_clear_line(info.value, path)
    with pytest.raises(ValueError, match='max_speed'):
        PolicyCore(path, PolicyCoreConfig(mode='latent'))


@pytest.mark.parametrize('value', [math.nan, math.inf, -math.inf])
def test_non_finite_weights_are_refused(tmp_path, value):
    """NaN weights used to load silently (the node started and never assisted, health OK)."""
    actor = Actor(good_meta()['vec_dim'], 3, hidden=(8,))
    sd = actor.state_dict()
    sd['head.0.weight'][0, 0] = value
    path = write(tmp_path / 'nan.pt', good_meta(), sd)
    with pytest.raises(ValueError, match='non-finite values in weights head.0.weight') as info:
        load_actor(path)
    assert_one_clear_line(info.value, path)


def test_weights_of_another_shape_are_refused(tmp_path):
    other = Actor(good_meta()['vec_dim'], 3, hidden=(16,)).state_dict()
    path = write(tmp_path / 'shape.pt', good_meta(), other)
    with pytest.raises(ValueError, match='do not match') as info:
        load_actor(path)
    assert_one_clear_line(info.value, path)


def test_huge_architecture_in_metadata_allocates_nothing(tmp_path):
    """vec_dim/hidden are only shapes until checked against the weights (meta device)."""
    path = write(tmp_path / 'huge.pt', {**good_meta(), 'condition': None, 'vec_dim': 100_000, 'hidden': [8192] * 16})
    with pytest.raises(ValueError, match='do not match') as info:
        load_actor(path)
    assert_one_clear_line(info.value, path)


class _Evil:
    def __reduce__(self):
        return (print, ('code ran',))


@pytest.mark.parametrize('payload', ['truncated', 'garbage', 'pickle', 'list'])
def test_corrupt_or_hostile_files_fail_with_one_line(tmp_path, payload, capsys):
    path = tmp_path / f'{payload}.pt'
    good = write(tmp_path / 'good.pt', good_meta())
    if payload == 'truncated':
        path.write_bytes(good.read_bytes()[:200])
    elif payload == 'garbage':
        path.write_bytes(b'\x00not a torch file' * 10)
    elif payload == 'pickle':
        torch.save({'actor': _Evil(), 'meta': good_meta()}, path)
    else:
        torch.save([1, 2, 3], path)
    with pytest.raises(ValueError) as info:
        load_actor(path)
    assert_one_clear_line(info.value, path)
    assert 'code ran' not in capsys.readouterr().out
