"""ArduCopter's GUIDED velocity response as a plant of the fast simulator (`flight_controller: arducopter`).

Written from ArduCopter's documented behaviour (the position-controller and land-detector pages of the
ArduPilot wiki, the parameter reference) and fitted to logs of real ArduCopter SITL flying our airframe
(``test/fixtures/guided``); it is a behavioural model, not a port of ArduPilot's code. Per axis group
(horizontal as one 2-D vector, vertical on its own):

1. **Setpoint delay.** A velocity setpoint reaches the controller ``setpoint_delay_s`` after it was sent.
2. **Shaping.** The controller's target velocity moves towards the setpoint along an acceleration- and
   jerk-limited trajectory: a square-root controller on the velocity error (gain jerk/accel, so the demand
   decelerates smoothly into the setpoint) gives the wanted acceleration, limited to ``accel_*``; the
   target acceleration moves towards it at no more than ``jerk_*``.
3. **Path hold.** The target position is the integral of the target velocity; a vehicle that lags is
   pulled back onto that path (square-root controller with gain ``pos_*_p``), so it catches up after a
   lag (``path_hold: false`` resets the target position to the vehicle's each tick instead).
4. **Tracking.** The demanded acceleration = target acceleration + ``vel_*_p`` x (target velocity + path
   correction - velocity), plus horizontally the integral of that error (``vel_xy_i``), horizontally
   limited by the lean angle (g tan ``lean_max_deg``); the vehicle's acceleration follows it with a
   first-order lag (``attitude_tc_s`` horizontally, the time the airframe takes to lean; ``throttle_tc_s``
   vertically). The airframe leans by the angle its acceleration needs, so the camera tilts with it (the
   encoder's levelling undoes it).
5. **Land detector.** After first contact with a descent demanded, a landing is declared once, for
   ``land_detect_s`` without a break: the demand is still a descent with no sideways setpoint (at most
   ``land_setpoint_xy_max_mps``), the lean it asks for is below ``land_lean_max_deg``, the vehicle's
   acceleration is below ``land_accel_max_mps2`` and its vertical speed below ``land_vz_max_mps``. A
   sideways command at contact keeps it flying (it slides on the pad top). Once landed the motors idle
   and setpoints are ignored until ``takeoff()``.

Pure numpy, no pybullet: `GuidedVelocityModel.tick` turns (setpoint, state) into a world acceleration;
`LandingWorld` applies it as a force on the airframe, and `simulate` integrates it as a point mass
(for fitting and for the fixture tests).
"""
from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from assist_common.settings import RULE_KEY, check_named, setting

FLIGHT_CONTROLLERS = ('ideal', 'arducopter')
LAND_ACCEL_FILTER_HZ = 1.0     # the land detector's acceleration is low-passed at this cut-off


