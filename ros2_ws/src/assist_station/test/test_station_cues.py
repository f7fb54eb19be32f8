"""Pilot station core: validation of the assistant's intent (goal estimate, descent light, blended command) and what
the page may draw of it (IntentCues.view)."""
import math
from collections import Counter

import numpy as np
import pytest

from assist_common.settings import SettingsError
from assist_station.station_core import (CueConfig, InputError, IntentCues, match_pad, pad_top_centres,
                                         parse_blended, parse_goal_estimate)

# two pads in odom: box centre, quaternion (x, y, z, w), size; pad 0 level, pad 1 yawed 30 degrees
PLATFORMS = [{'id': 0, 'p': [4.0, 1.0, 0.4], 'q': [0.0, 0.0, 0.0, 1.0], 's': [1.2, 1.0, 0.8], 'c': [0.8, 0.7, 0.2]},
             {'id': 1, 'p': [8.0, -1.0, 0.5], 'q': [0.0, 0.0, math.sin(math.pi / 12), math.cos(math.pi / 12)],
              's': [1.0, 1.0, 1.0], 'c': [0.2, 0.5, 0.8]}]
TOP0, TOP1 = (4.0, 1.0, 0.8), (8.0, -1.0, 1.0)
ALL = {'goal': True, 'descent': True, 'push': True}


def cov(var_x=0.01, var_y=0.01, var_z=0.01):
    c = [0.0] * 36
    c[0], c[7], c[14] = var_x, var_y, var_z
    c[21] = c[28] = c[35] = 1e6
    return c


def goal(cues, p=TOP0, now=100.0, stamp=None, frame='odom', var=(0.01, 0.01, 0.01), q=(0.0, 0.0, 0.0, 1.0)):
    return cues.note_goal(frame, now if stamp is None else stamp, p, q, cov(*var), now)


def test_pad_top_centres_follow_the_box_rotation():
    tops = dict(pad_top_centres(PLATFORMS))
    np.testing.assert_allclose(tops[0], TOP0)
    np.testing.assert_allclose(tops[1], TOP1)                    # yaw leaves the top above the centre
    s = math.sqrt(0.5)                                            # pitched 90 degrees about y: local +z is world +x
    tipped = pad_top_centres([{'id': 7, 'p': [1.0, 2.0, 3.0], 'q': [0.0, s, 0.0, s], 's': [1.0, 1.0, 2.0]}])
    assert tipped[0][0] == 7
    np.testing.assert_allclose(tipped[0][1], [2.0, 2.0, 3.0], atol=1e-12)


def test_match_pad_takes_the_nearest_pad_within_the_tolerance():
    pads = pad_top_centres(PLATFORMS)
    assert match_pad((4.3, 1.2, 0.9), pads, 0.5) == 0
    assert match_pad((7.7, -0.8, 1.0), pads, 0.5) == 1
    assert match_pad((4.0, 1.0, 1.4), pads, 0.5) is None         # above the pad by more than the tolerance
    assert match_pad((6.0, 0.0, 0.9), pads, 0.5) is None         # between the pads
    assert match_pad((6.0, 0.0, 0.9), pads, 3.0) == 0            # both within: the nearer one


def test_a_good_estimate_is_matched_to_its_pad_with_its_sigma():
    pads = pad_top_centres(PLATFORMS)
    est = parse_goal_estimate('odom', 99.9, TOP1, (0, 0, 0, 1), cov(0.04, 0.09), 100.0, pads, CueConfig())
    assert est.pad == 1 and est.p == TOP1 and est.t == 99.9
    assert est.sigma_m == pytest.approx(0.3)                     # sqrt(max(var x, var y))
    assert parse_goal_estimate('', None, TOP0, (0, 0, 0, 1), cov(), 100.0, pads, CueConfig()).t == 100.0   # unset
    free = parse_goal_estimate('odom', 100.0, (50.0, 50.0, 3.0), (0, 0, 0, 1), cov(), 100.0, None, CueConfig())
    assert free.pad is None                                       # no scene known: any position is accepted


