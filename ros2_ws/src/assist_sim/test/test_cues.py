"""Simulated pilots who read the assistant's cues (assist_sim.cues)."""
import math

import numpy as np
import pytest

from assist_common.settings import SettingsError
from assist_sim.cues import Cue, CueConfig, CueReader
from assist_sim.pilots import make_pilot

GOAL = np.array([10.0, 0.0, 0.8])
OTHER = np.array([6.0, 0.0, 0.6])
START = np.array([0.0, 0.0, 3.0])


def reader(trust: float = 1.0, **cfg) -> CueReader:
    r = CueReader(CueConfig(trust=trust, **cfg), np.random.default_rng(1))
    r.reset()
    return r


def test_an_agreeing_cue_pulls_the_estimate_onto_the_highlighted_pad():
    r = reader()
    r.see(Cue(GOAL + np.array([0.1, 0.0, 0.0]), 0.1, None))
    est = GOAL + np.array([1.5, 0.3, 0.0])                 # misjudged in depth
    new, follow = r.estimate(GOAL, est)
    assert follow
    np.testing.assert_allclose(new, est + 0.2 * (GOAL + np.array([0.1, 0.0, 0.0]) - est))


def test_a_cue_on_another_pad_is_not_followed_and_corrects_an_aim_on_it():
    r = reader()
    r.see(Cue(OTHER, 0.1, None))
    aiming_there = OTHER + np.array([0.2, 0.0, 0.0])        # the pilot thinks its pad is where OTHER is
    new, follow = r.estimate(GOAL, aiming_there)
    assert not follow
    np.testing.assert_allclose(new, aiming_there + 0.05 * (GOAL - aiming_there))
    elsewhere = GOAL + np.array([0.5, 0.0, 0.0])            # aiming at its own pad: only the push is not followed
    new, follow = r.estimate(GOAL, elsewhere)
    assert not follow and new is elsewhere


def test_an_unsure_absent_or_unread_cue_changes_nothing():
    est = GOAL + np.array([1.0, 0.0, 0.0])
    unsure = reader()
    unsure.see(Cue(OTHER, 0.9, False))                     # sigma above max_sigma_m
    assert unsure.estimate(GOAL, est) == (est, True)
    absent = reader()
    absent.see(None)
    assert absent.estimate(GOAL, est) == (est, True) and absent.vertical(GOAL, 1.0, -0.5, 0.5) == -0.5
    never = reader(trust=0.0)
    never.see(Cue(OTHER, 0.1, False))
    assert not never.reading
    assert never.estimate(GOAL, est) == (est, True) and never.vertical(GOAL, 1.0, -0.5, 0.5) == -0.5


def test_the_light_descends_on_green_over_its_pad_and_holds_on_red_low_down():
    r = reader()
    r.see(Cue(GOAL, 0.1, True))
    assert r.vertical(GOAL, 2.5, 0.0, 0.5) == -0.5
    r.see(Cue(OTHER, 0.1, True))                           # green, but over a pad it does not mean
    assert r.vertical(GOAL, 2.5, 0.0, 0.5) == 0.0
    r.see(Cue(GOAL, 0.1, False))
    assert r.vertical(GOAL, 1.5, -0.5, 0.5) == 0.0         # red, low: hold
    assert r.vertical(GOAL, 3.0, -0.5, 0.5) == -0.5        # red, high: still on its way
    assert r.vertical(GOAL, 1.5, 0.5, 0.5) == 0.5          # climbing is never held


def test_trust_is_a_chance_per_landing():
    r = CueReader(CueConfig(trust=0.3), np.random.default_rng(7))
    reads = []
    for _ in range(2000):
        r.reset()
        reads.append(r.reading)
    assert 0.25 < np.mean(reads) < 0.35


def test_a_pilot_who_never_reads_cues_flies_exactly_as_without_them():
    plain = make_pilot('keyboard', 0.5, 0.4, rng=np.random.default_rng(3))
    blind = make_pilot('keyboard', 0.5, 0.4, rng=np.random.default_rng(3), cues=CueConfig(trust=0.0))
    for p in (plain, blind):
        p.reset(GOAL, START)
    blind.see_cue(Cue(OTHER, 0.1, False))
    pos = START.copy()
    for k in range(200):
        a = np.array([0.4 * math.sin(0.1 * k), 0.2, -0.1])
        u1, u2 = plain.act(pos, a), blind.act(pos, a)
        np.testing.assert_array_equal(u1, u2)
        pos = pos + 0.05 * u1


def test_a_reading_pilot_leaves_a_wrong_aim_the_cue_shows_it():
    def estimate_after(cues: CueConfig | None) -> np.ndarray:
        p = make_pilot('paper', 0.5, 0.2, rng=np.random.default_rng(5), cues=cues)
        p.reset(GOAL, START, goal_estimate=OTHER.copy())    # it aims at the pad before its goal
        p.see_cue(Cue(OTHER, 0.1, None))                     # the assistant highlights where it heads
        for _ in range(40):                                  # 2 s
            p.act(START, None)
        return p.goal_estimate
    reading, blind = estimate_after(CueConfig(trust=1.0)), estimate_after(None)
    assert np.linalg.norm(reading[:2] - OTHER[:2]) > 0.8     # off the pad it now knows is not its own
    assert np.linalg.norm(blind[:2] - OTHER[:2]) < 0.3       # still aiming there (skill alone is slow)


def test_settings_out_of_range_are_refused():
    with pytest.raises(SettingsError, match='trust'):
        CueConfig(trust=1.5)
    with pytest.raises(SettingsError, match='adopt_rate'):
        CueConfig(adopt_rate=-0.1)