@dataclass
class ArduCopterConfig:
    """GUIDED velocity-control model; defaults are ArduCopter's parameters, lags fitted to SITL logs."""

    # The shaping limits are ArduCopter's parameters; the loop gains and lags are effective values fitted with
    # fit_guided to real SITL flying our airframe (test/fixtures/guided; the model lumps ArduCopter's
    # acceleration, attitude and rate loops into them, so they differ from the PSC_* defaults they stand for).
    setpoint_delay_s: float = setting(0.048, ge=0.0, le=0.5)   # fitted: MAVLink + scheduler latency
    accel_xy_mps2: float = setting(2.51, ge=0.2, le=10.0)      # WPNAV_ACCEL 2.5 (fitted 2.51)
    jerk_xy_mps3: float = setting(5.25, ge=0.5, le=50.0)       # PSC_JERK_XY 5 (fitted 5.25)
    accel_z_mps2: float = setting(1.0, ge=0.2, le=5.0)         # WPNAV_ACCEL_Z
    jerk_z_mps3: float = setting(7.38, ge=0.5, le=50.0)        # PSC_JERK_Z 5 (fitted 7.38 with the throttle lag)
    pos_xy_p: float = setting(1.0, ge=0.0, le=5.0)             # PSC_POSXY_P (1/s)
    vel_xy_p: float = setting(1.84, ge=0.1, le=10.0)           # PSC_VELXY_P 2 (fitted 1.84, 1/s)
    vel_xy_i: float = setting(1.0, ge=0.0, le=10.0)            # PSC_VELXY_I (1/s^2): persistent errors wind it up
    vel_xy_imax_mps2: float = setting(10.0, ge=0.0, le=20.0)   # PSC_VELXY_IMAX (1000 cm/s^2)
    pos_z_p: float = setting(1.0, ge=0.0, le=5.0)              # PSC_POSZ_P (1/s)
    vel_z_p: float = setting(1.81, ge=0.1, le=20.0)            # fitted (PSC_VELZ_P 5 with the acceleration loop)
    path_hold: bool = setting(True)                            # GUID_OPTIONS bit 4 clear: the path is held
    lean_max_deg: float = setting(30.0, ge=5.0, le=60.0)       # ANGLE_MAX: horizontal accel <= g tan(this)
    attitude_tc_s: float = setting(0.087, ge=0.01, le=1.0)     # fitted: lean (horizontal accel) follows its demand
    throttle_tc_s: float = setting(0.119, ge=0.01, le=1.0)     # fitted: vertical accel follows its demand
    # contact to the landing being declared when all is quiet: ArduCopter's 1 s trigger after its throttle has
    # wound down to the lower limit (1.62-1.67 s on SITL at 0.5 m/s: fixtures/guided/touchdown.csv)
    land_detect_s: float = setting(1.37, ge=0.1, le=5.0)
    land_accel_max_mps2: float = setting(1.0, ge=0.1, le=5.0)  # LAND_DETECTOR_ACCEL_MAX
    land_vz_max_mps: float = setting(1.0, ge=0.1, le=3.0)      # vertical speed below this
    land_lean_max_deg: float = setting(15.0, ge=1.0, le=45.0)  # a larger lean request blocks the detector
    # a sideways setpoint faster than this at contact blocks it too (SITL: 0.5 m/s held after contact was
    # never declared landed; released at contact, declared as a vertical touchdown)
    land_setpoint_xy_max_mps: float = setting(0.1, ge=0.0, le=2.0)
    idle_thrust_fraction: float = setting(0.05, ge=0.0, le=0.5)  # of hover thrust once landed (ground idle)
    # on a surface with a descent demanded the throttle winds down to ground idle over this (the detector wants
    # it at its lower limit; with it the airframe stops pushing sideways: SITL stopped within 3 cm of contact)
    ground_spool_down_s: float = setting(0.6, ge=0.05, le=5.0)

    def validate(self) -> None:
        """ValueError naming the first setting outside its range (`arducopter.<name> ...`)."""
        check_named(self, 'arducopter')


# the fields `randomised` varies (the dynamics; thresholds of the land detector stay ArduCopter's)
RANDOMISED_FIELDS = ('setpoint_delay_s', 'accel_xy_mps2', 'jerk_xy_mps3', 'accel_z_mps2', 'jerk_z_mps3',
                     'pos_xy_p', 'vel_xy_p', 'pos_z_p', 'vel_z_p', 'attitude_tc_s', 'throttle_tc_s')


def randomised(cfg: ArduCopterConfig, rng: np.random.Generator, spread: float = 0.3) -> ArduCopterConfig:
    """A copy with each dynamic setting scaled by a uniform factor in [1 - spread, 1 + spread] (clipped to range)."""
    if not 0.0 <= spread < 1.0:
        raise ValueError(f'spread must be in [0, 1), got {spread}')
    rules = {f.name: f.metadata[RULE_KEY] for f in dataclasses.fields(ArduCopterConfig)}
    changes = {}
    for name in RANDOMISED_FIELDS:
        r = rules[name]
        changes[name] = float(np.clip(getattr(cfg, name) * rng.uniform(1 - spread, 1 + spread), r.ge, r.le))
    return dataclasses.replace(cfg, **changes)


