"""The ArduCopter GUIDED model against logs of real ArduCopter SITL flying our airframe (test/fixtures/guided).

The model's defaults are the values `fit_guided` fitted to the non-random sequences; the random pilot-like
sequences were never fitted and test it. A fixture that no longer matches fails with the numbers."""
from pathlib import Path

import numpy as np
import pytest

from assist_sim.core.arducopter import ArduCopterConfig
from assist_sim.core.config import WorldConfig
from assist_sim.core.world import LandingWorld
from assist_sim.guided_fit import HELD_OUT_PREFIX, load_fixture, response, rmse, step_metrics

FIXTURES = Path(__file__).parent / 'fixtures' / 'guided'
SEQUENCES = sorted(p for p in FIXTURES.glob('*.csv') if not p.name.startswith('touchdown'))
HELD_OUT_RMSE_MPS = 0.05         # the stated bound on sequences never fitted
FITTED_RMSE_MPS = 0.04
RISE_TOL_S = 0.10                # 10-90 % rise time of a step: model within this of SITL's
OVERSHOOT_TOL = 0.03             # overshoot (fraction of the step): within this
BRAKE_TOL_M = 0.08               # distance to stop from the step's speed (SITL: 0.64-0.72 m): within this
TOUCHDOWN_TOL_S = 0.15           # contact to the landing declared: within this (SITL's spread is 0.05 s)


def test_the_fixtures_cover_fitted_and_held_out_sequences():
    names = [p.stem for p in SEQUENCES]
    assert sum(n.startswith(HELD_OUT_PREFIX) for n in names) >= 2
    assert {'step_x_pos', 'step_z', 'square_x_0p25', 'chirp_x'} <= set(names)


@pytest.mark.parametrize('path', SEQUENCES, ids=lambda p: p.stem)
def test_the_model_reproduces_each_sitl_sequence(path):
    fx = load_fixture(path)
    bound = HELD_OUT_RMSE_MPS if fx.held_out else FITTED_RMSE_MPS
    err = rmse(ArduCopterConfig(), fx)
    assert err <= bound, f'{fx.name}: velocity RMSE {err:.4f} m/s against SITL (bound {bound})'


@pytest.mark.parametrize('name,axis', [('step_x_pos', 0), ('step_x_neg', 0), ('step_y_pos', 1), ('step_y_neg', 1),
                                       ('step_z', 2), ('step_diag', 0)])
def test_steps_rise_overshoot_and_brake_as_sitl_does(name, axis):
    fx = load_fixture(FIXTURES / f'{name}.csv')
    model = response(ArduCopterConfig(), fx)
    cmd = fx.cmd[:, axis]
    changes = np.flatnonzero(np.diff(cmd) != 0) + 1
    on, off = changes[0], changes[1] if len(changes) > 1 else len(cmd) - 1
    v0, v1 = float(cmd[on - 1]), float(cmd[on])
    window = slice(0, off)
    sitl_m = step_metrics(fx.t[window], fx.vel[window, axis], fx.t[on], v0, v1)
    model_m = step_metrics(fx.t[window], model[window, axis], fx.t[on], v0, v1)
    assert abs(model_m['rise_s'] - sitl_m['rise_s']) <= RISE_TOL_S, (name, model_m, sitl_m)
    assert abs(model_m['overshoot'] - sitl_m['overshoot']) <= OVERSHOOT_TOL, (name, model_m, sitl_m)
    if cmd[off] == 0.0:            # the step ends by stopping: the distance it takes
        dt = np.diff(fx.t[off:])
        brake_sitl = float(np.sum(fx.vel[off:-1, axis] * dt))
        brake_model = float(np.sum(model[off:-1, axis] * dt))
        assert abs(brake_model - brake_sitl) <= BRAKE_TOL_M, (name, brake_model, brake_sitl)


def test_quick_reversals_drift_as_on_sitl():
    """A +-1 m/s square wave reversed every 0.25 s: ArduCopter's shaping never reverses, the vehicle drifts."""
    fx = load_fixture(FIXTURES / 'square_x_0p25.csv')
    model = response(ArduCopterConfig(), fx)
    steady = (fx.t > 4.0) & (fx.cmd[:, 0] != 0.0)
    for v in (fx.vel[steady, 0], model[steady, 0]):
        assert np.ptp(v) < 0.2
    assert abs(model[steady, 0].mean() - fx.vel[steady, 0].mean()) < 0.1


def _touchdowns() -> list[dict]:
    lines = [ln for ln in (FIXTURES / 'touchdown.csv').read_text().splitlines() if not ln.startswith('#')]
    cols = lines[0].split(',')
    return [dict(zip(cols, ln.split(','))) for ln in lines[1:]]


def _model_touchdown(lateral: float, release_at_contact: bool, descent: float, wait_s: float) -> float | None:
    """Contact-to-landed delay of the ArduCopter plant descending onto the floor (None: never within wait_s)."""
    cfg = WorldConfig(flight_controller='arducopter')
    cfg.turbulence.enabled = False
    cfg.touchdown.enabled = False          # the raw autopilot, as the SITL trials flew it
    w = LandingWorld(cfg, seed=0)
    try:
        w.reset(seed=5, start_position=(0.0, 0.0, 1.0))
        contact = None
        while w.episode_time < 30.0:
            held = lateral if contact is None or not release_at_contact else 0.0
            w.step([held, 0.0, -descent], frame='world', dt=0.01)
            if contact is None and w._was_touching:
                contact = w.episode_time
            if w.flight_controller.landed:
                return w.episode_time - contact
            if contact is not None and w.episode_time - contact > wait_s:
                return None
        return None
    finally:
        w.close()


def test_touchdowns_are_declared_as_sitl_declares_them():
    trials = _touchdowns()
    assert len(trials) >= 3
    for tr in trials:
        lateral, release = float(tr['lateral_cmd_mps']), tr['lateral_released_at_contact'] == '1'
        came = tr['on_ground_came'] == '1'
        delay = _model_touchdown(lateral, release, float(tr['descent_cmd_mps']), wait_s=8.0)
        if came:
            assert delay is not None, f'{tr["trial"]}: SITL declared it after {tr["delay_s"]} s, the model never'
            assert abs(delay - float(tr['delay_s'])) <= TOUCHDOWN_TOL_S, (tr['trial'], delay, tr['delay_s'])
        else:
            assert delay is None, f'{tr["trial"]}: SITL never declared this landing, the model did after {delay:.2f} s'
