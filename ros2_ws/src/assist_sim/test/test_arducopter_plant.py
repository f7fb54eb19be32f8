"""ArduCopter's GUIDED velocity response as a plant: the model on its own and flown in the landing world."""
import math

import numpy as np
import pytest

from assist_sim.core.arducopter import (ArduCopterConfig, GuidedVelocityModel, randomised, simulate,
                                        sqrt_controller)
from assist_sim.core.config import WorldConfig
from assist_sim.core.world import LandingWorld

DT = 0.05


def _hold(t_end: float, value, until: float, axis: int = 0):
    t = np.arange(0.0, t_end, DT)
    sp = np.zeros((len(t), 3))
    sp[t < until, axis] = value
    return t, sp


def _ideal_response(t, sp):
    """The ideal plant's velocity for the same setpoints (pybullet world, no turbulence, high above the floor)."""
    cfg = WorldConfig()
    cfg.turbulence.enabled = False
    w = LandingWorld(cfg, seed=0)
    try:
        w.reset(seed=1, start_position=(0.0, 0.0, 3.0))
        out = [w.state.velocity.copy()]
        for i in range(1, len(t)):
            out.append(w.step(sp[i - 1], dt=DT, frame='world').velocity.copy())
        return np.array(out)
    finally:
        w.close()


def test_sqrt_controller_is_linear_near_zero_and_sqrt_shaped_beyond():
    assert sqrt_controller(0.01, 2.0, 5.0, 0.0) == pytest.approx(0.02)
    big = sqrt_controller(10.0, 2.0, 5.0, 0.0)
    assert big == pytest.approx(math.sqrt(2 * 5.0 * (10.0 - 0.5 * 5.0 / 4.0)))
    assert sqrt_controller(-10.0, 2.0, 5.0, 0.0) == pytest.approx(-big)
    assert sqrt_controller(0.01, 100.0, 5.0, 0.1) == pytest.approx(0.1)     # never past the error in one step


def test_braking_takes_longer_than_the_ideal_loop_and_the_shaped_target_respects_its_limits():
    t, sp = _hold(12.0, 1.0, 6.0)
    cfg = ArduCopterConfig()
    v, p = simulate(cfg, t, sp)
    i = int(np.searchsorted(t, 6.0))
    assert abs(v[i, 0] - 1.0) < 0.02                       # reached the setpoint
    brake = p[-1, 0] - p[i, 0]
    v_ideal = _ideal_response(t, sp)
    brake_ideal = float(np.sum(v_ideal[i:, 0]) * DT)
    assert brake > 1.5 * brake_ideal                       # documented: about twice the ideal loop's
    assert brake > 1.0 ** 2 / (2 * cfg.accel_xy_mps2)      # never shorter than the acceleration limit allows
    accel = np.diff(v[:, 0]) / DT
    assert np.max(np.abs(accel)) <= cfg.accel_xy_mps2 * 1.05