def sqrt_controller(error: float, gain: float, limit: float, dt: float) -> float:
    """Square-root controller: linear (gain x error) near zero, sqrt(2 limit |error|)-shaped beyond,
    never overshooting the error within one step of dt."""
    if gain <= 0.0:
        out = math.copysign(math.sqrt(2.0 * limit * abs(error)), error) if limit > 0.0 else 0.0
    elif limit <= 0.0:
        out = gain * error
    else:
        linear = limit / (gain * gain)
        if abs(error) > linear:
            out = math.copysign(math.sqrt(2.0 * limit * (abs(error) - 0.5 * linear)), error)
        else:
            out = gain * error
    if dt > 0.0 and abs(out) > abs(error) / dt:
        out = error / dt
    return out


def _sqrt2(ex: float, ey: float, gain: float, limit: float, dt: float) -> tuple[float, float]:
    """`sqrt_controller` on the length of a 2-D vector, along its direction."""
    n = math.hypot(ex, ey)
    if n < 1e-12:
        return 0.0, 0.0
    k = sqrt_controller(n, gain, limit, dt) / n
    return ex * k, ey * k


def _limit2(x: float, y: float, limit: float) -> tuple[float, float]:
    n = math.hypot(x, y)
    if n > limit > 0.0:
        return x * limit / n, y * limit / n
    return x, y


class _Shaper:
    """Acceleration- and jerk-limited target velocity (and its integrated path) for one axis group.

    Horizontal: a 2-D vector (x, y); vertical: one axis (y unused). Plain floats: it runs at the physics rate."""

    def __init__(self, planar: bool):
        self.planar = planar
        self.px = self.py = self.vx = self.vy = self.ax = self.ay = 0.0

    def reset(self, pos: tuple[float, float], vel: tuple[float, float]) -> None:
        self.px, self.py = pos
        self.vx, self.vy = vel
        self.ax = self.ay = 0.0

    def update(self, sx: float, sy: float, accel: float, jerk: float, dt: float) -> None:
        if self.planar:
            wx, wy = _sqrt2(sx - self.vx, sy - self.vy, jerk / accel, jerk, dt)
            wx, wy = _limit2(wx, wy, accel)
            dx, dy = _limit2(wx - self.ax, wy - self.ay, jerk * dt)
        else:
            w = min(max(sqrt_controller(sx - self.vx, jerk / accel, jerk, dt), -accel), accel)
            dx, dy = min(max(w - self.ax, -jerk * dt), jerk * dt), 0.0
        self.ax += dx
        self.ay += dy
        self.px += self.vx * dt + 0.5 * self.ax * dt * dt
        self.py += self.vy * dt + 0.5 * self.ay * dt * dt
        self.vx += self.ax * dt
        self.vy += self.ay * dt


