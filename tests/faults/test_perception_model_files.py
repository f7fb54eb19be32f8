"""Fault injection, CM-VAE weights files: mutated config and metadata, non-finite weights and buffers,
corrupt and hostile files. Contract: a file loads and encodes finite latents, or load_model raises
ModelLoadError with one line naming the file (no traceback text, no weights_only advice).
"""
from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from assist_perception.model import CMVAE, CMVAEConfig, ModelLoadError, load_model, save_model

SETTINGS = settings(max_examples=40, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
JUNK = st.one_of(st.none(), st.booleans(), st.integers(-10**9, 10**9), st.floats(allow_nan=True),
                 st.sampled_from([math.nan, math.inf, -1.0, 0, 2, 10, 64, 'ten', '', (), (1.0,), (1.0, 2.0),
                                  (0.0, 0.0, 2.0), (1.0, math.nan, 1.0), (1.0, -1.0, 1.0), (1.0, 0.0, 1.0),
                                  (32, 64, 128), (32, 64), (0, 64, 128), [32, 64, 128.5]]),
                 st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4).map(tuple))
FIELDS = ['latent_dim', 'image_size', 'channels', 'depth_scale_m', 'max_input_depth_m', 'init_depth_m',
          'xyz_hidden', 'xyz_mean', 'xyz_std']


@pytest.fixture(scope='module')
def payload(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp('cmvae') / 'good.pt'
    save_model(path, CMVAE(CMVAEConfig(latent_dim=8)).eval(), {'epoch': 1})
    return torch.load(path, weights_only=True)


def assert_one_clear_line(exc: BaseException, path) -> None:
    text = str(exc)
    assert '\n' not in text and str(path) in text, text
    assert 'weights_only=False' not in text and 'Traceback' not in text and len(text) < 400, text


def usable(model: CMVAE) -> None:
    with torch.no_grad():
        out = model(torch.rand(1, 4, 64, 64), sample=False)
    assert torch.isfinite(out.mu).all() and torch.isfinite(out.xyz).all() and torch.isfinite(out.depth).all()


@SETTINGS
@given(changes=st.dictionaries(st.sampled_from(FIELDS), JUNK, min_size=1, max_size=2))
def test_mutated_config_loads_usably_or_fails_with_one_line(tmp_path_factory, payload, changes):
    path = tmp_path_factory.mktemp('c') / 'cmvae.pt'
    torch.save({**payload, 'config': {**payload['config'], **changes}}, path)
    try:
        model = load_model(path)
    except ModelLoadError as exc:
        assert_one_clear_line(exc, path)
        return
    usable(model)


@pytest.mark.parametrize('field,value', [('depth_scale_m', math.nan), ('depth_scale_m', -5.0),
                                         ('max_input_depth_m', math.inf), ('xyz_std', (1.0, 1.0)),
                                         ('xyz_std', (1.0, 0.0, 1.0)), ('xyz_mean', (0.0, math.nan, 2.0)),
                                         ('latent_dim', 'ten'), ('channels', (32, 64)), ('latent_dim', True)])
def test_bad_config_values_are_refused(tmp_path, payload, field, value):
    """A NaN depth_scale_m (a plain float, not a weight) used to load and make every latent NaN."""
    path = tmp_path / 'bad.pt'
    torch.save({**payload, 'config': {**payload['config'], field: value}}, path)
    with pytest.raises(ModelLoadError, match=field) as info:
        load_model(path)
    assert_one_clear_line(info.value, path)


@pytest.mark.parametrize('name', ['encoder.conv.weight', 'xyz_std', 'xyz_mean'])
def test_non_finite_weights_and_buffers_are_refused(tmp_path, payload, name):
    sd = {k: v.clone() for k, v in payload['state_dict'].items()}
    key = next(k for k in sd if k.startswith(name.rsplit('.', 1)[0]) and sd[k].is_floating_point())
    sd[key].view(-1)[0] = math.nan
    path = tmp_path / 'nan.pt'
    torch.save({**payload, 'state_dict': sd}, path)
    with pytest.raises(ModelLoadError, match='non-finite') as info:
        load_model(path)
    assert_one_clear_line(info.value, path)


def test_non_positive_std_buffer_is_refused(tmp_path, payload):
    sd = {k: v.clone() for k, v in payload['state_dict'].items()}
    sd['xyz_std'][1] = 0.0
    path = tmp_path / 'std.pt'
    torch.save({**payload, 'state_dict': sd}, path)
    with pytest.raises(ModelLoadError, match='xyz_std') as info:
        load_model(path)
    assert_one_clear_line(info.value, path)


@pytest.mark.parametrize('mutation', ['no_config', 'config_list', 'metadata_list', 'state_dict_list',
                                      'truncated', 'wrong_shape'])
def test_structural_damage_fails_with_one_line(tmp_path, payload, mutation):
    path = tmp_path / f'{mutation}.pt'
    if mutation == 'truncated':
        good = tmp_path / 'good.pt'
        torch.save(payload, good)
        path.write_bytes(good.read_bytes()[:5000])
    else:
        bad = dict(payload)
        if mutation == 'no_config':
            del bad['config']
        elif mutation == 'config_list':
            bad['config'] = [1, 2, 3]
        elif mutation == 'metadata_list':
            bad['metadata'] = ['x']
        elif mutation == 'state_dict_list':
            bad['state_dict'] = [torch.zeros(3)]
        else:
            bad['config'] = {**payload['config'], 'latent_dim': 12}
        torch.save(bad, path)
    with pytest.raises(ModelLoadError) as info:
        load_model(path)
    assert_one_clear_line(info.value, path)
