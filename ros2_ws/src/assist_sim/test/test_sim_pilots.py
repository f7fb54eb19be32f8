"""Pilot population (assist_sim.pilots): one behavioural test per family, split, determinism."""
import numpy as np
import pytest

from assist_sim.pilot import PilotConfig, SimulatedPilot
from assist_sim.pilots import (APPROACH_FAMILIES, FAMILIES, GOAL_CHANGING_FAMILIES, GRAPH_PILOT_NAMES, HELDOUT_FAMILIES,
                               MIX_FAMILIES, PILOT_NAMES, POPULATIONS, TRAIN_FAMILIES, UNTUNED_FAMILIES, CautiousConfig,
                               FamilyConfig, confuse, make_pilot)

GOAL = np.array([12.0, 0.5, 0.8])
START = np.array([0.0, 0.0, 3.5])
PADS = np.array([[4.0, 0.3, 0.6], [8.0, -0.4, 1.0], GOAL, [16.0, 0.2, 0.5], [20.0, -0.1, 0.9]])
DT = 0.05


def commands(pilot, positions):
    """Commands of `pilot` along a fixed sequence of positions (open loop)."""
    return np.array([pilot.act(p) for p in positions])


def fly(pilot, steps=1600):
    """Integrate the commands as velocities (perfect tracking) until down at the goal height."""
    p, cmds = START.copy(), []
    for _ in range(steps):
        u = pilot.act(p)
        cmds.append(u)
        p = p + u * DT
        if p[2] <= GOAL[2]:
            break
    return p, np.array(cmds)