class GuidedVelocityModel:
    """ArduCopter GUIDED velocity control (module docstring): setpoint + vehicle state -> acceleration."""

    def __init__(self, cfg: ArduCopterConfig | None = None, gravity_mps2: float = 9.81):
        self.cfg = cfg or ArduCopterConfig()
        self.cfg.validate()
        self.g = float(gravity_mps2)
        self._xy = _Shaper(planar=True)
        self._z = _Shaper(planar=False)
        self._queue: deque[tuple[float, tuple[float, float, float]]] = deque()
        self.reset((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))

    def reset(self, position, velocity, landed: bool = False) -> None:
        """Start from this state (hovering with the setpoint at the current velocity, or landed)."""
        px, py, pz = (float(v) for v in position)
        vx, vy, vz = (float(v) for v in velocity)
        self._xy.reset((px, py), (vx, vy))
        self._ix = self._iy = 0.0              # the horizontal velocity loop's integrator (m/s^2)
        self._ground_s = 0.0                   # time on a surface with a descent demanded
        self._z.reset((pz, 0.0), (vz, 0.0))
        self._queue.clear()
        self._sp = (vx, vy, vz)
        self._acc = (0.0, 0.0, 0.0)            # the vehicle's acceleration from thrust (world, without gravity)
        self._demand = (0.0, 0.0, 0.0)         # the demanded acceleration before the lags
        self.time = 0.0
        self.landed = bool(landed)
        self.touched = bool(landed)            # contact with a descent demanded since the last take-off
        self._land_timer = 0.0
        self.landed_at: float | None = None
        self._last_vel: tuple[float, float, float] | None = None
        self._acc_filtered = [0.0, 0.0, 0.0]

    def takeoff(self, position, velocity) -> None:
        """Leave the landed state (ArduCopter: a take-off command); the path starts where the vehicle is."""
        self.reset(position, velocity, landed=False)

    def command(self, setpoint) -> None:
        """A new velocity setpoint (world ENU, m/s), used `setpoint_delay_s` from now."""
        sp = tuple(float(v) for v in np.asarray(setpoint, dtype=float).reshape(3))
        if not all(math.isfinite(v) for v in sp):
            raise ValueError(f'setpoint must be 3 finite numbers, got {list(sp)}')
        self._queue.append((self.time + self.cfg.setpoint_delay_s, sp))

    @property
    def setpoint(self) -> np.ndarray:
        """The setpoint the controller is using now (after the delay)."""
        return np.array(self._sp)

    @property
    def accel(self) -> np.ndarray:
        """The vehicle's acceleration from thrust (world, without gravity)."""
        return np.array(self._acc)

    @property
    def demand(self) -> np.ndarray:
        """The demanded acceleration, before the attitude and throttle lags."""
        return np.array(self._demand)

    @property
    def lean_rad(self) -> float:
        """Lean angle the current horizontal acceleration needs."""
        ax, ay, az = self._acc
        return math.atan2(math.hypot(ax, ay), self.g + az)

    def thrust_direction(self) -> tuple[float, float, float]:
        """Unit vector of the thrust (world): the airframe's body z axis."""
        ax, ay, az = self._acc
        z = self.g + az
        n = math.sqrt(ax * ax + ay * ay + z * z)
        return (ax / n, ay / n, z / n) if n > 1e-9 else (0.0, 0.0, 1.0)

    def tick(self, position, velocity, dt: float, touching: bool = False,
             disturbance=None) -> tuple[float, float, float]:
        """Advance dt; return the world acceleration the thrust gives (without gravity; idle when landed).

        `touching`: the airframe is in contact with something (the land detector's evidence, as
        ArduCopter's motors-at-lower-limit is); `disturbance`: a velocity added to the tracked target
        (the world's turbulence)."""
        c = self.cfg
        self.time += dt
        q = self._queue
        while q and q[0][0] <= self.time + 1e-12:
            self._sp = q.popleft()[1]
        if self.landed:
            self._acc = self._demand = (0.0, 0.0, (c.idle_thrust_fraction - 1.0) * self.g)
            return self._acc
        px, py, pz = position[0], position[1], position[2]
        vx, vy, vz = velocity[0], velocity[1], velocity[2]
        sx, sy, sz = self._sp
        xy, zz = self._xy, self._z
        xy.update(sx, sy, c.accel_xy_mps2, c.jerk_xy_mps3, dt)
        zz.update(sz, 0.0, c.accel_z_mps2, c.jerk_z_mps3, dt)
        if not c.path_hold:
            xy.px, xy.py, zz.px = px, py, pz
        nx, ny, nz = (0.0, 0.0, 0.0) if disturbance is None else (disturbance[0], disturbance[1], disturbance[2])
        cx, cy = _sqrt2(xy.px - px, xy.py - py, c.pos_xy_p, c.accel_xy_mps2, dt)
        cz = sqrt_controller(zz.px - pz, c.pos_z_p, c.accel_z_mps2, dt)
        ex, ey = xy.vx + cx + nx - vx, xy.vy + cy + ny - vy
        self._ix, self._iy = _limit2(self._ix + c.vel_xy_i * ex * dt, self._iy + c.vel_xy_i * ey * dt,
                                     c.vel_xy_imax_mps2)
        dx = xy.ax + c.vel_xy_p * ex + self._ix
        dy = xy.ay + c.vel_xy_p * ey + self._iy
        dx, dy = _limit2(dx, dy, self.g * math.tan(math.radians(c.lean_max_deg)))
        dz = max(zz.ax + c.vel_z_p * (zz.vx + cz + nz - vz), -self.g)     # no negative thrust
        self._ground_s = self._ground_s + dt if touching and sz < 0.0 else 0.0
        if self._ground_s > 0.0:                  # blocked descent: the throttle winds down to ground idle
            w = min(1.0, self._ground_s / c.ground_spool_down_s)
            dz = (1.0 - w) * dz + w * (c.idle_thrust_fraction - 1.0) * self.g
        self._demand = (dx, dy, dz)
        kxy = 1.0 - math.exp(-dt / c.attitude_tc_s)
        kz = 1.0 - math.exp(-dt / c.throttle_tc_s)
        ax, ay, az = self._acc
        az = az + kz * (dz - az)
        # the horizontal force is the thrust leaned over: no more than (g + a_z) tan(lean_max), so a vehicle
        # whose thrust winds down on the ground stops pushing sideways (SITL: it stops within 3 cm of contact)
        ax, ay = _limit2(ax + kxy * (dx - ax), ay + kxy * (dy - ay),
                         max(self.g + az, 0.0) * math.tan(math.radians(c.lean_max_deg)))
        self._acc = (ax, ay, az)
        self._detect_landing(vx, vy, vz, touching, dt)
        return self._acc

    def _detect_landing(self, vx: float, vy: float, vz: float, touching: bool, dt: float) -> None:
        c = self.cfg
        f = self._acc_filtered
        if self._last_vel is not None and dt > 0.0:     # measured acceleration, low-passed at 1 Hz
            k = 1.0 - math.exp(-dt * 2.0 * math.pi * LAND_ACCEL_FILTER_HZ)
            lx, ly, lz = self._last_vel
            f[0] += k * ((vx - lx) / dt - f[0])
            f[1] += k * ((vy - ly) / dt - f[1])
            f[2] += k * ((vz - lz) / dt - f[2])
        self._last_vel = (vx, vy, vz)
        descending = self._sp[2] < 0.0
        self.touched = self.touched or (touching and descending)
        if not self.touched:
            return
        lean_request = math.atan2(math.hypot(self._demand[0], self._demand[1]), self.g)
        quiet = (descending and touching and lean_request < math.radians(c.land_lean_max_deg)
                 and math.hypot(self._sp[0], self._sp[1]) <= c.land_setpoint_xy_max_mps
                 and abs(vz) < c.land_vz_max_mps
                 and math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]) < c.land_accel_max_mps2)
        self._land_timer = self._land_timer + dt if quiet else 0.0
        if self._land_timer >= c.land_detect_s:
            self.landed = True
            self.landed_at = self.time


