"""The flight monitor (assist_policy.flight) on what real vehicles give it: EKF noise, a vehicle that does not follow
the descent, a frozen odometry source, a 0.3 m wander on the ground, a clock that steps back, the vehicle's own
landed state; and the core's ~/reset rate limit."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from assist_policy.flight import FlightConfig, FlightMonitor, LandedState, surface_clearance
from assist_policy.policy_core import InputRejected, PolicyCore, PolicyCoreConfig

_spec = importlib.util.spec_from_file_location('policy_core_helpers_flight',
                                               Path(__file__).with_name('test_policy_core.py'))
_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_helpers)

DT = 0.05                 # odometry period (20 Hz, the control rate)
SIGMA_V = 0.03            # EKF velocity noise per axis, white (m/s)
SIGMA_P = 0.01            # EKF position noise per axis, white (m); the velocity noise integrates into it too
LEGS = 0.12               # base_link over the surface when standing on it (the sim's legs)
SEEDS = range(12)


def ekf(rng: np.random.Generator, z: np.ndarray, vz: np.ndarray, xy=(2.0, 1.0)):
    """Noisy odometry (positions, velocities) of a true vertical trajectory `z`, `vz` at DT, hovering over `xy`."""
    n = len(z)
    truth_p = np.column_stack([np.full(n, xy[0]), np.full(n, xy[1]), z])
    truth_v = np.column_stack([np.zeros(n), np.zeros(n), vz])
    v_noise = rng.normal(0.0, SIGMA_V, (n, 3))
    p = truth_p + rng.normal(0.0, SIGMA_P, (n, 3)) + np.cumsum(v_noise, axis=0) * DT
    return p, truth_v + v_noise


def landing_then_takeoff(surface: float):
    """Descend from 3 m at 0.5 m/s onto `surface` (command held down 2 s after touchdown... and on), rest, climb
    at 0.8 m/s from t = 10 s: (times, true z, true vz, command vz, touchdown time, lift-off time)."""
    t = np.arange(0.0, 14.0, DT)
    rest = surface + LEGS
    touchdown = (3.0 - rest) / 0.5
    z = np.where(t < touchdown, 3.0 - 0.5 * t, rest)
    vz = np.where(t < touchdown, -0.5, 0.0)
    cmd = np.full(t.size, -0.5)
    climb = t >= 10.0
    z = np.where(climb, rest + 0.8 * (t - 10.0), z)
    vz = np.where(climb, 0.8, vz)
    cmd = np.where(climb, 0.8, cmd)
    return t, z, vz, cmd, touchdown, 10.0


def run(monitor: FlightMonitor, t, p, v, cmd) -> list[tuple[float, str]]:
    """Feed the samples; the boundaries seen, with their times."""
    seen = []
    for k in range(len(t)):
        b = monitor.update(t[k], p[k], v[k], cmd[k])
        if b is not None:
            seen.append((float(t[k]), b))
    return seen


@pytest.mark.parametrize('surface', [0.0, 0.85])      # the floor, a pad's top
def test_noisy_ekf_landing_and_takeoff_are_seen_promptly(surface):
    for seed in SEEDS:
        t, z, vz, cmd, touchdown, liftoff = landing_then_takeoff(surface)
        p, v = ekf(np.random.default_rng(seed), z, vz)
        seen = run(FlightMonitor(), t, p, v, cmd)
        assert [b for _, b in seen] == ['landed', 'takeoff'], (seed, seen)
        (t_land, _), (t_off, _) = seen
        assert touchdown < t_land <= touchdown + 2.0, (seed, seen)          # rest_s 1 s, within a couple
        assert liftoff < t_off <= liftoff + 1.5, (seed, seen)                # 0.5 m at 0.8 m/s, then the window


def test_a_hover_with_a_descending_command_is_not_a_landing():
    t = np.arange(0.0, 30.0, DT)
    z, vz, cmd = np.full(t.size, 2.5), np.zeros(t.size), np.full(t.size, -0.3)
    # a vehicle that does not follow the descent (an autopilot's altitude floor, a link that drops the setpoints):
    # motionless, exactly or with EKF noise
    m = FlightMonitor()
    assert run(m, t, np.column_stack([np.full(t.size, 2.0), np.full(t.size, 1.0), z]), np.zeros((t.size, 3)),
               cmd) == []
    assert not m.landed
    for seed in SEEDS:
        p, v = ekf(np.random.default_rng(seed), z, vz)
        m = FlightMonitor()
        assert run(m, t, p, v, cmd) == [] and not m.landed, seed


def test_odometry_frozen_mid_air_is_not_a_landing_while_the_camera_sees_the_floor_far_below():
    m = FlightMonitor()
    t = np.arange(0.0, 20.0, DT)
    z_true = np.maximum(3.0 - 0.5 * t, 1.8)                # the vehicle descends to 1.8 m and hovers there...
    frozen = 2.0                                           # ... its odometry froze at 2.0 m, stamps still fresh
    seen = []
    for k, tk in enumerate(t):
        z_odom = z_true[k] if z_true[k] > frozen else frozen
        vz = -0.5 if z_true[k] > frozen else 0.0
        b = m.update(tk, [2.0, 1.0, z_odom], [0.0, 0.0, vz], -0.5)
        m.observe_surface(tk, z_true[k])                   # the depth camera: the floor, z_true below
        if b is not None:
            seen.append((tk, b))
    assert seen == [] and not m.landed


def test_a_small_wander_on_the_ground_is_no_takeoff_a_climb_is():
    rng = np.random.default_rng(7)
    parts = [np.full(60, LEGS),                                        # 3 s standing: starts landed
             LEGS + np.minimum(np.arange(1, 101) * DT * 0.3, 0.3),     # a 0.3 m rise (EKF wander, a hop) held
             np.full(40, LEGS),                                        # back down
             LEGS + np.arange(1, 1201) * DT * 0.45 / 60.0]             # 0.45 m of slow drift over a minute
    z = np.concatenate(parts)
    vz = np.gradient(z, DT)
    t = np.arange(z.size) * DT
    cmd = np.zeros(z.size)
    p, v = ekf(rng, z, vz)
    m = FlightMonitor()
    assert run(m, t, p, v, cmd) == [] and m.landed
    # then a real take-off: 0.6 m/s up to 2 m
    climb = z[-1] + 0.6 * DT * np.arange(1, 80)
    t2 = t[-1] + DT * np.arange(1, 80)
    p2, v2 = ekf(rng, climb, np.full(climb.size, 0.6))
    p2 += p[-1] - np.array([2.0, 1.0, z[-1]])              # the EKF's drift carries on
    seen = run(m, t2, p2, v2, np.full(climb.size, 0.6))
    assert [b for _, b in seen] == ['takeoff'] and not m.landed
    assert seen[0][0] - t2[0] < 0.5 / 0.6 + 0.6


def test_a_clock_stepping_back_does_not_delay_the_landing():
    t, z, vz, cmd, touchdown, _ = landing_then_takeoff(0.85)
    keep = t < 9.0
    t, z, vz, cmd = t[keep], z[keep], vz[keep], cmd[keep]
    p = np.column_stack([np.full(t.size, 2.0), np.full(t.size, 1.0), z])          # exact odometry: the step alone
    v = np.column_stack([np.zeros(t.size), np.zeros(t.size), vz])
    step_at = int((touchdown + 0.3) / DT)                   # 0.3 s after touchdown the clock steps back 10 s
    stamps = np.where(np.arange(t.size) >= step_at, t - 10.0, t)
    m = FlightMonitor()
    seen = run(m, stamps, p, v, cmd)
    assert [b for _, b in seen] == ['landed'] and m.clock_steps == 1
    k_land = int(np.flatnonzero(stamps == seen[0][0])[0])
    # seen about rest_s after touchdown by the samples' count, as without the step (not 10 s later)
    assert touchdown < t[k_land] <= touchdown + 2.0


def test_the_vehicle_landed_state_wins_over_odometry():
    m = FlightMonitor()
    L = LandedState
    assert m.vehicle_state(0.0, L.IN_AIR) is None and not m.landed        # the first report: where it stands
    t, z, vz, cmd, touchdown, _ = landing_then_takeoff(0.0)
    p, v = ekf(np.random.default_rng(1), z, vz)
    stop = int(8.0 / DT)
    seen = []
    for k in range(stop):                # odometry says landed (at rest after coming down); the vehicle: in the air
        if k % 10 == 0:
            assert m.vehicle_state(t[k], L.IN_AIR) is None
        b = m.update(t[k], p[k], v[k], cmd[k])
        if b is not None:
            seen.append(b)
    assert seen == [] and not m.landed
    assert m.vehicle_state(t[stop], L.ON_GROUND) == 'vehicle_landed' and m.landed
    assert 'ON_GROUND' in m.last_detail
    assert m.vehicle_state(t[stop] + 0.5, L.ON_GROUND) is None             # repeated reports: one boundary
    # odometry climbing 0.8 m at 0.8 m/s while the vehicle still says ON_GROUND: not a take-off
    for k in range(20):
        tk = t[stop] + 0.5 + DT * (k + 1)
        if k % 10 == 0:
            m.vehicle_state(tk, L.ON_GROUND)
        assert m.update(tk, [2.0, 1.0, LEGS + 0.04 * (k + 1)], [0, 0, 0.8], 0.8) is None
    assert m.landed
    assert m.vehicle_state(tk, L.TAKEOFF) == 'vehicle_takeoff' and not m.landed
    assert m.vehicle_state(tk + 0.5, L.IN_AIR) is None
    assert m.update(tk + DT, [9.0, 1.0, 1.0], [0, 0, 0], 0.0) == 'odom_jump'   # a jump still counts
    with pytest.raises(ValueError):
        m.vehicle_state(tk, 7)


def test_a_stale_or_undefined_landed_state_hands_back_to_odometry():
    for last_report in (LandedState.IN_AIR, LandedState.UNDEFINED):
        m = FlightMonitor(FlightConfig(landed_state_timeout_s=2.0))
        m.vehicle_state(0.0, LandedState.IN_AIR)
        m.vehicle_state(0.5, last_report)                   # then nothing more: stale from 2.5 s on
        t, z, vz, cmd, touchdown, _ = landing_then_takeoff(0.0)
        p, v = ekf(np.random.default_rng(2), z, vz)
        seen = run(m, t[t < 9.0], p, v, cmd)
        assert [b for _, b in seen] == ['landed'], (last_report, seen)
        assert seen[0][0] <= touchdown + 2.0


def test_surface_clearance_reads_the_centre_of_the_depth_image():
    d = np.full((64, 64), 2.0, np.float32)
    assert surface_clearance(d, 0.05) == pytest.approx(2.05)
    d[24:40, 24:40] = 0.0                                   # the camera too near to see (holes): no evidence
    assert surface_clearance(d, 0.05) is None


def test_policy_core_landed_state_input_and_reset_rate_limit(tmp_path):
    core = PolicyCore(_helpers.constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0]),
                      PolicyCoreConfig(mode='latent'))
    core.set_odom(0.0, [0, 0, 2.0], [0, 0, 0])
    core.set_landed_state(0.0, 2)                            # IN_AIR: where it stands
    core.set_landed_state(1.0, 1)                            # ON_GROUND: the flight ends
    assert core.flight_resets['vehicle_landed'] == 1 and core.last_reset == (1.0, 'vehicle_landed')
    assert 'ON_GROUND' in core.last_reset_detail
    core.set_landed_state(2.0, 3)
    assert core.flight_resets['vehicle_takeoff'] == 1
    with pytest.raises(InputRejected) as exc:
        core.set_landed_state(2.5, 9)
    assert exc.value.reason == 'landed_state_range' and core.rejections['landed_state_range'] == 1
    # ~/reset: at most one per flight_reset_min_interval_s (1 s)
    assert core.request_reset(10.0)[0]
    ok, why = core.request_reset(10.5)
    assert not ok and 'flight_reset_min_interval_s' in why and core.flight.resets_refused == 1
    assert core.flight_resets['service'] == 1
    assert core.request_reset(11.0)[0]
    assert core.request_reset(3.0)[0]                        # the clock stepped back: the interval starts anew
    assert core.flight_resets['service'] == 3
    core.configure(flight={'reset_min_interval_s': 0.0})     # 0: no limit
    assert core.request_reset(3.0)[0] and core.request_reset(3.0)[0]


def test_policy_core_camera_vetoes_a_landing_its_odometry_would_make(tmp_path):
    """A vehicle that stops descending at 2 m (or whose odometry froze there) while the pilot holds the descent:
    came down, at rest, the command descends; the depth frames show the floor 2 m below: not landed."""
    core = PolicyCore(_helpers.constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0]),
                      PolicyCoreConfig(mode='latent'))
    floor = np.full((64, 64), 2.0 - 0.05, np.float32)
    for k in range(200):
        tk = k * DT
        z = max(3.0 - 0.5 * tk, 2.0)
        core.set_odom(tk, [0, 0, z], [0, 0, -0.5 if z > 2.0 else 0.0])
        core.set_depth(tk, np.full((64, 64), z - 0.05, np.float32) if z > 2.0 else floor)
        core.set_pilot(tk, [0, 0, -0.5])
        assert core.step(tk).velocity[2] == pytest.approx(-0.5)   # the command flown descends throughout
    assert sum(core.flight_resets.values()) == 0 and not core.flight.landed


def test_policy_core_after_a_clock_step_back_takes_depth_frames_again(tmp_path):
    """A boundary dates the flight's start (older depth frames are refused); a clock that steps back behind that
    date must not blind the floor guard until the clock makes the step up."""
    core = PolicyCore(_helpers.constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0]),
                      PolicyCoreConfig(mode='latent'))
    core.set_odom(100.0, [0, 0, 3.0], [0, 0, 0])
    core.set_odom(100.05, [5.0, 0, 3.0], [0, 0, 0])          # a jump: the flight starts at 100.05 s
    assert core.flight_resets['odom_jump'] == 1
    with pytest.raises(InputRejected):
        core.set_depth(100.06, np.full((64, 64), 2.95, np.float32), stamp=100.0)
    core.set_odom(10.0, [5.0, 0, 3.0], [0, 0, 0])            # the clock steps back 90 s
    core.set_depth(10.01, np.full((64, 64), 2.95, np.float32), stamp=10.0)   # taken, not 'before the flight'
    assert core.rejections['depth_before_flight'] == 1 and core.flight.clock_steps == 1