@pytest.mark.parametrize('change, kind', [
    ({'p': (math.nan, 1.0, 0.8)}, 'nonfinite'),
    ({'p': (4.0, math.inf, 0.8)}, 'nonfinite'),
    ({'q': (0.0, 0.0, math.nan, 1.0)}, 'nonfinite'),
    ({'var': (math.nan, 0.01, 0.01)}, 'nonfinite'),
    ({'var': (0.01, math.inf, 0.01)}, 'nonfinite'),
    ({'var': (-0.01, 0.01, 0.01)}, 'variance'),
    ({'var': (0.01, 0.01, -1.0)}, 'variance'),
    ({'frame': 'map'}, 'frame'),
    ({'frame': 'base_link'}, 'frame'),
    ({'stamp': 100.4}, 'future_stamp'),                           # tolerance 0.25 s
    ({'stamp': 99.3}, 'stale_stamp'),                             # timeout 0.5 s
    ({'p': (6.0, 0.0, 0.9)}, 'unknown_pad'),
    ({'p': (4.0, 1.0, 2.0)}, 'unknown_pad'),
])
def test_unusable_estimates_are_rejected_by_kind(change, kind):
    cues = IntentCues(CueConfig(timeout_s=0.5, stamp_tolerance_s=0.25))
    cues.set_scene(PLATFORMS)
    goal(cues, now=99.0)                                          # a good one first
    args = {'p': TOP0, 'stamp': 100.0, 'frame': 'odom', 'var': (0.01, 0.01, 0.01), 'q': (0.0, 0.0, 0.0, 1.0)}
    args.update(change)
    with pytest.raises(InputError) as err:
        goal(cues, now=100.0, **args)
    assert err.value.kind == kind
    # the rejected estimate is not drawn: the cue stays at the last good estimate, shown as unknown (grey)
    g = cues.view(100.0, True, ALL)['goal']
    assert g['state'] == 'unknown' and tuple(g['p']) == TOP0


def test_wrongly_sized_fields_are_rejected():
    with pytest.raises(InputError) as err:
        parse_goal_estimate('odom', None, TOP0, (0, 0, 0, 1), [0.0] * 9, 1.0, None, CueConfig())
    assert err.value.kind == 'shape'


def test_nothing_is_shown_while_assistance_is_off():
    cues = IntentCues()
    cues.set_scene(PLATFORMS)
    goal(cues, now=10.0)
    cues.note_descent(True, 10.0)
    cues.note_blended('base_link', 10.0, (1.0, 0.0, 0.0), 10.0)
    assert cues.view(10.0, False, ALL) == {'goal': None, 'descent': None, 'push': None}
    on = cues.view(10.0, True, ALL)
    assert on['goal']['state'] == 'sure' and on['descent'] == 'ok' and on['push'] == [1.0, 0.0, 0.0]


def test_each_cue_is_switched_on_its_own():
    cues = IntentCues()
    goal(cues, now=10.0)
    cues.note_descent(False, 10.0)
    cues.note_blended('', 10.0, (0.0, 0.5, 0.0), 10.0)
    for off in ALL:
        view = cues.view(10.0, True, dict(ALL, **{off: False}))
        assert view[off] is None and all(view[k] is not None for k in ALL if k != off), (off, view)


def test_sure_unsure_by_sigma():
    cues = IntentCues(CueConfig(max_sigma_m=0.5))
    cues.set_scene(PLATFORMS)
    goal(cues, var=(0.24, 0.01, 0.01))                            # sigma 0.49
    assert cues.view(100.0, True, ALL)['goal']['state'] == 'sure'
    goal(cues, var=(0.01, 0.26, 0.01))                            # sigma 0.51 (y)
    g = cues.view(100.0, True, ALL)['goal']
    assert g['state'] == 'unsure' and g['pad'] == 0 and g['sigma_m'] == pytest.approx(math.sqrt(0.26), abs=1e-3)