def simulate(cfg: ArduCopterConfig, t: np.ndarray, setpoints: np.ndarray, velocity0=None,
             position0=None, substeps: int = 8, command_times=None) -> tuple[np.ndarray, np.ndarray]:
    """Point-mass response to a setpoint sequence: velocity and position (N, 3) at the times `t`.

    `setpoints[k]` is sent at `command_times[k]` (default: `t`, one setpoint per sample, held until the
    next); the model is stepped `substeps` times per sample interval. Used to fit the model to SITL logs
    and to test it against them."""
    t = np.asarray(t, dtype=float)
    sp = np.asarray(setpoints, dtype=float).reshape(-1, 3)
    sent = t if command_times is None else np.asarray(command_times, dtype=float)
    if len(t) < 2 or len(sent) != len(sp):
        raise ValueError('need >= 2 output times and one send time per setpoint')
    model = GuidedVelocityModel(cfg)
    vel = np.zeros(3) if velocity0 is None else np.asarray(velocity0, dtype=float).copy()
    pos = np.zeros(3) if position0 is None else np.asarray(position0, dtype=float).copy()
    model.reset(pos, vel)
    out_v = np.zeros((len(t), 3))
    out_p = np.zeros((len(t), 3))
    out_v[0], out_p[0] = vel, pos
    k, now = 0, t[0]
    for i in range(1, len(t)):
        h = (t[i] - t[i - 1]) / substeps
        for _ in range(substeps):
            while k < len(sent) and sent[k] <= now + 1e-9:
                model.command(sp[k])
                k += 1
            a = np.array(model.tick(pos, vel, h))
            pos = pos + vel * h + 0.5 * a * h * h
            vel = vel + a * h
            now += h
        out_v[i], out_p[i] = vel, pos
    return out_v, out_p
