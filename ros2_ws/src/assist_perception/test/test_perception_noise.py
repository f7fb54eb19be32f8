"""Statistics of the depth noise model G against its parameters."""
import dataclasses

import numpy as np
import pytest

from assist_perception.noise import NoiseConfig, apply_depth_noise, discontinuity_band, frame_rng

# Every effect off; each test switches on the one it measures.
QUIET = NoiseConfig(sigma_z2=0.0, disparity_step_px=0.0, depth_unit_m=0.0, edge_hole_prob=0.0,
                    flying_pixel_prob=0.0, dark_hole_prob=0.0, base_hole_prob=0.0, blob_rate=0.0)


def only(**kw) -> NoiseConfig:
    """QUIET with some fields changed."""
    return dataclasses.replace(QUIET, **kw)


def test_quiet_model_is_identity_and_input_untouched():
    z = np.random.default_rng(0).uniform(0.5, 5.0, size=(64, 64)).astype(np.float32)
    z_copy = z.copy()
    out = apply_depth_noise(z, np.random.default_rng(1), only(edge_threshold_m=100.0))
    np.testing.assert_array_equal(out, z)
    np.testing.assert_array_equal(z, z_copy)
    assert out.dtype == np.float32


def test_hole_fraction_matches_base_probability():
    z = np.full((40, 64, 64), 2.0, np.float32)
    out = apply_depth_noise(z, np.random.default_rng(2), only(base_hole_prob=0.07))
    frac = float((out == 0).mean())
    n = z.size
    assert abs(frac - 0.07) < 4 * np.sqrt(0.07 * 0.93 / n)


@pytest.mark.parametrize('sigma', [0.005, 0.02])
def test_axial_noise_grows_with_square_of_range(sigma):
    rng = np.random.default_rng(3)
    cfg = only(sigma_z2=sigma)
    stds = {}
    for zz in (1.0, 3.0):
        out = apply_depth_noise(np.full((20, 64, 64), zz, np.float32), rng, cfg)
        err = out - zz
        assert abs(err.mean()) < 4 * sigma * zz * zz / np.sqrt(err.size)
        stds[zz] = float(err.std())
        assert stds[zz] == pytest.approx(sigma * zz * zz, rel=0.03)
    assert stds[3.0] / stds[1.0] == pytest.approx(9.0, rel=0.05)


def test_disparity_quantisation_lies_on_grid_and_step_grows_with_range():
    cfg = only(disparity_step_px=0.08)
    z = np.linspace(0.5, 6.0, 64 * 64, dtype=np.float32).reshape(64, 64)
    out = apply_depth_noise(z, np.random.default_rng(4), cfg)
    d = cfg.focal_baseline_px_m / out.astype(np.float64)
    k = d / cfg.disparity_step_px
    np.testing.assert_allclose(k, np.round(k), atol=1e-3)
    # max quantisation error ~ half a step: dz = z^2 * step / (2 fb)
    bound = z.astype(np.float64) ** 2 * cfg.disparity_step_px / (2 * cfg.focal_baseline_px_m)
    assert np.all(np.abs(out - z) <= bound * 1.01 + 1e-6)
    near, far = np.abs(out - z)[:8].max(), np.abs(out - z)[-8:].max()
    assert far > 10 * near


def test_millimetre_output_units():
    out = apply_depth_noise(np.full((64, 64), 1.23456, np.float32), np.random.default_rng(5),
                            only(depth_unit_m=0.001, sigma_z2=0.01))
    mm = out * 1000.0
    np.testing.assert_allclose(mm, np.round(mm), atol=2e-3)


def test_range_limits_make_holes():
    z = np.full((64, 64), 2.0, np.float32)
    z[:, :10] = 0.1     # closer than min range
    z[:, -10:] = 15.0   # beyond max range
    z[0, 20] = np.nan
    out = apply_depth_noise(z, np.random.default_rng(6), only(edge_threshold_m=100.0))
    assert np.all(out[:, :10] == 0) and np.all(out[:, -10:] == 0) and out[0, 20] == 0
    assert np.all(out[1:, 10:-10] == 2.0)


