"""The touchdown envelope: a descent's last decimetres become a vertical descent the autopilot detects."""
import math

import numpy as np
import pytest

from assist_common.settings import SettingsError, check_settings
from assist_common.touchdown import TouchdownConfig, TouchdownEnvelope


def test_high_up_commands_pass_unchanged():
    env = TouchdownEnvelope()
    cmd = np.array([0.8, -0.3, -0.6])
    assert np.array_equal(env.apply(cmd, 2.0), cmd)
    assert not env.engaged


def test_a_low_descent_becomes_the_final_descent_with_little_sideways_speed_then_vertical_at_touchdown():
    cfg = TouchdownConfig()
    env = TouchdownEnvelope(cfg)
    out = env.apply([0.7, 0.4, -0.8], cfg.engage_range_m - 0.05)
    assert out[2] == -cfg.descent_mps and env.engaged and env.engagements == 1
    assert np.hypot(out[0], out[1]) == pytest.approx(cfg.lateral_max_mps)     # limited, same direction
    assert out[0] / out[1] == pytest.approx(0.7 / 0.4)
    # a small correction passes as it is; the final descent holds while the command descends
    assert env.apply([0.1, -0.05, -0.3], cfg.release_range_m - 0.01).tolist() == [0.1, -0.05, -cfg.descent_mps]
    # legs down: nothing sideways at all
    assert env.apply([1.0, -1.0, -0.5], cfg.commit_range_m).tolist() == [0.0, 0.0, -cfg.descent_mps]


def test_legs_down_finishes_the_landing_even_for_a_level_command():
    cfg = TouchdownConfig()
    env = TouchdownEnvelope(cfg)
    assert env.apply([0.4, 0.0, 0.0], cfg.commit_range_m - 0.01).tolist() == [0.0, 0.0, -cfg.descent_mps]
    assert env.engaged and env.engagements == 1


def test_hovering_low_or_climbing_low_does_not_engage():
    cfg = TouchdownConfig()
    env = TouchdownEnvelope(cfg)
    low = cfg.engage_range_m - 0.1          # above the legs-down range
    assert env.apply([0.5, 0.0, 0.0], low).tolist() == [0.5, 0.0, 0.0]
    assert env.apply([0.5, 0.0, -0.5 * cfg.engage_descent_mps], low).tolist()[0] == 0.5
    assert env.apply([0.5, 0.0, 0.4], low).tolist() == [0.5, 0.0, 0.4]
    assert not env.engaged


def test_a_climb_command_or_a_lost_range_lets_go():
    cfg = TouchdownConfig()
    env = TouchdownEnvelope(cfg)
    env.apply([0.0, 0.0, -1.0], 0.2)
    assert env.engaged
    out = env.apply([0.3, 0.0, cfg.abort_climb_mps + 0.1], 0.2)
    assert not env.engaged and out.tolist() == [0.3, 0.0, cfg.abort_climb_mps + 0.1]
    env.apply([0.0, 0.0, -1.0], 0.2)
    assert env.engaged
    assert env.apply([0.2, 0.0, -1.0], math.nan).tolist() == [0.2, 0.0, -1.0]   # unknown range: the command
    assert not env.engaged
    assert env.apply([0.2, 0.0, -1.0], None).tolist() == [0.2, 0.0, -1.0]


def test_disabled_is_a_pass_through_and_reset_forgets():
    env = TouchdownEnvelope(TouchdownConfig(enabled=False))
    assert env.apply([0.5, 0.5, -1.0], 0.15).tolist() == [0.5, 0.5, -1.0]
    on = TouchdownEnvelope()
    on.apply([0.0, 0.0, -1.0], 0.2)
    on.reset()
    assert not on.engaged


def test_settings_out_of_range_or_inconsistent_are_refused():
    with pytest.raises(SettingsError, match='descent-mps'):
        check_settings(TouchdownConfig(descent_mps=-0.5))
    with pytest.raises(ValueError, match='release_range_m'):
        TouchdownEnvelope(TouchdownConfig(engage_range_m=0.5, release_range_m=0.4))


def test_a_touchdown_with_the_legs_down_holds_the_descent_for_commit_s_whatever_is_commanded():
    cfg = TouchdownConfig()
    env = TouchdownEnvelope(cfg)
    env.apply([0.3, 0.0, -0.6], 0.3, now=10.0)
    assert env.engaged and not env.committed
    env.apply([0.0, 0.0, -0.6], cfg.commit_range_m - 0.02, now=10.5)     # the legs are down
    assert env.committed and env.commits == 1
    climb = [0.8, 0.0, 1.0]                    # the pilot hops: held down until commit_s has passed
    assert env.apply(climb, 0.12, now=10.5 + cfg.commit_s - 0.05).tolist() == [0.0, 0.0, -cfg.descent_mps]
    assert env.apply(climb, math.nan, now=10.5 + cfg.commit_s - 0.01).tolist() == [0.0, 0.0, -cfg.descent_mps]
    out = env.apply(climb, 0.12, now=10.5 + cfg.commit_s + 0.01)
    assert out.tolist() == climb and not env.engaged and not env.committed


def test_without_a_clock_or_with_commit_s_zero_nothing_is_committed():
    env = TouchdownEnvelope()
    env.apply([0.0, 0.0, -0.6], 0.13)
    assert env.engaged and not env.committed
    assert env.apply([0.0, 0.0, 1.0], 0.13).tolist() == [0.0, 0.0, 1.0]
    off = TouchdownEnvelope(TouchdownConfig(commit_s=0.0))
    off.apply([0.0, 0.0, -0.6], 0.13, now=1.0)
    assert not off.committed
    with pytest.raises(ValueError, match='commit_range_m'):
        TouchdownEnvelope(TouchdownConfig(commit_range_m=0.45))


def test_a_command_that_stops_descending_in_the_final_descent_is_let_go():
    """A floor guard that stops a descent over the floor low down is obeyed, not overruled into a floor landing."""
    cfg = TouchdownConfig()
    env = TouchdownEnvelope(cfg)
    env.apply([0.2, 0.0, -0.3], 0.35, now=1.0)
    assert env.engaged
    assert env.apply([0.2, 0.0, 0.0], 0.30, now=1.05).tolist() == [0.2, 0.0, 0.0]
    assert not env.engaged and not env.committed
