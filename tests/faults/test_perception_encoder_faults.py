"""Fault injection, encoder core: arbitrary image buffers, encodings, sizes, steps, byte orders and
array contents thrown at decode_color / decode_depth / LatentEncoder.encode. Contract: a frame is
encoded into finite outputs of the model's sizes, or refused with BadFrame (a short reason key).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from assist_perception.encoder_core import (COLOR_ENCODINGS, DEPTH_ENCODINGS, BadFrame, LatentEncoder,
                                            decode_color, decode_depth)
from assist_perception.model import CMVAE, CMVAEConfig, save_model

SETTINGS = settings(max_examples=80, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
ENCODINGS = st.sampled_from(sorted(COLOR_ENCODINGS) + sorted(DEPTH_ENCODINGS) + ['mono8', '', 'rgb8 ', '8UC3',
                                                                                  '32FC3', 'jpeg'])
DIMS = st.one_of(st.integers(-2, 12), st.sampled_from([0, 2**31, 10**9]))


@pytest.fixture(scope='module')
def encoder(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp('m') / 'cmvae.pt'
    save_model(path, CMVAE(CMVAEConfig(latent_dim=8)).eval())
    return LatentEncoder(path)


@SETTINGS
@given(data=st.binary(max_size=2048), enc=ENCODINGS, h=DIMS, w=DIMS, step=DIMS, big=st.booleans())
def test_decoders_return_valid_images_or_bad_frame(data, enc, h, w, step, big):
    try:
        rgb = decode_color(data, enc, h, w, step)
    except BadFrame as exc:
        assert exc.reason in ('bad_encoding', 'bad_size')
    else:
        assert rgb.dtype == np.uint8 and rgb.shape == (h, w, 3)
    try:
        depth = decode_depth(data, enc, h, w, step, big)
    except BadFrame as exc:
        assert exc.reason in ('bad_encoding', 'bad_size')
    else:
        assert depth.dtype == np.float32 and depth.shape == (h, w)
        assert np.all(np.isfinite(depth)) and np.all(depth >= 0)


ARRAY_DTYPES = st.sampled_from([np.uint8, np.uint16, np.float32, np.float64, np.int32, np.bool_])
ELEMENTS = st.floats(allow_nan=True, allow_infinity=True, width=32)


def arrays(shape_strategy):
    return ARRAY_DTYPES.flatmap(lambda dt: hnp.arrays(
        dt, shape_strategy, elements=ELEMENTS if np.issubdtype(dt, np.floating) else None))


@SETTINGS
@given(rgb=arrays(st.sampled_from([(64, 64, 3), (32, 48, 3), (64, 64), (64, 64, 4), (1, 1, 3), (0, 5, 3)])),
       depth=arrays(st.sampled_from([(64, 64), (32, 48), (64, 64, 1), (1, 1), (0, 5)])))
def test_encode_gives_finite_outputs_or_bad_frame(encoder, rgb, depth):
    try:
        out = encoder.encode(rgb, depth, want_depth=True)
    except BadFrame as exc:
        assert exc.reason in ('bad_size', 'size_mismatch', 'no_valid_depth', 'bad_encoding'), exc
        assert not isinstance(exc, ZeroDivisionError)
        return
    assert out.mu.shape == (8,) and np.all(np.isfinite(out.mu))
    assert out.pad_xyz.shape == (3,) and np.all(np.isfinite(out.pad_xyz))
    assert out.depth.shape == (64, 64) and np.all(np.isfinite(out.depth))


@pytest.mark.parametrize('value', [math.nan, math.inf, 1e39, -5.0])
def test_float_colour_images_with_nasty_values_are_refused(encoder, value):
    """A float colour array (not uint8) used to reach the network: NaN/inf made every latent NaN."""
    rgb = np.full((64, 64, 3), value, np.float64)
    with pytest.raises(BadFrame) as info:
        encoder.encode(rgb, np.full((64, 64), 2.0, np.float32))
    assert info.value.reason == 'bad_encoding'


def test_overflowing_model_output_is_a_bad_frame_not_a_latent(tmp_path):
    """Finite but huge weights can overflow: such outputs were published as latents."""
    model = CMVAE(CMVAEConfig(latent_dim=8)).eval()
    with torch.no_grad():
        for p in model.encoder.parameters():
            p.fill_(1e30)
    save_model(tmp_path / 'huge.pt', model)
    enc = LatentEncoder(tmp_path / 'huge.pt')
    with pytest.raises(BadFrame) as info:
        enc.encode(np.full((64, 64, 3), 200, np.uint8), np.full((64, 64), 2.0, np.float32))
    assert info.value.reason == 'nonfinite_output'


def test_huge_depth_values_are_holes_not_inputs(encoder):
    depth = np.full((64, 64), 2.0, np.float32)
    depth[:8] = 3e38
    a = encoder.encode(np.zeros((64, 64, 3), np.uint8), depth)
    assert np.all(np.isfinite(a.mu))