def test_quick_reversals_are_smoothed_away():
    t = np.arange(0.0, 8.0, DT)
    sp = np.zeros((len(t), 3))
    sp[:, 0] = np.where((t // 0.25) % 2 == 0, 1.0, -1.0)
    v, _ = simulate(ArduCopterConfig(), t, sp)
    v_ideal = _ideal_response(t, sp)
    half = len(t) // 2
    ptp = np.ptp(v[half:, 0])
    assert ptp < 0.5 * np.ptp(v_ideal[half:, 0])
    assert ptp < 0.3


def test_a_setpoint_acts_only_after_the_setpoint_delay():
    cfg = ArduCopterConfig(setpoint_delay_s=0.2)
    m = GuidedVelocityModel(cfg)
    m.reset(np.zeros(3), np.zeros(3))
    m.command([1.0, 0.0, 0.0])
    for _ in range(19):          # 0.19 s
        a = m.tick(np.zeros(3), np.zeros(3), 0.01)
        assert np.allclose(a, 0.0)
    for _ in range(5):
        a = m.tick(np.zeros(3), np.zeros(3), 0.01)
    assert a[0] > 0.0


def test_path_hold_pulls_a_lagging_vehicle_back_onto_the_path():
    """A vehicle held back for a second catches up with the path when held, and does not when not."""
    ends = {}
    for hold in (True, False):
        cfg = ArduCopterConfig(path_hold=hold, vel_xy_i=0.0)     # the path alone (the integrator also catches up)
        m = GuidedVelocityModel(cfg)
        m.reset(np.zeros(3), np.zeros(3))
        pos, vel = np.zeros(3), np.zeros(3)
        for k in range(int(8.0 / 0.01)):
            m.command([1.0, 0.0, 0.0]) if k % 5 == 0 else None
            a = np.array(m.tick(pos, vel, 0.01))
            if 200 <= k < 300:            # held: no motion for a second
                vel = np.zeros(3)
                continue
            pos, vel = pos + vel * 0.01 + 0.5 * a * 1e-4, vel + a * 0.01
        ends[hold] = pos[0]
    assert ends[True] > ends[False] + 0.5


def test_landed_model_idles_and_ignores_setpoints_until_takeoff():
    m = GuidedVelocityModel()
    m.reset(np.zeros(3), np.zeros(3), landed=True)
    m.command([1.0, 0.0, 1.0])
    a = m.tick(np.zeros(3), np.zeros(3), 0.1)
    assert a[0] == 0.0 and a[2] < -0.9 * m.g
    m.takeoff(np.zeros(3), np.zeros(3))
    m.command([0.0, 0.0, 1.0])
    for _ in range(30):
        a = m.tick(np.zeros(3), np.zeros(3), 0.01)
    assert a[2] > 0.0 and not m.landed


def test_settings_out_of_range_are_refused_with_the_setting_named():
    with pytest.raises(ValueError, match=r'arducopter\.accel_xy_mps2 must be <= 10'):
        GuidedVelocityModel(ArduCopterConfig(accel_xy_mps2=99.0))
    with pytest.raises(ValueError, match=r'arducopter\.attitude_tc_s'):
        LandingWorld(WorldConfig(flight_controller='arducopter', arducopter=ArduCopterConfig(attitude_tc_s=0.0)))
    with pytest.raises(ValueError, match='flight_controller must be one of'):
        LandingWorld(WorldConfig(flight_controller='px4'))
    with pytest.raises(ValueError, match=r'touchdown\.descent_mps'):
        cfg = WorldConfig(flight_controller='arducopter')
        cfg.touchdown.descent_mps = 0.0
        LandingWorld(cfg)


def test_randomised_settings_stay_within_the_spread_and_in_range():
    base = ArduCopterConfig()
    r = randomised(base, np.random.default_rng(3), 0.3)
    r.validate()
    assert r != base
    for name in ('accel_xy_mps2', 'attitude_tc_s', 'vel_xy_p'):
        assert 0.7 * getattr(base, name) <= getattr(r, name) <= 1.3 * getattr(base, name)
    assert r.land_detect_s == base.land_detect_s
    with pytest.raises(ValueError):
        randomised(base, np.random.default_rng(0), 1.5)


# ------------------------------------------------------------------------------------------ in the world
def _land(world: LandingWorld, seed: int, lateral_at_contact: float = 0.0, max_steps: int = 1500):
    """Fly over the goal pad and descend onto it; returns (result, max tilt in degrees)."""
    st = world.reset(seed=seed)
    goal = world.goal_position
    tilt = 0.0
    for _ in range(max_steps):
        if world.done:
            break
        d = goal - st.position
        v = np.zeros(3)
        v[:2] = np.clip(0.8 * d[:2], -1.5, 1.5)
        low = st.height_above_surface < 0.3            # the last decimetres: the legs are about to touch
        over = np.linalg.norm(d[:2]) < 0.15 or low
        v[2] = -0.6 if over else (0.0 if st.position[2] > goal[2] + 1.0 else 0.5)
        if low and lateral_at_contact:
            v[:2] = (lateral_at_contact, 0.0)
        st = world.step(v, frame='world')
        r = world._bc.getMatrixFromQuaternion(st.quaternion)
        tilt = max(tilt, math.degrees(math.acos(min(1.0, r[8]))))
    return world.result, tilt


def test_the_arducopter_plant_lands_where_its_land_detector_agrees_and_the_airframe_leans():
    w = LandingWorld(WorldConfig(flight_controller='arducopter'), seed=0)
    ideal = LandingWorld(WorldConfig(), seed=0)
    try:
        for seed in (101, 102, 103):
            res, tilt = _land(w, seed)
            assert res is not None and res.outcome == 'success', res
            assert res.autopilot_landed is True
            assert w.flight_controller.landed
            assert tilt > 5.0                      # leaning to accelerate: the camera sees it
            res_i, tilt_i = _land(ideal, seed)
            assert res_i.outcome == 'success' and res_i.autopilot_landed is None
            assert tilt_i < 4.0
    finally:
        w.close()
        ideal.close()


def test_a_sideways_command_at_contact_keeps_arducopter_flying_unless_the_envelope_takes_the_descent():
    cfg = WorldConfig(flight_controller='arducopter')
    cfg.touchdown.enabled = False
    bare = LandingWorld(cfg, seed=0)
    w = LandingWorld(WorldConfig(flight_controller='arducopter'), seed=0)
    try:
        res, _ = _land(bare, 101, lateral_at_contact=0.6)
        assert res is None or res.autopilot_landed is not True
        assert not bare.flight_controller.landed
        res, _ = _land(w, 101, lateral_at_contact=0.6)
        assert res.autopilot_landed is True and w.touchdown.engagements >= 1
    finally:
        bare.close()
        w.close()


def test_a_climb_setpoint_takes_off_again_after_a_landing():
    w = LandingWorld(WorldConfig(flight_controller='arducopter'), seed=0)
    try:
        res, _ = _land(w, 101)
        assert w.flight_controller.landed
        z0 = w.state.position[2]
        for _ in range(40):
            st = w.step([0.0, 0.0, 1.0], frame='world')
        assert not w.flight_controller.landed and st.position[2] > z0 + 0.5
    finally:
        w.close()
