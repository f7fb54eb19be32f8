"""Rigid-body quad-X driven by motor PWM: the landing world as ArduPilot SITL's physics (JSON backend).

In `physics: ardupilot_json` mode the velocity-tracking controller of `LandingWorld` is not used:
the same pybullet airframe (box body, four leg links, same mass, contacts and landing judge) is
flown by four motors whose PWM comes from ArduCopter SITL. Pure Python (numpy + pybullet), no rclpy.

Motor layout (ArduPilot FRAME_CLASS 1 QUAD, FRAME_TYPE 1 X; checked against
libraries/SITL/SIM_Frame.cpp `quad_x_motors` and AP_MotorsMatrix, ArduPilot commit 90700977c553):

    servo 1: angle  45 deg (front right), CCW      servo 3: angle -45 deg (front left), CW
    servo 2: angle -135 deg (back left),  CCW      servo 4: angle 135 deg (back right), CW

Angles are measured clockwise from the nose in body FRD. A CCW propeller's reaction torque yaws the
body clockwise seen from above, i.e. +z in FRD (SIM_Motor.cpp: rotor_torque = thrust_vector *
yaw_factor * ..., thrust_vector = (0, 0, -1), YAW_FACTOR_CCW = +1); in our FLU body that is -z.

Motor model (per motor, same shape as ArduPilot's own SIM_Motor.cpp `pwm_to_command` and
`calc_thrust`, so ArduCopter's thrust linearisation is exact for it):

    c*  = clamp((pwm - pwm_spin_min) / (pwm_spin_max - pwm_spin_min), 0, 1)
          pwm_spin_min = PWM_MIN + SPIN_MIN (PWM_MAX - PWM_MIN), likewise pwm_spin_max
    c  -> c* first order with time constant `motor_time_constant_s`
    T   = max_thrust_n ((1 - expo) c + expo c^2)            (expo = MOT_THST_EXPO)
    Q   = yaw_torque_per_thrust_m * T                        (rotor drag torque)

so ArduCopter's hover throttle (MOT_THST_HOVER, a thrust fraction) is m g / (4 max_thrust_n):
0.42 with the defaults (1.2 kg, 7 N per motor). Aerodynamic drag on the body is
-(linear + quadratic |v|) v, plus angular damping. Ground-effect turbulence is the velocity-mode
noise process (`world.turbulence_sigma`, same std and correlation time) turned into a disturbance
force m K n, with K the velocity-loop gains of the velocity controller (kp_xy, kp_xy, kp_z): a
vehicle holding its velocity that stiffly sees the same velocity disturbance as in velocity mode.

Frames (ArduPilot JSON readme and SIM_JSON.cpp): positions/velocities NED, body FRD, attitude as
the rotation body FRD -> NED. Our world is ENU with body FLU:
    NED = (y, x, -z) of ENU;  FRD = (x, -y, -z) of FLU;  R_ned_frd = T R_enu_flu F.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as p

from .world import LandingWorld, turbulence_sigma

# ENU -> NED (symmetric, its own inverse) and FLU <-> FRD.
T_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
F_FRD_FLU = np.diag([1.0, -1.0, -1.0])

# ArduPilot quad X: (angle clockwise from the nose in degrees, yaw factor), servo order 1..4.
QUAD_X_MOTORS: tuple[tuple[float, float], ...] = ((45.0, 1.0), (-135.0, 1.0), (-45.0, -1.0), (135.0, -1.0))


@dataclass
class QuadJsonConfig:
    """Motor, drag and disturbance model of the JSON-mode quad (defaults: a 1.2 kg 450-class quad)."""

    arm_offset_m: float = 0.15            # motors at (+-a, +-a) in base_link, above the legs
    max_thrust_n: float = 7.0             # per motor at full command -> hover throttle 0.42 at 1.2 kg
    thrust_expo: float = 0.65             # MOT_THST_EXPO (ArduCopter default)
    pwm_min: float = 1000.0               # MOT_PWM_MIN
    pwm_max: float = 2000.0               # MOT_PWM_MAX
    spin_min: float = 0.15                # MOT_SPIN_MIN: no thrust at or below this output
    spin_max: float = 0.95                # MOT_SPIN_MAX: full thrust at this output
    motor_time_constant_s: float = 0.03   # first-order motor/propeller response
    yaw_torque_per_thrust_m: float = 0.01  # rotor drag torque / thrust
    drag_linear_n_per_mps: float = 0.10   # rotor/body linear drag
    drag_quadratic_n_per_mps2: float = 0.05  # body quadratic drag (terminal ~15 m/s at 45 deg)
    angular_damping_nm_per_rads: float = 0.002
    turbulence_min_thrust_fraction: float = 0.05  # rotor wash (and its turbulence) above this share of weight
    rangefinder_max_m: float = 20.0       # rng_1 range when nothing is hit

    def pwm_for_command(self, command: float) -> float:
        """PWM (us) that gives motor command `command` in [0, 1] (inverse of the command map)."""
        lo = self.pwm_min + self.spin_min * (self.pwm_max - self.pwm_min)
        hi = self.pwm_min + self.spin_max * (self.pwm_max - self.pwm_min)
        return lo + float(command) * (hi - lo)

    def command_for_thrust(self, thrust_n: float) -> float:
        """Motor command in [0, 1] giving `thrust_n` per motor (inverse thrust curve)."""
        f = min(max(float(thrust_n) / self.max_thrust_n, 0.0), 1.0)
        e = self.thrust_expo
        if e <= 1e-9:
            return f
        return (-(1.0 - e) + math.sqrt((1.0 - e) ** 2 + 4.0 * e * f)) / (2.0 * e)

    def hover_throttle(self, mass_kg: float, gravity: float = 9.81) -> float:
        """ArduCopter's MOT_THST_HOVER for this model: hover thrust as a fraction of full thrust."""
        return mass_kg * gravity / (4.0 * self.max_thrust_n)


