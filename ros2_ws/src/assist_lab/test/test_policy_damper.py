"""Oscillation damper (assist_policy.damper): reversal detection, the damping action, PolicyCore and evaluate."""
import csv

import numpy as np
import pytest

from assist_policy.blending import blend
from assist_policy.damper import DamperConfig, OscillationDamper
from assist_lab.evaluate import EvalArgs, evaluate
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig

from assist_policy.testing import LATENT, constant_actor

DT = 0.05
MAX_SPEED = (1.0, 1.0, 0.6)
HERE = np.array([5.0, 0.0, 3.0])            # the vehicle's odom position in the tests that do not move it
PADS = np.array([[5.1, 0.1, 0.8]])          # a mapped pad right below it
NO_AGENT = np.zeros(3)                      # the agent action act() passes by default


def swings(half_period_s: float, total_s: float, speed: float = 1.0, z: float = 0.0):
    """(t, u) of a pilot holding +x then -x keys, each for half_period_s, for total_s."""
    n = int(round(half_period_s / DT))
    for k in range(int(round(total_s / DT))):
        sign = 1.0 if (k // n) % 2 == 0 else -1.0
        yield k * DT, np.array([sign * speed, 0.0, z])


def act(d: OscillationDamper, t: float, u, agent=NO_AGENT, velocity=(0.5, 0.0, 0.0), position=HERE,
        pads=PADS):
    """One damper step (default: at HERE over PADS, moving 0.5 m/s along +x)."""
    return d.apply(t, np.asarray(u, dtype=float), agent, np.asarray(velocity, dtype=float), position, pads, MAX_SPEED)


def first_engaged(d: OscillationDamper, commands) -> float | None:
    """Time of the first step the damper acts on, None if never."""
    for t, u in commands:
        if act(d, t, u) is not None:
            return t
    return None


def test_a_pilot_swinging_back_and_forth_is_damped_after_two_reversals():
    d = OscillationDamper()
    t = first_engaged(d, swings(1.5, 10.0))
    # reversals are seen once the latest 0.5 s mean points against the mean 1 s earlier: the first swing
    # reverses at 1.5 s (seen ~2.0 s), the second at 3.0 s (seen ~3.5 s)
    assert t is not None and 3.0 < t < 4.0
    agent = np.array([0.2, -0.1, -0.3])
    a = act(d, t + DT, [1.0, 0.0, 0.0], agent, (0.8, -0.7, 0.1))
    assert a[:2] == pytest.approx([-1.0, 1.0])                # -gain v_xy = (-1.6, 1.4), clipped to the range
    assert a[2] == agent[2]                                    # the vertical action stays the actor's
    a = act(d, t + 2 * DT, [1.0, 0.0, 0.0], agent, (0.3, 0.1, 0.0))
    assert a[:2] == pytest.approx([-0.6, -0.2])
    v = blend(np.array([1.0, 0.0, 0.0]), a)
    assert v[0] == pytest.approx(0.2)                          # V_x = (u - gain v) / 2: the held key slowed


def test_a_held_key_a_single_switch_and_fine_taps_are_not_an_oscillation():
    assert first_engaged(OscillationDamper(), ((k * DT, np.array([1.0, 1.0, 0.0])) for k in range(400))) is None
    switch = [(k * DT, np.array([1.0 if k < 60 else -1.0, 0.0, 0.0])) for k in range(300)]   # back to another pad
    assert first_engaged(OscillationDamper(), switch) is None
    # fine taps: one step pressed in three (0.33 m/s mean), alternating direction every 1.5 s
    taps = [(t, u if int(round(t / DT)) % 3 == 0 else np.zeros(3)) for t, u in swings(1.5, 10.0)]
    assert first_engaged(OscillationDamper(), taps) is None
    # swings slower than the window (one reversal per 9 s) never count two within 8 s
    assert first_engaged(OscillationDamper(), swings(9.0, 30.0)) is None


def test_it_stays_out_during_a_descent_and_lets_go_once_the_swings_stop():
    d = OscillationDamper()
    cmds = list(swings(1.5, 6.0))
    assert [d.oscillating(t, u, HERE) for t, u in cmds].count(True) > 0
    assert [r[0] for r in d._reversals] == pytest.approx([1.85, 3.35, 4.85])   # each counted once, ~0.35 s after it
    t = cmds[-1][0] + DT
    assert act(d, t, [1.0, 0.0, -0.5]) is None
    assert act(d, t + DT, [1.0, 0.0, 0.0]) is not None
    # hovering still: two reversals stay within the 8 s window until the one at 3.35 s leaves it
    still = [(t + 2 * DT + k * DT, np.zeros(3)) for k in range(200)]
    acted = [s for s, u in still if act(d, s, u) is not None]
    assert acted and acted[-1] == pytest.approx(3.35 + 8.0, abs=0.06)


def test_only_swings_across_a_mapped_pad_are_damped():
    """The path between the last two reversals must pass near a mapped pad that the vehicle is still near."""
    def flown(pads):
        d, x, acted = OscillationDamper(), 4.55, []
        for t, u in swings(1.5, 10.0):                         # 0.6 m/s: the vehicle swings over 4.55..5.45 m in x
            x += 0.6 * u[0] * DT
            if act(d, t, u, velocity=(0.6 * u[0], 0, 0), position=np.array([x, 0.0, 3.0]), pads=pads) is not None:
                acted.append(t)
        return acted
    assert flown(PADS)                                         # swinging across the pad at x 5.1
    assert flown(np.array([[5.0, 0.45, 0.8], [9.0, 0.0, 0.5]]))   # 0.45 m beside the swing: still across it
    assert not flown(np.array([[5.0, 0.8, 0.8]]))              # 0.8 m to the side: beside it, not across
    assert not flown(np.zeros((0, 3)))                         # no pad mapped
    assert not flown(np.array([[6.5, 0.0, 0.8]]))              # 1 m beyond the swing's end


def test_a_pilot_leaving_the_pad_after_swinging_across_it_is_let_go():
    """Getting farther from the pad for leave_s (1.5 s) is a departure: the damper stops, the swings recent or not."""
    d, x = OscillationDamper(), 4.55
    for t, u in swings(1.5, 6.0):
        x += 0.6 * u[0] * DT
        act(d, t, u, velocity=(0.6 * u[0], 0, 0), position=np.array([x, 0.0, 3.0]))
    acted = []
    for k in range(80):                                        # then holds +x: over the pad (x 5.1) at ~6.9 s, off
        t, x = 6.0 + k * DT, x + 0.6 * DT
        if act(d, t, [1.0, 0, 0], velocity=(0.6, 0, 0), position=np.array([x, 0.0, 3.0])) is not None:
            acted.append(t)
    # damped while it comes back over the pad, let go 1.5 s after it starts getting farther from it
    assert acted and acted[0] == pytest.approx(6.0) and 8.0 < acted[-1] + DT < 8.5, acted[-1]
    assert acted == pytest.approx([6.0 + k * DT for k in range(len(acted))])


def test_reset_off_bad_input_and_config():
    d = OscillationDamper()
    cmds = list(swings(1.5, 6.0))
    assert first_engaged(d, cmds) is not None
    d.reset()
    assert act(d, 6.0, [1.0, 0, 0]) is None
    assert first_engaged(d, cmds) is not None                  # the clock went back (new landing): starts over
    off = OscillationDamper(DamperConfig(enabled=False))
    assert first_engaged(off, swings(1.5, 10.0)) is None
    assert act(d, 7.0, [np.nan, 0, 0]) is None
    assert act(d, 7.05, [1.0, 0, 0], velocity=(np.inf, 0, 0)) is None
    assert act(d, 7.1, [1.0, 0, 0], position=np.array([np.nan, 0, 3.0])) is None
    for bad in ({'gain': float('nan')}, {'window_s': -1.0}, {'mean_s': 0.0}, {'min_reversals': 0},
                {'cross_radius_m': -0.1}):
        with pytest.raises(ValueError):
            DamperConfig(**bad)


def test_policy_core_damps_an_oscillating_pilot_and_reports_it(tmp_path):
    path = constant_actor(tmp_path / 'nudge.pt', [0.1, 0.0, 0.0])
    depth = np.full((64, 64), 3.0 - 0.05, np.float32)          # from 3 m: floor, and a 0.8 m pad right below
    depth[22:42, 22:42] = 3.0 - 0.05 - 0.8
    for enabled in (True, False):
        core = PolicyCore(path, PolicyCoreConfig(mode='latent', damper=DamperConfig(enabled=enabled)))
        keys = []
        for t, u in swings(1.5, 6.0):
            core.set_odom(t, [0.0, 0.0, 3.0], [0.4 * np.sign(u[0]), 0.0, 0.0])
            core.set_depth(t, depth)
            core.set_latent(t, np.zeros(LATENT))
            core.set_pilot(t, u)
            out = core.step(t)
            keys.append(out.key)
        if enabled:
            assert (out.key == 'oscillation_damper' and core.engaged['oscillation_damper'] > 0
                    and len(core.recall.map.pads) == 1)
            assert out.agent[:2] == pytest.approx([-2.0 * 0.4 * np.sign(u[0]), 0.0])
            assert keys.count('oscillation_damper') == core.engaged['oscillation_damper']
        else:
            assert 'oscillation_damper' not in keys and core.engaged['oscillation_damper'] == 0
    core.reset()
    assert act(core.damper, 0.0, [1.0, 0, 0]) is None


def test_evaluate_damper_rows_and_column(tmp_path):
    """A delay pilot (0.63 s) circling the goal pad at beta 1 lands with the damper (it timed out without)."""
    out = tmp_path / 'ev'
    evaluate(EvalArgs(out=str(out), conditions=('latent',), betas=(1.0,), landings=1, seed=10014, pilot='delay',
                      safety=True, override=True, recall=True, damper=True, plot=False))
    rows = list(csv.DictReader(open(out / 'landings.csv')))
    assert [r['condition'] for r in rows] == ['latent+guard+override+recall+damper']
    assert float(rows[0]['damper_fraction']) > 0.05
    assert rows[0]['outcome'] == 'success' and float(rows[0]['duration_s']) < 45.0
