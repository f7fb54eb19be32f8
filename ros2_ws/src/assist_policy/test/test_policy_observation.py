"""Observation building: 1 s means of pilot and agent actions, layout per condition."""
import numpy as np
import pytest

from assist_policy.observation import (ACTIONS_DIM, DYNAMICS_DIM, GOAL_SCALE, ActionHistory, Condition,
                                       ObservationBuilder, image_feature, oracle_feature, vector_dim)


def test_history_means_over_trailing_second():
    h = ActionHistory(1.0)
    for k in range(40):  # 20 Hz for 2 s: u_x = k, a_y = -k
        h.push(k * 0.05, np.array([k, 0, 0]), np.array([0, -k, 0]))
    mu, ma = h.means(39 * 0.05)
    # samples with t in (0.95, 1.95] -> k = 20..39, mean 29.5
    assert len(h) == 20
    np.testing.assert_allclose(mu, [29.5, 0, 0])
    np.testing.assert_allclose(ma, [0, -29.5, 0])


def test_history_empty_is_zero_and_stale_samples_drop():
    h = ActionHistory(1.0)
    np.testing.assert_allclose(h.means(0.0)[0], np.zeros(3))
    h.push(0.0, np.ones(3), np.ones(3))
    np.testing.assert_allclose(h.means(0.5)[0], np.ones(3))
    np.testing.assert_allclose(h.means(1.5)[0], np.zeros(3))


def test_history_clears_when_clock_jumps_back():
    h = ActionHistory(1.0)
    h.push(10.0, np.ones(3), np.ones(3))
    h.push(0.1, 2 * np.ones(3), np.zeros(3))
    np.testing.assert_allclose(h.means(0.1)[0], 2 * np.ones(3))


def test_history_rejects_nonfinite():
    with pytest.raises(ValueError):
        ActionHistory().push(0.0, np.array([np.nan, 0, 0]), np.zeros(3))


def test_oracle_layout():
    b = ObservationBuilder(Condition.ORACLE)
    assert b.dim == 3 + DYNAMICS_DIM + ACTIONS_DIM == vector_dim('oracle')
    b.record(0.0, np.array([1.0, 0, 0]), np.array([0, 0.5, 0]))
    b.record(0.05, np.array([0.0, 0, 0]), np.array([0, 0.5, 0]))
    feat = oracle_feature(np.array([8.0, 1.0, 1.0]), np.array([0.0, 0.0, 3.0]))
    np.testing.assert_allclose(feat, np.array([8.0, 1.0, -2.0]) / GOAL_SCALE)
    obs = b.build(0.1, feat, np.array([0.1, 0.2, 0.3]), 3.0, np.array([0, 1.0, 0]))
    assert obs.dtype == np.float32 and obs.shape == (b.dim,)
    np.testing.assert_allclose(obs[3:7], [0.1, 0.2, 0.3, 0.75])
    np.testing.assert_allclose(obs[7:10], [0, 1, 0])
    np.testing.assert_allclose(obs[10:13], [0.5, 0, 0])   # mean u over the last second
    np.testing.assert_allclose(obs[13:16], [0, 0.5, 0])   # mean a


def test_latent_feature_size_checked():
    b = ObservationBuilder(Condition.LATENT, latent_dim=8)
    assert b.dim == 8 + DYNAMICS_DIM + ACTIONS_DIM
    with pytest.raises(ValueError):
        b.build(0.0, np.zeros(5), np.zeros(3), 1.0, np.zeros(3))
    with pytest.raises(ValueError):
        b.build(0.0, np.full(8, np.nan), np.zeros(3), 1.0, np.zeros(3))


def test_image_feature_scaling_and_invalid_depth():
    rgb = np.full((64, 64, 3), 255, np.uint8)
    depth = np.full((64, 64), 2.5, np.float32)
    depth[0, 0] = np.nan
    img = image_feature(rgb, depth)
    assert img.shape == (4, 64, 64)
    assert img[0].max() == 1.0 and img[3, 0, 0] == 0.0 and img[3, 1, 1] == pytest.approx(0.5)