def test_the_goal_cue_goes_grey_when_its_estimate_ages_and_comes_back_with_a_new_one():
    counts = Counter()
    cues = IntentCues(CueConfig(timeout_s=0.5), count=lambda key: counts.update([key]))
    cues.set_scene(PLATFORMS)
    assert cues.view(10.0, True, ALL)['goal'] is None             # none received yet: nothing to draw
    goal(cues, p=TOP1, now=10.0)
    assert cues.view(10.4, True, ALL)['goal']['state'] == 'sure'
    for t in (10.6, 10.8, 11.0):                                  # stamped more than 0.5 s ago
        g = cues.view(t, True, ALL)['goal']
        assert g['state'] == 'unknown' and g['pad'] == 1
    assert counts['cue_goal_unknown'] == 1                        # counted once, when it went grey
    goal(cues, p=TOP0, now=11.0)
    g = cues.view(11.0, True, ALL)['goal']
    assert g['state'] == 'sure' and g['pad'] == 0
    goal(cues, p=TOP0, now=50.0)
    assert cues.view(40.0, True, ALL)['goal']['state'] == 'unknown'   # the clock went back (a new sim run)


def test_the_descent_light_is_dated_by_arrival():
    counts = Counter()
    cues = IntentCues(CueConfig(timeout_s=0.5), count=lambda key: counts.update([key]))
    assert cues.view(5.0, True, ALL)['descent'] == 'unknown'      # assisting, nothing heard: grey
    cues.note_descent(True, 5.0)
    assert cues.view(5.5, True, ALL)['descent'] == 'ok'
    cues.note_descent(False, 5.6)
    assert cues.view(5.7, True, ALL)['descent'] == 'hold'
    assert cues.view(6.2, True, ALL)['descent'] == 'unknown'
    assert counts['cue_descent_unknown'] == 1


def test_the_push_is_the_blended_command_minus_the_pilots():
    cues = IntentCues(CueConfig(timeout_s=0.5))
    cues.note_pilot((1.0, 0.0, -0.5))
    cues.note_blended('base_link', 20.0, (0.75, 0.25, -0.5), 20.0)
    np.testing.assert_allclose(cues.view(20.1, True, ALL)['push'], [-0.25, 0.25, 0.0])
    assert cues.view(20.6, True, ALL)['push'] is None             # V stamped too long ago: no push shown
    cues.note_blended('base_link', 21.0, (1.0, 0.0, -0.5), 21.0)
    assert cues.view(21.0, True, ALL)['push'] is None             # V = u: no push
    with pytest.raises(InputError) as err:
        cues.note_blended('odom', 21.0, (2.0, 0.0, 0.0), 21.0)
    assert err.value.kind == 'frame'
    assert cues.view(21.0, True, ALL)['push'] is None             # a rejected V drops the push
    for v, kind in (((math.nan, 0.0, 0.0), 'nonfinite'), ((0.0, 0.0), 'nonfinite')):
        with pytest.raises(InputError) as err:
            parse_blended('', None, v, 1.0, CueConfig())
        assert err.value.kind == kind


def test_a_new_scene_forgets_the_estimate():
    cues = IntentCues()
    cues.set_scene(PLATFORMS)
    goal(cues, p=TOP0, now=3.0)
    cues.set_scene(PLATFORMS[1:])
    assert cues.view(3.0, True, ALL)['goal'] is None
    with pytest.raises(InputError):
        goal(cues, p=TOP0, now=3.0)                               # pad 0 is gone
    assert goal(cues, p=TOP1, now=3.0).pad == 1


@pytest.mark.parametrize('field, value', [('timeout_s', 0.0), ('max_sigma_m', -1.0), ('pad_tolerance_m', 0.0),
                                          ('stamp_tolerance_s', -0.1)])
def test_bad_cue_config_is_refused(field, value):
    with pytest.raises(SettingsError):
        CueConfig(**{field: value})