def enu_to_ned(v) -> list[float]:
    """ENU vector -> NED list."""
    return [float(v[1]), float(v[0]), -float(v[2])]


def flu_to_frd(v) -> list[float]:
    """Body FLU vector -> body FRD list."""
    return [float(v[0]), -float(v[1]), -float(v[2])]


def rotation_ned_frd(r_enu_flu: np.ndarray) -> np.ndarray:
    """Rotation body FRD -> NED from the rotation body FLU -> ENU."""
    return T_NED_ENU @ r_enu_flu @ F_FRD_FLU


def matrix_to_quaternion_wxyz(r: np.ndarray) -> list[float]:
    """Rotation matrix -> unit quaternion [w, x, y, z] (ArduPilot's q1..q4 order), w >= 0."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2]) * 2.0
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2]) * 2.0
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1]) * 2.0
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    n = math.sqrt(sum(x * x for x in q))
    q = [x / n for x in q]
    return q if q[0] >= 0.0 else [-x for x in q]


def matrix_to_euler_321(r: np.ndarray) -> list[float]:
    """Rotation body -> earth -> [roll, pitch, yaw] (ZYX, ArduPilot's Matrix3::to_euler)."""
    return [math.atan2(r[2, 1], r[2, 2]), -math.asin(min(max(r[2, 0], -1.0), 1.0)), math.atan2(r[1, 0], r[0, 0])]


class QuadJsonModel:
    """Flies a LandingWorld's airframe from motor PWM and reports SITL's JSON sensor fields."""

    def __init__(self, world: LandingWorld, cfg: QuadJsonConfig | None = None, seed: int = 0):
        self.world = world
        self.cfg = cfg or QuadJsonConfig()
        c = self.cfg
        if not (c.pwm_min < c.pwm_max and 0.0 <= c.spin_min < c.spin_max <= 1.0):
            raise ValueError('need pwm_min < pwm_max and 0 <= spin_min < spin_max <= 1')
        if c.max_thrust_n <= 0 or not 0.0 <= c.thrust_expo <= 1.0 or c.motor_time_constant_s < 0:
            raise ValueError('need max_thrust_n > 0, 0 <= thrust_expo <= 1, motor_time_constant_s >= 0')
        a = c.arm_offset_m
        # motor positions in FLU: FRD (cos, sin) * r -> FLU (cos, -sin) * r, r = a sqrt(2)
        self.motor_positions = np.array(
            [[a * math.sqrt(2) * math.cos(math.radians(ang)), -a * math.sqrt(2) * math.sin(math.radians(ang)), 0.0]
             for ang, _ in QUAD_X_MOTORS])
        self.yaw_factors = np.array([yf for _, yf in QUAD_X_MOTORS])
        self._rng = np.random.default_rng(seed)
        self._cid = world._cid          # the world's own pybullet client (same package: shared internals)
        self._vid = world._vehicle
        self._mass = world.cfg.vehicle.mass_kg
        self._dt = 0.0
        self.command = np.zeros(4)      # lagged motor commands in [0, 1]
        self.thrust = np.zeros(4)       # N per motor
        self._noise = np.zeros(3)       # turbulence velocity (m/s, ENU)
        self._accel_flu = np.array([0.0, 0.0, world.cfg.gravity_mps2])
        self.reset()

    # ------------------------------------------------------------------ lifecycle
    def reset(self) -> None:
        """Motors stopped, turbulence cleared, IMU at rest (call after teleporting the airframe)."""
        self.command[:] = 0.0
        self.thrust[:] = 0.0
        self._noise[:] = 0.0
        self._accel_flu = self._static_specific_force()

    def _static_specific_force(self) -> np.ndarray:
        _, orn = p.getBasePositionAndOrientation(self._vid, physicsClientId=self._cid)
        r = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
        return r.T @ np.array([0.0, 0.0, self.world.cfg.gravity_mps2])

    def set_rate(self, rate_hz: float) -> None:
        """Physics step = 1 / rate_hz (SITL's frame_rate); also the judge's tick."""
        dt = 1.0 / float(rate_hz)
        if abs(dt - self._dt) > 1e-12:
            self._dt = dt
            p.setPhysicsEngineParameter(fixedTimeStep=dt, numSubSteps=0, physicsClientId=self._cid)
            # the landing judge counts its settle time in 1/physics_hz ticks
            self.world.cfg.physics_hz = int(round(rate_hz))
            self.world._tick_dt = dt

    @property
    def dt(self) -> float:
        """Current physics step (s)."""
        return self._dt

    # ------------------------------------------------------------------ physics
    def motor_commands(self, pwm) -> np.ndarray:
        """PWM (us) of servos 1..4 -> target motor commands in [0, 1] (ArduPilot SIM_Motor::pwm_to_command)."""
        c = self.cfg
        lo = c.pwm_min + c.spin_min * (c.pwm_max - c.pwm_min)
        hi = c.pwm_min + c.spin_max * (c.pwm_max - c.pwm_min)
        return np.clip((np.asarray(pwm[:4], dtype=float) - lo) / (hi - lo), 0.0, 1.0)

    def step(self, pwm) -> None:
        """Advance one physics step of `dt` with servo outputs `pwm` (us, at least 4 channels)."""
        if self._dt <= 0:
            raise RuntimeError('set_rate() before step()')
        c, dt, cid, vid, w = self.cfg, self._dt, self._cid, self._vid, self.world
        target = self.motor_commands(pwm)
        alpha = 1.0 if c.motor_time_constant_s <= 0 else 1.0 - math.exp(-dt / c.motor_time_constant_s)
        self.command += alpha * (target - self.command)
        e = c.thrust_expo
        self.thrust = c.max_thrust_n * ((1.0 - e) * self.command + e * self.command * self.command)

        pos, orn = p.getBasePositionAndOrientation(vid, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(vid, physicsClientId=cid)
        r = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
        v = np.array(lin)
        total = float(self.thrust.sum())
        # body-frame thrust and torques (FLU): thrust along +z at each motor, rotor drag torque about z
        f_body = np.array([0.0, 0.0, total])
        tau_body = np.cross(self.motor_positions, np.column_stack([np.zeros(4), np.zeros(4), self.thrust])).sum(axis=0)
        tau_body[2] += float(-(self.yaw_factors * self.thrust).sum()) * c.yaw_torque_per_thrust_m
        speed = float(np.linalg.norm(v))
        f_world = r @ f_body - (c.drag_linear_n_per_mps + c.drag_quadratic_n_per_mps2 * speed) * v
        f_world += self._turbulence_force(np.asarray(pos), total, dt)
        tau_world = r @ tau_body - c.angular_damping_nm_per_rads * np.array(ang)
        p.applyExternalForce(vid, -1, f_world.tolist(), pos, p.WORLD_FRAME, physicsClientId=cid)
        p.applyExternalTorque(vid, -1, tau_world.tolist(), p.WORLD_FRAME, physicsClientId=cid)
        p.stepSimulation(physicsClientId=cid)
        w.time += dt
        w.episode_time += dt
        lin_after, _ = p.getBaseVelocity(vid, physicsClientId=cid)
        # IMU specific force = a - g, from the velocity change over the step (as ArduPilot's
        # pybullet example does), so contact forces are felt too; g = (0, 0, -9.81) in ENU
        a = (np.array(lin_after) - v) / dt
        a[2] += w.cfg.gravity_mps2
        _, orn_after = p.getBasePositionAndOrientation(vid, physicsClientId=cid)
        r_after = np.array(p.getMatrixFromQuaternion(orn_after)).reshape(3, 3)
        self._accel_flu = r_after.T @ a
        w._judge(lin)                   # the same landing judge as velocity mode

    def _turbulence_force(self, pos: np.ndarray, total_thrust: float, dt: float) -> np.ndarray:
        t = self.world.cfg.turbulence
        weight = self._mass * self.world.cfg.gravity_mps2
        if not t.enabled or total_thrust < self.cfg.turbulence_min_thrust_fraction * weight:
            self._noise[:] = 0.0
            return np.zeros(3)
        clearance = self.world._height_above_surface(pos) - self.world.cfg.vehicle.leg_length_m
        sigma = turbulence_sigma(clearance, t)
        a = math.exp(-dt / t.correlation_s)
        self._noise = a * self._noise + math.sqrt(1 - a * a) * sigma * self._rng.standard_normal(3)
        k = self.world.cfg.controller
        return self._mass * np.array([k.kp_xy, k.kp_xy, k.kp_z]) * self._noise

    # ------------------------------------------------------------------ sensors
    def rangefinder(self, pos: np.ndarray, r: np.ndarray) -> float:
        """Distance (m) from base_link along body -z to the first surface (rng_1, a downward rangefinder)."""
        down = -r[:, 2]
        start_off = self.world.cfg.vehicle.body_half_extents_m[2] + 0.002   # just below the body box
        start = pos + down * start_off
        end = pos + down * self.cfg.rangefinder_max_m
        hit = p.rayTest(start.tolist(), end.tolist(), physicsClientId=self._cid)[0]
        if hit[0] < 0:
            return self.cfg.rangefinder_max_m
        return start_off + float(hit[2]) * (self.cfg.rangefinder_max_m - start_off)

    def sensors(self, timestamp: float, origin_enu=(0.0, 0.0, 0.0), rangefinder: bool = True) -> dict:
        """SITL JSON input fields (timestamp, imu, position, velocity, attitude, quaternion[, rng_1])."""
        cid, vid = self._cid, self._vid
        pos, orn = p.getBasePositionAndOrientation(vid, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(vid, physicsClientId=cid)
        r = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
        pos = np.array(pos)
        gyro_flu = r.T @ np.array(ang)
        r_nb = rotation_ned_frd(r)
        out = {
            'timestamp': float(timestamp),
            'imu': {'gyro': flu_to_frd(gyro_flu), 'accel_body': flu_to_frd(self._accel_flu)},
            'position': enu_to_ned(pos - np.asarray(origin_enu, dtype=float)),
            'velocity': enu_to_ned(lin),
            'attitude': matrix_to_euler_321(r_nb),
            'quaternion': matrix_to_quaternion_wxyz(r_nb),
        }
        if rangefinder:
            out['rng_1'] = self.rangefinder(pos, r)
        return out


__all__ = ['QuadJsonConfig', 'QuadJsonModel', 'QUAD_X_MOTORS', 'enu_to_ned', 'flu_to_frd', 'rotation_ned_frd',
           'matrix_to_quaternion_wxyz', 'matrix_to_euler_321']