def path(n=400):
    """A straight fly-over toward and past the goal, descending slowly."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    return START + s * (np.array([16.0, 1.0, 1.2]) - START)


def test_registry_split_and_populations():
    assert set(TRAIN_FAMILIES).isdisjoint(HELDOUT_FAMILIES)
    assert set(TRAIN_FAMILIES) | set(HELDOUT_FAMILIES) == set(FAMILIES)
    assert 'paper' in TRAIN_FAMILIES
    assert POPULATIONS['mix'] == MIX_FAMILIES and POPULATIONS['train_mix'] == TRAIN_FAMILIES
    assert POPULATIONS['approach_mix'] == APPROACH_FAMILIES == ('glide', 'low_flyer')
    assert set(MIX_FAMILIES) | set(APPROACH_FAMILIES) | set(UNTUNED_FAMILIES) == set(HELDOUT_FAMILIES)
    assert not set(UNTUNED_FAMILIES) & (set(MIX_FAMILIES) | set(APPROACH_FAMILIES))   # in no population
    with pytest.raises(ValueError, match='unknown pilot'):
        make_pilot('nobody')
    seen = {make_pilot('mix', rng=s).name for s in range(60)}
    assert seen == set(MIX_FAMILIES)                    # the held-out mix is unchanged by the later families
    assert set(GOAL_CHANGING_FAMILIES) <= set(UNTUNED_FAMILIES) and not set(GOAL_CHANGING_FAMILIES) & set(
        GRAPH_PILOT_NAMES)
    assert {make_pilot('approach_mix', rng=s).name for s in range(20)} == set(APPROACH_FAMILIES)


def test_paper_family_is_the_reference_pilot_bit_for_bit():
    ref = SimulatedPilot(0.5, 0.3, rng=5)
    fam = make_pilot('paper', 0.5, 0.3, rng=5)
    ref.reset(GOAL, START)
    fam.reset(GOAL, START)
    np.testing.assert_array_equal(ref.goal_estimate, fam.goal_estimate)
    a = np.array([0.4, -0.2, 0.0])
    for p in path():
        np.testing.assert_array_equal(ref.act(p, a), fam.act(p, a))


@pytest.mark.parametrize('name', PILOT_NAMES)
def test_deterministic_per_seed_and_params_drawn_per_episode(name):
    runs = []
    for _ in range(2):
        pl = make_pilot(name, 0.5, 0.5, rng=11, pads=PADS)
        pl.reset(GOAL, START)
        runs.append((commands(pl, path()), dict(pl.params)))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    assert runs[0][1] == runs[1][1]
    pl = make_pilot(name, 0.5, 0.5, rng=11, pads=PADS)
    draws = []
    for _ in range(3):
        pl.reset(GOAL, START)
        draws.append(dict(pl.params))
    if pl.name != 'paper':
        assert draws[0] != draws[1] != draws[2]       # a new episode draws new parameters


@pytest.mark.parametrize('name', [n for n in FAMILIES if n not in ('key_confusion', 'glide')])
def test_keyboard_commands_are_discrete(name):
    pl = make_pilot(name, 0.5, 0.5, rng=3, pads=PADS)
    pl.reset(GOAL, START)
    _, cmds = fly(pl)
    speeds = {0.0, pl.cfg.speed_xy_mps, round(float(pl.params.get('speed_xy_mps', pl.cfg.speed_xy_mps)), 9)}
    assert set(np.abs(cmds[:, :2]).ravel().round(9)) <= speeds
    assert set(cmds[:, 2].round(9)) <= {0.0, -pl.cfg.speed_down_mps, pl.cfg.speed_up_mps}


def test_delay_family_lags_the_reference_by_its_delay():
    ref = make_pilot('paper', 0.5, 0.5, rng=7)
    late = make_pilot('delay', 0.5, 0.5, rng=7)
    ref.reset(GOAL, START)
    late.reset(GOAL, START)
    n = late.delay_steps
    assert 0.25 <= late.params['delay_s'] <= 0.8 and n == round(late.params['delay_s'] * 20)
    pos = path()
    r, d = commands(ref, pos), commands(late, pos)
    np.testing.assert_array_equal(d[:n], 0.0)              # nothing pressed before the first reaction
    np.testing.assert_array_equal(d[n:], r[:-n])           # then exactly the reference, n steps late


def test_bang_bang_overshoots_and_reverses():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    pl = make_pilot('bang_bang', 0.5, 1.0, cfg, rng=4)
    pl.reset(GOAL, START, goal_estimate=GOAL.copy())
    p = np.array([GOAL[0] - 6.0, GOAL[1], GOAL[2] + 2.5])
    xs, ux = [], []
    for _ in range(300):
        u = pl.act(p)
        p = p + u * DT
        xs.append(p[0])
        ux.append(u[0])
    xs, ux = np.array(xs), np.array(ux)
    overshoot = xs.max() - GOAL[0]
    speed, delay = pl.params['speed_xy_mps'], pl.params['release_delay_s']
    assert overshoot == pytest.approx(speed * delay, abs=speed * DT + 0.07)   # released delay_s after passing
    assert overshoot > 0.25                                       # the paper pilot stops within its deadband
    assert (np.diff(np.sign(ux[ux != 0])) != 0).sum() >= 1        # reversed at least once
    assert set(np.abs(ux).round(9)) <= {0.0, round(speed, 9)}


def test_bang_bang_commits_to_a_descent_started_while_passing():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    pl = make_pilot('bang_bang', 0.5, 1.0, cfg, rng=4)
    ref = make_pilot('paper', 0.5, 1.0, cfg, rng=4)
    descents = []
    for pilot in (pl, ref):
        pilot.reset(GOAL, START, goal_estimate=GOAL.copy())
        p = np.array([GOAL[0] - 3.0, GOAL[1], GOAL[2] + 2.5])
        down_far = 0
        for _ in range(200):
            u = pilot.act(p)
            p = p + u * DT
            down_far += int(u[2] < 0 and abs(p[0] - GOAL[0]) > pilot.cfg.hold_radius_m)
        descents.append(down_far)
    assert descents[0] > 0 and descents[1] == 0


def test_tapper_taps_near_the_aim_and_freezes():
    pl = make_pilot('tapper', 0.5, 1.0, rng=2)
    pl.reset(GOAL, START)
    p, cmds = fly(pl)
    assert p[2] <= GOAL[2]                                          # it still lands
    near = np.array([np.hypot(*(q[:2] - GOAL[:2])) for q in np.cumsum(np.vstack([START, cmds * DT]), 0)[:-1]])
    horiz = np.abs(cmds[:, :2]).max(axis=1) > 0
    zone = near < pl.params['tap_radius_m'] - 0.6                   # well inside the tapping zone
    # intermittent: within the zone no key is held longer than one tap (tap_s), then released
    runs, run = [], 0
    for h, z in zip(horiz, zone):
        if h and z:
            run += 1
        elif run:
            runs.append(run)
            run = 0
    assert runs and max(runs) <= round(pl.params['tap_s'] / DT) + 1
    assert horiz[zone].mean() < 0.7
    assert set(np.abs(cmds[:, :2]).ravel()) <= {0.0, 1.0}
    # freezes: stretches with no key at all in the air
    idle = ~np.any(cmds != 0, axis=1)
    assert idle.sum() >= 10


def test_late_correction_flies_to_a_neighbour_pad_then_switches():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    pl = make_pilot('late_correction', 0.5, 1.0, cfg, rng=8, pads=PADS)
    pl.reset(GOAL, START)
    neighbours = [PADS[1], PADS[3]]
    first = pl.goal_estimate.copy()
    assert min(np.linalg.norm(first[:2] - q[:2]) for q in neighbours) < 0.4    # a real neighbour pad
    p = START.copy()
    est = []
    for _ in range(1600):
        u = pl.act(p)
        p = p + u * DT
        est.append(pl.goal_estimate.copy())
        if p[2] <= GOAL[2]:
            break
    est = np.array(est)
    k = int(np.argmax(np.linalg.norm(est[:, :2] - first[:2], axis=1) > 1.0))
    assert k > 20 and pl.corrected
    # beta = 1, yet no gradual correction before the switch; a jump of a pad spacing at it
    assert np.linalg.norm(est[k - 1, :2] - first[:2]) < 0.05
    assert np.linalg.norm(est[k, :2] - GOAL[:2]) < 0.4
    assert np.linalg.norm(p[:2] - GOAL[:2]) < 0.5                                  # then lands on the goal


def test_change_mind_reaches_its_goal_then_chooses_another_pad_and_lands_there():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    seen = set()
    for seed in range(8):
        pl = make_pilot('change_mind', 0.5, 1.0, cfg, rng=seed, pads=PADS)
        pl.fcfg.change_mind.switch_time_s = (60.0, 60.0)        # only the low-over-its-aim trigger
        pl.reset(GOAL, START)
        assert pl.new_goal_index is None
        p = START.copy()
        at_switch = None
        for _ in range(2400):
            p = p + pl.act(p) * DT
            if at_switch is None and pl.new_goal_index is not None:
                at_switch = p.copy()
            if p[2] <= 0.5:
                break
        j = pl.new_goal_index
        assert j is not None and j != 2 and pl.params['new_goal_index'] == j
        seen.add(j)
        # it changed its mind low over its first goal, and then flew to the new one
        assert np.hypot(*(at_switch[:2] - GOAL[:2])) < 1.0 and at_switch[2] - GOAL[2] < 1.5
        assert np.array_equal(pl.goal, PADS[j]) and np.linalg.norm(p[:2] - PADS[j][:2]) < 0.6
    assert {1, 3} <= seen                                       # both neighbours occur
    # without the pads it cannot choose a real one: it keeps its goal
    pl = make_pilot('change_mind', 0.5, 1.0, cfg, rng=0)
    pl.reset(GOAL, START)
    for _ in range(600):
        pl.act(START + np.array([12.0, 0.5, -2.5]))
    assert pl.new_goal_index is None and 'switched_at_s' in pl.params


def test_late_correction_without_pads_uses_one_spacing():
    pl = make_pilot('late_correction', 0.5, 0.5, rng=1)
    pl.reset(GOAL, START)
    assert abs(abs(pl.goal_estimate[0] - GOAL[0]) - pl.fcfg.late.fallback_gap_m) < 1e-9


def test_depth_bias_lands_offset_by_its_bias_whatever_the_skill():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    for seed in (1, 2):
        pl = make_pilot('depth_bias', 0.5, 1.0, cfg, rng=seed)
        pl.reset(GOAL, START, goal_estimate=GOAL.copy())
        p, _ = fly(pl)
        b = pl.params['bias_m']
        assert 0.25 <= abs(b) <= 0.6
        assert p[0] - GOAL[0] == pytest.approx(-b, abs=0.1)     # it lands where it believes the goal is


def test_key_confusion_spells_transform_the_reference_command():
    ref = make_pilot('paper', 0.5, 0.5, rng=21)
    kc = make_pilot('key_confusion', 0.5, 0.5, rng=21)
    kc.fcfg.key_confusion.rate_hz = (0.5, 0.5)          # frequent spells for the test
    ref.reset(GOAL, START)
    kc.reset(GOAL, START)
    confused, differ = 0, 0
    for p in path(600):
        kind = kc.confusion
        r, c = ref.act(p), kc.act(p)
        if kind is None and kc.confusion is None:
            np.testing.assert_array_equal(c, r)
        elif kind is not None:
            np.testing.assert_array_equal(c, confuse(r, kind))
            confused += 1
            differ += int(not np.array_equal(c, r))
    assert confused > 40 and differ > 10 and kc.params['spells'] >= 3


def test_confuse_mappings():
    u = np.array([1.0, -1.0, -0.5])
    np.testing.assert_array_equal(confuse(u, 'swap_xy'), [-1.0, 1.0, -0.5])
    np.testing.assert_array_equal(confuse(u, 'flip_x'), [-1.0, -1.0, -0.5])
    np.testing.assert_array_equal(confuse(u, 'flip_z'), [1.0, -1.0, 0.5])
    with pytest.raises(ValueError):
        confuse(u, 'flip_w')


def test_alpha_extremes_follow_or_ignore_the_assistant():
    ign = make_pilot('ignorer', 0.5, 0.0, rng=3)
    fol = make_pilot('follower', 0.5, 0.0, rng=3)
    a = np.array([0.0, 1.0, 0.0])
    moved = []
    for pl in (ign, fol):
        pl.reset(GOAL, START, goal_estimate=GOAL.copy())
        for _ in range(40):                              # 2 s of a 1 m/s push
            pl.update_estimate(a)
        moved.append(pl.goal_estimate[1] - GOAL[1])
    assert 0.0 <= ign.alpha <= 0.1 and 0.9 <= fol.alpha <= 1.0
    assert moved[0] < 0.2 and moved[1] > 1.8


def test_keyboard_composite_has_every_component():
    pl = make_pilot('keyboard', 0.5, 0.5, rng=5, pads=PADS)
    pl.reset(GOAL, START)
    for key in ('delay_s', 'speed_xy_mps', 'tap_s', 'notice_height_m', 'bias_m'):
        assert key in pl.params
    p, _ = fly(pl)
    assert p[2] <= GOAL[2] + 0.05


def test_glide_descends_on_its_way_over_the_nearer_pads_with_a_trembling_stick():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    pl = make_pilot('glide', 0.5, 1.0, cfg, rng=4, pads=PADS)
    goal = PADS[2]
    pl.reset(goal, START, goal_estimate=goal.copy())
    p, cmds, ps = START.copy(), [], []
    for _ in range(600):
        u = pl.act(p)
        p = p + u * DT
        cmds.append(u)
        ps.append(p.copy())
    cmds, ps = np.array(cmds), np.array(ps)
    n = pl.delay_steps
    np.testing.assert_array_equal(cmds[:n], 0.0)              # reacts delay_s late
    moving_down = (cmds[:, 2] < 0) & (np.hypot(*(goal[:2] - ps[:, :2]).T) > 1.5)
    assert moving_down.sum() > 20 and np.all(cmds[moving_down, 0] > 0.3)   # descends while still flying on
    speeds = np.hypot(cmds[n:, 0], cmds[n:, 1])
    assert speeds.max() <= pl.params['max_speed_mps'] + 4 * pl.params['tremor_mps']
    assert len(np.unique(cmds[n:, 0].round(6))) > 100          # analog, not keys
    assert np.hypot(*(ps[-1, :2] - goal[:2])) < 0.4 and ps[-1, 2] < goal[2] + 0.2   # down at its aim


def test_low_flyer_cruises_just_over_the_pad_tops_then_descends_over_its_aim():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    pl = make_pilot('low_flyer', 0.5, 1.0, cfg, rng=2, pads=PADS)
    goal = PADS[2]
    pl.reset(goal, START, goal_estimate=goal.copy())
    z = pl.params['cruise_z_m']
    assert PADS[:, 2].max() + 0.3 <= z <= PADS[:, 2].max() + 0.9
    p, ps = START.copy(), []
    for _ in range(600):
        p = p + pl.act(p) * DT
        ps.append(p.copy())
    ps = np.array(ps)
    transit = np.hypot(*(goal[:2] - ps[:, :2]).T) > 1.0
    late = transit & (np.arange(len(ps)) > 120)               # after its first descent to the cruise height
    assert late.sum() > 20 and np.all(np.abs(ps[late, 2] - z) < 0.15)
    assert np.hypot(*(ps[-1, :2] - goal[:2])) < 0.3 and ps[-1, 2] < z - 0.3


def _fly_cautious(side_probability: float, rng: int):
    fcfg = FamilyConfig(cautious=CautiousConfig(side_probability=side_probability))
    pl = make_pilot('cautious', 0.5, 1.0, PilotConfig(perception_sigma_m=(0.0, 0.0)), rng=rng, pads=PADS,
                    family_cfg=fcfg)
    pl.reset(GOAL, START, goal_estimate=GOAL.copy())
    p, ps, us = START.copy(), [], []
    for _ in range(1600):
        u = pl.act(p)
        p = p + u * DT
        ps.append(p.copy())
        us.append(u)
        if p[2] <= GOAL[2]:
            break
    return pl, np.array(ps), np.array(us)


def test_cautious_climbs_to_look_flies_beside_the_row_and_descends_in_stages():
    pl, ps, us = _fly_cautious(1.0, rng=4)
    prm = pl.params
    # climbs first, straight up, by its look climb, before any horizontal key
    first_move = int(np.argmax(np.any(us[:, :2] != 0, axis=1)))
    assert first_move > 0 and np.all(us[:first_move, 2] == pl.cfg.speed_up_mps)
    assert abs(ps[first_move - 1, 2] - (START[2] + prm['look_climb_m'])) < 0.15
    # beside the row: while still farther than slide_in along x, it flies toward the side line, so it
    # spends most of the transit more than 1 m to the side of the pad row
    side = float(prm['side_m'])
    assert 1.2 <= abs(side) <= 2.5
    far = np.abs(ps[:, 0] - GOAL[0]) > prm['slide_in_m'] + 0.3
    assert np.mean(np.abs(ps[far & (np.arange(len(ps)) > first_move + 60), 1] - GOAL[1]) > 1.0) > 0.8
    # then slides in and lands on the aim, in stages: every stage of continuous descent loses at most
    # step_m (one step's rounding), separated by hovers of check_s
    assert np.hypot(*(ps[-1, :2] - GOAL[:2])) < 0.3
    down = us[:, 2] < 0
    runs, n = [], 0
    for d in down:
        if d:
            n += 1
        elif n:
            runs.append(n)
            n = 0
    if n:
        runs.append(n)
    drop = np.array(runs) * pl.cfg.speed_down_mps * DT
    assert len(runs) >= 3 and np.all(drop <= prm['step_m'] + pl.cfg.speed_down_mps * DT + 1e-9)
    gaps = np.flatnonzero(np.diff(down.astype(int)) == -1)       # a stage ends: a hover of check_s follows
    hover = np.array([np.argmax(down[g + 1:]) for g in gaps[:-1]]) * DT
    assert np.all(np.abs(hover - prm['check_s']) <= 2 * DT)


def test_cautious_without_the_side_approach_flies_straight_to_its_aim():
    pl, ps, _ = _fly_cautious(0.0, rng=4)
    assert pl.params['side_m'] == 0.0
    assert np.max(np.abs(ps[:, 1] - np.linspace(START[1], GOAL[1], len(ps)))) < 0.8
    assert np.hypot(*(ps[-1, :2] - GOAL[:2])) < 0.3