def _step_scene(n=30):
    z = np.full((n, 64, 64), 3.0, np.float32)
    z[:, :, 32:] = 1.5     # a box top at the right half: one vertical discontinuity
    return z


def test_edge_holes_only_near_discontinuities_with_given_probability():
    z = _step_scene()
    cfg = only(edge_hole_prob=0.6, edge_band_px=1)
    out = apply_depth_noise(z, np.random.default_rng(7), cfg)
    band = discontinuity_band(z, cfg.edge_threshold_m, cfg.edge_band_px)
    assert band[:, :, 31:33].all() and band.sum() == z.shape[0] * 64 * 2
    holes = out == 0
    assert not holes[~band].any()
    n = band.sum()
    assert abs(holes[band].mean() - 0.6) < 4 * np.sqrt(0.24 / n)


def test_flying_pixels_lie_between_the_two_surfaces():
    z = _step_scene()
    cfg = only(flying_pixel_prob=0.5, edge_band_px=1)
    out = apply_depth_noise(z, np.random.default_rng(8), cfg)
    band = discontinuity_band(z, cfg.edge_threshold_m, cfg.edge_band_px)
    changed = out != z
    assert not changed[~band].any()
    flying = out[changed]
    assert np.all((flying > 1.5) & (flying < 3.0))
    assert abs(changed[band].mean() - 0.5) < 4 * np.sqrt(0.25 / band.sum())


def test_dark_surfaces_lose_depth():
    z = np.full((20, 64, 64), 2.0, np.float32)
    rgb = np.full((20, 64, 64, 3), 200, np.uint8)
    rgb[:, :32] = 10   # dark upper half
    out = apply_depth_noise(z, np.random.default_rng(9), only(dark_hole_prob=0.4), rgb=rgb)
    dark_holes = (out[:, :32] == 0).mean()
    assert abs(dark_holes - 0.4) < 4 * np.sqrt(0.24 / out[:, :32].size)
    assert not (out[:, 32:] == 0).any()


def test_blob_count_follows_poisson_rate():
    rate = 1.5
    z = np.full((600, 32, 32), 2.0, np.float32)
    out = apply_depth_noise(z, np.random.default_rng(10), only(blob_rate=rate))
    frames_with_blob = float((out == 0).any(axis=(1, 2)).mean())
    expected = 1 - np.exp(-rate)
    assert abs(frames_with_blob - expected) < 4 * np.sqrt(expected * (1 - expected) / 600)


def test_defaults_are_seeded_and_deterministic():
    z = _step_scene(4)
    a = apply_depth_noise(z, np.random.default_rng(11))
    b = apply_depth_noise(z, np.random.default_rng(11))
    c = apply_depth_noise(z, np.random.default_rng(12))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert 0.0 < (a == 0).mean() < 0.5


def test_bad_config_and_shape_are_rejected():
    with pytest.raises(ValueError):
        NoiseConfig(edge_hole_prob=1.5)
    with pytest.raises(ValueError):
        apply_depth_noise(np.zeros((2, 2, 2, 2)), np.random.default_rng(0))


def test_frame_noise_is_a_function_of_seed_and_stamp_alone():
    """encoder_node's per-frame generator: same seed and stamp, same noise, whatever came before; else other noise."""
    z = _step_scene(1)[0]
    stamp = 1_700_000_000_050_000_000
    a = apply_depth_noise(z, frame_rng(7, stamp))
    apply_depth_noise(z, frame_rng(7, stamp + 50_000_000))              # another frame in between changes nothing
    np.testing.assert_array_equal(apply_depth_noise(z, frame_rng(7, stamp)), a)
    assert not np.array_equal(apply_depth_noise(z, frame_rng(7, stamp + 1)), a)       # 1 ns later: another frame
    assert not np.array_equal(apply_depth_noise(z, frame_rng(8, stamp)), a)           # another seed
    with pytest.raises(ValueError):
        frame_rng(7, -1)
