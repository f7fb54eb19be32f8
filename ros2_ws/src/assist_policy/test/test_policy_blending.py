"""Blending rule and action scaling (paper: V = (u + a)/2 if |a| > 0.25 else u)."""
import numpy as np
import pytest

from assist_policy.actions import DEFAULT_MAX_SPEED, scale_action, unscale_action
from assist_policy.blending import blend


def test_small_action_relinquishes_to_pilot():
    u = np.array([1.0, 0.0, -0.5])
    a = np.array([0.2, 0.1, 0.0])  # |a| = 0.224 <= 0.25
    np.testing.assert_allclose(blend(u, a), u)


def test_large_action_is_averaged():
    u = np.array([1.0, 0.0, -0.5])
    a = np.array([0.0, 0.6, 0.0])
    np.testing.assert_allclose(blend(u, a), [0.5, 0.3, -0.25])


def test_threshold_uses_norm_not_components():
    u = np.zeros(3)
    a = np.array([0.2, 0.2, 0.0])  # each < 0.25 but |a| = 0.283
    np.testing.assert_allclose(blend(u, a), [0.1, 0.1, 0.0])


def test_threshold_is_strict_and_configurable():
    u = np.array([1.0, 1.0, 1.0])
    a = np.array([0.25, 0.0, 0.0])
    np.testing.assert_allclose(blend(u, a), u)
    np.testing.assert_allclose(blend(u, a, threshold=0.1), [0.625, 0.5, 0.5])


def test_nonfinite_agent_action_counts_as_absent_and_bad_pilot_raises():
    u = np.array([0.3, -0.2, 0.0])
    np.testing.assert_allclose(blend(u, np.array([np.nan, 1.0, 0.0])), u)
    with pytest.raises(ValueError):
        blend(np.array([np.inf, 0, 0]), np.zeros(3))


def test_scale_action_roundtrip_and_clip():
    raw = np.array([0.5, -1.0, 2.0])
    v = scale_action(raw)
    np.testing.assert_allclose(v, [0.5 * DEFAULT_MAX_SPEED[0], -DEFAULT_MAX_SPEED[1], DEFAULT_MAX_SPEED[2]])
    np.testing.assert_allclose(unscale_action(v), [0.5, -1.0, 1.0])
