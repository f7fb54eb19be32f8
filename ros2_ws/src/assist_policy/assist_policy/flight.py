"""When a flight begins and ends: from the vehicle's own landed state where it reports one, else from odometry.

The assistant's memories (action history, pad and wall maps, landing spots, override and damper state)
belong to one flight (ARCHITECTURE.md, "Flights and the assistant's memory"). One ``FlightMonitor`` class
decides, for policy_node's core and for the training/evaluation env alike; each call that sees a flight
boundary returns its reason (``REASONS``) and leaves the why in ``last_detail``.

**The vehicle's report wins.** ``vehicle_state`` takes MAV_LANDED_STATE as the bridge publishes it on
/uav/landed_state (0 undefined, 1 on ground, 2 in air, 3 take-off, 4 landing). While a report is known (not
UNDEFINED, and no older than ``landed_state_timeout_s`` on the clock it was given with), ON_GROUND is a landing
(``vehicle_landed``), TAKEOFF or IN_AIR after it a take-off (``vehicle_takeoff``), and the odometry landing and
take-off rules below wait. The first report only says where the flight stands (no boundary). A report that goes
stale hands the decision back to odometry: a publisher that sends every report it receives keeps it current (and
one that falls silent, a lost link, goes stale); with one that sends only changes, the changes still end and begin
flights, and between them the odometry rules run too (a boundary is never counted twice: a report that finds the
flight where odometry already put it is none). The env (simulation) has no such report: odometry rules only.

**Odometry rules** (``update``, once per odometry sample; times are the samples' stamps):

* ``odom_jump``: the position moved farther between two samples than the twist's speed explains, by more than
  ``jump_m`` (a simulator reset, a teleport, an EKF reset or a new odometry origin). Memories kept in the odom
  frame mean nothing across it. It applies whatever the vehicle reports.
* ``landed`` needs all of, over the last ``rest_s`` (the rest window):

  1. *at rest*, judged from displacement, not from the twist (EKF velocity noise of several cm/s per sample
     would read as motion): a straight line fitted to the positions moves slower than ``rest_speed_mps``, and
     every position lies within ``rest_radius_m`` of their mean;
  2. the command flown descended at ``rest_descent_mps`` or more throughout (a hover, or a descent the floor
     guard holds, is no landing);
  3. *evidence of contact*: the vehicle came down into the rest (it was ``touchdown_descent_m`` higher at some
     time in the ``touchdown_lookback_s`` before the window), or it rests within ``ground_altitude_m`` of the
     floor (odom z = 0, where an autopilot's origin lies), or within ``contact_height_m`` of a surface the
     camera saw below it (``observe_surface``, kept ``surface_memory_s`` within ``surface_radius_m``);
  4. and *not well above a known surface*: where the camera saw the surface below, resting more than
     ``contact_height_m`` above the highest one is not a landing, whatever else says so. A vehicle hovering
     while the command descends, or an odometry source frozen with fresh stamps, is still in the air: the camera
     keeps seeing the floor far below. (Without a camera and without a landed state a frozen source that froze
     during a descent cannot be told from a touchdown.)
* ``takeoff``, after a landing: the altitude (the mean over ``takeoff_window_s``) more than ``takeoff_climb_m``
  above the rest altitude, and climbing (a line fitted over that window rises at ``takeoff_speed_mps`` or more)
  or held that high for ``takeoff_hold_s``. While landed, the rest altitude follows the windows at rest, so a
  slow EKF drift is no climb, nor is a 0.3 m wander.
* start (and after a jump): the first full rest window at rest below ``ground_altitude_m`` finds the vehicle
  landed (an autopilot starts on the ground), anything else flying; no boundary.
* a clock that steps back (a stamp older than the last) counts as one sample period: the times held are moved
  back by the step and the windows go on from there, so a landing is seen when it would have been, not after the
  clock has made up the step.

``~/reset`` on policy_node (``reason`` 'service', at most one per ``reset_min_interval_s``: ``request_reset``)
and the env's ``reset`` (a new episode: 'episode') are the explicit boundaries. ``/sim/goal`` is not one: the
latent and end-to-end assistants never read it.
"""
from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from assist_common.settings import check_named, setting
from .settings import node_param

REASONS = ('odom_jump', 'landed', 'takeoff', 'vehicle_landed', 'vehicle_takeoff', 'service', 'episode')
_EPS = 1e-6          # time comparisons (s)
_MIN_SAMPLES = 3     # odometry samples a window needs to be judged
CENTRE_FRACTION = 0.25      # surface_clearance reads the central patch of the depth image (this share of a side)
MIN_VALID_FRACTION = 0.25   # ... when at least this share of it is valid


class LandedState(enum.IntEnum):
    """MAV_LANDED_STATE (MAVLink EXTENDED_SYS_STATE.landed_state), as /uav/landed_state carries it."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


class Phase(enum.Enum):
    """Where the flight stands as the monitor sees it."""

    UNKNOWN = 'unknown'
    FLYING = 'flying'
    LANDED = 'landed'


@dataclass
class FlightConfig:
    """Thresholds of the flight boundaries (policy_node flight_* parameters; the rest are fixed here)."""

    # False: only the explicit boundaries (~/reset, a new env episode)
    enabled: bool = node_param(True, 'flight_boundaries', 'Forget the flight (action history, pad and wall maps, '
                               'landing spots, override and damper state) at an odometry jump, a landing and a '
                               'take-off (assist_policy.flight); false: only at ~/reset.')
    # odometry moving this much farther than its speed explains: a jump (m)
    jump_m: float = node_param(1.0, 'flight_jump_m', 'Odometry moving this much farther between two samples than '
                               'its speed explains is a jump (reset, teleport, EKF reset): a new flight (m).',
                               min=0.0, max=100.0, min_exclusive=True)
    # a line fitted to the positions over rest_s slower than this counts as at rest
    rest_speed_mps: float = node_param(0.05, 'flight_rest_speed_mps', 'At rest: a line fitted to the odometry '
                                       'positions over flight_rest_s moves slower than this (m/s; displacement, not '
                                       'the noisy twist).', min=0.0, max=1.0, min_exclusive=True)
    # ... for this long, while the command flown descends, with evidence of contact: landed
    rest_s: float = node_param(1.0, 'flight_rest_s', 'At rest this long while /cmd_vel descends at '
                               'flight_rest_descent_mps or more, after coming down or near a surface below: '
                               'landed, the flight ends (s).', min=0.0, max=60.0, min_exclusive=True)
    # the command's descent that makes a rest a landing (m/s)
    rest_descent_mps: float = node_param(0.1, 'flight_rest_descent_mps', 'Descent of the command flown that makes a '
                                         'rest a landing (m/s).', min=0.0, max=5.0, min_exclusive=True)
    # rising this far above the resting altitude, climbing: a take-off (m)
    takeoff_climb_m: float = node_param(0.5, 'flight_takeoff_climb_m', 'After a landing, rising this far above it '
                                        'while climbing (or staying that high for 2 s) is a take-off: a new flight '
                                        '(m).', min=0.0, max=10.0, min_exclusive=True)
    # resting no higher than this over a surface the camera saw below: contact; higher: not landed
    contact_height_m: float = node_param(0.4, 'flight_contact_height_m', 'Odometry landing: base_link resting more '
                                         'than this above the highest surface the camera saw below it is still in '
                                         'the air (a hover, a frozen odometry source); within it counts as contact '
                                         '(m; above the legs\' length).', min=0.0, max=10.0, min_exclusive=True)
    # a /uav/landed_state report older than this no longer counts: the odometry rules decide again
    landed_state_timeout_s: float = node_param(2.0, 'flight_landed_state_timeout_s', 'A /uav/landed_state report '
                                               '(the vehicle\'s own, wins over the odometry rules) counts this long '
                                               'after it arrived (s); older or UNDEFINED: the odometry rules decide.',
                                               min=0.0, max=60.0, min_exclusive=True)
    # ~/reset answers success=false to a call sooner than this after the last one it honoured (0: no limit)
    reset_min_interval_s: float = node_param(1.0, 'flight_reset_min_interval_s', '~/reset honours at most one call '
                                             'per this many seconds (node clock); sooner calls are answered '
                                             'success=false and counted (flight_reset_refused); 0: no limit.',
                                             min=0.0, max=3600.0)
    rest_radius_m: float = setting(0.1, gt=0)  # at rest: every position of the window this close to their mean
    touchdown_descent_m: float = setting(0.15, gt=0)  # came down into the rest: this much higher shortly before it...
    touchdown_lookback_s: float = setting(3.0, gt=0)  # ... within this long before the rest window
    surface_memory_s: float = setting(10.0, gt=0)  # surfaces the camera saw count this long...
    surface_radius_m: float = setting(0.5, gt=0)  # ... within this horizontal distance
    takeoff_window_s: float = setting(0.5, gt=0)  # take-off: altitude (mean) and climb speed (fitted) over this window
    takeoff_speed_mps: float = setting(0.1, gt=0)  # climbing at least this fast...
    takeoff_hold_s: float = setting(2.0, gt=0)  # ... or held above takeoff_climb_m this long
    ground_altitude_m: float = setting(0.3)  # at rest below this altitude (odom z): on the floor

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self, type(self).__name__)


def surface_clearance(depth: np.ndarray, camera_offset_m: float) -> float | None:
    """base_link's height over the surface straight below from a downward depth image (metres, holes 0 or NaN):
    the median valid depth of its central patch (CENTRE_FRACTION of each side) plus the camera's offset below
    base_link; None when under MIN_VALID_FRACTION of that patch is valid (a camera too near to see: no evidence)."""
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2 or d.size == 0:
        return None
    h, w = d.shape
    ph, pw = max(1, round(h * CENTRE_FRACTION)), max(1, round(w * CENTRE_FRACTION))
    patch = d[(h - ph) // 2:(h - ph) // 2 + ph, (w - pw) // 2:(w - pw) // 2 + pw]
    valid = patch[np.isfinite(patch) & (patch > 0)]
    if valid.size < MIN_VALID_FRACTION * patch.size:
        return None
    return float(np.median(valid)) + float(camera_offset_m)


def _fit(ts: np.ndarray, ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean, velocity) of a least-squares line through positions `ps` (N x k) at times `ts`."""
    mean = ps.mean(axis=0)
    tc = ts - ts.mean()
    denom = float(tc @ tc)
    slope = (tc @ (ps - mean)) / denom if denom > 0 else np.zeros(ps.shape[1])
    return mean, slope


class FlightMonitor:
    """Decides flight boundaries (module docstring); ``update`` / ``vehicle_state`` return a reason or None."""

    def __init__(self, cfg: FlightConfig | None = None):
        self.cfg = cfg or FlightConfig()
        self._vehicle: tuple[float, int] | None = None   # (clock time, MAV_LANDED_STATE) of the latest report
        self._last_service: float | None = None         # clock time of the latest ~/reset honoured
        self.resets_refused = 0                          # ~/reset calls refused by the rate limit
        self.clock_steps = 0                             # odometry stamps that stepped back (times re-dated)
        self.last_detail = ''                            # why the latest boundary
        self.reset()

    def reset(self) -> None:
        """Start watching afresh (after an explicit boundary); the vehicle's latest report still says where it is."""
        self._samples: deque[tuple[float, float, float, float]] = deque()   # (t, x, y, z) odometry, recent
        self._surfaces: deque[tuple[float, float, float, float]] = deque()  # (t, x, y, surface z) seen below
        self._last_speed = 0.0
        self._descend_since: float | None = None    # since when the command flown descends
        self._above_since: float | None = None      # since when the altitude is take-off high
        self._rest_z: float | None = None           # resting altitude while landed
        self.phase = self._reported_phase() or Phase.UNKNOWN

    # ------------------------------------------------------------------ state
    @property
    def landed(self) -> bool:
        """Whether the vehicle is on a surface (between a landing and the next take-off)."""
        return self.phase is Phase.LANDED

    @property
    def vehicle_report(self) -> int | None:
        """The latest MAV_LANDED_STATE the vehicle reported (None: none yet)."""
        return None if self._vehicle is None else self._vehicle[1]

    def vehicle_known(self, now: float) -> bool:
        """Whether the vehicle's report decides at clock time `now` (known state, not stale)."""
        v = self._vehicle
        if v is None or v[1] == LandedState.UNDEFINED:
            return False
        if now < v[0]:                                  # the clock stepped back: the report is dated anew
            self._vehicle = (float(now), v[1])
            return True
        return now - v[0] <= self.cfg.landed_state_timeout_s

    def _reported_phase(self) -> Phase | None:
        v = self._vehicle
        if v is None or v[1] == LandedState.UNDEFINED:
            return None
        return Phase.LANDED if v[1] == LandedState.ON_GROUND else Phase.FLYING

    def _boundary(self, reason: str, detail: str) -> str:
        self.last_detail = detail
        return reason

    # ------------------------------------------------------------------ inputs
    def vehicle_state(self, t: float, state: int) -> str | None:
        """The vehicle's MAV_LANDED_STATE at clock time `t`; the boundary it makes, or None (ValueError if not 0-4)."""
        try:
            state = LandedState(int(state))
        except (TypeError, ValueError):
            raise ValueError(f'landed state {state!r} is not a MAV_LANDED_STATE (0-4)') from None
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f'landed state time {t!r} is not finite')
        self._vehicle = (t, int(state))
        if not self.cfg.enabled or state in (LandedState.UNDEFINED, LandedState.LANDING):
            if state == LandedState.LANDING and self.phase is Phase.UNKNOWN:
                self.phase = Phase.FLYING
            return None
        previous = self.phase
        if state == LandedState.ON_GROUND:
            if previous is Phase.LANDED:
                return None
            self.phase = Phase.LANDED
            self._rest_z = self._samples[-1][3] if self._samples else None
            self._above_since = None
            if previous is Phase.UNKNOWN:
                return None
            return self._boundary('vehicle_landed', 'the vehicle reports ON_GROUND (/uav/landed_state)')
        if previous is not Phase.LANDED:                # IN_AIR or TAKEOFF
            self.phase = Phase.FLYING
            return None
        self.phase = Phase.FLYING
        self._descend_since = None
        return self._boundary('vehicle_takeoff', f'the vehicle reports {state.name} after ON_GROUND '
                                                 '(/uav/landed_state)')

    def observe_surface(self, t: float, clearance_m: float) -> None:
        """The camera saw a surface `clearance_m` below base_link at time `t` (placed by the latest odometry)."""
        clearance_m, t = float(clearance_m), float(t)
        if not (math.isfinite(clearance_m) and clearance_m > 0 and math.isfinite(t)) or not self._samples:
            return
        if self._surfaces and t < self._surfaces[-1][0] - _EPS:      # clock stepped back
            self._surfaces.clear()
        _, x, y, z = self._samples[-1]
        self._surfaces.append((t, x, y, z - clearance_m))
        while self._surfaces and self._surfaces[0][0] < t - self.cfg.surface_memory_s:
            self._surfaces.popleft()

    def request_reset(self, now: float) -> str | None:
        """Rate limit of ~/reset at clock time `now`: None when the call may reset, else why it is refused (counted)."""
        now = float(now)
        last, gap = self._last_service, self.cfg.reset_min_interval_s
        if gap > 0 and last is not None and 0.0 <= now - last < gap:
            self.resets_refused += 1
            return (f'refused: {now - last:.2f} s after the last reset, sooner than flight_reset_min_interval_s '
                    f'({gap:g} s)')
        self._last_service = now        # a clock that stepped back (now < last) starts the interval anew
        return None

    def update(self, t: float, position: np.ndarray, velocity: np.ndarray, command_vz: float,
               now: float | None = None) -> str | None:
        """One odometry sample stamped `t` (`position` odom; `velocity` any frame: only its norm is read) and the
        vertical command flown in the previous step; `now` is the clock of ``vehicle_state`` (None: `t`).
        The boundary seen, or None."""
        c = self.cfg
        if not c.enabled:
            return None
        p = np.asarray(position, dtype=float).reshape(3)
        speed = float(np.linalg.norm(np.asarray(velocity, dtype=float)))
        t = float(t)
        now = t if now is None else float(now)
        if not (np.all(np.isfinite(p)) and math.isfinite(speed) and math.isfinite(t) and math.isfinite(now)):
            return None
        last = self._samples[-1] if self._samples else None
        if last is not None and t < last[0] - _EPS:    # the clock stepped back: the windows go on from here
            self.clock_steps += 1
            self._redate(t - last[0] - self._period())
        boundary = None
        if last is not None:
            dt = max(t - last[0], 0.0)
            moved = math.dist(p, last[1:])
            explained = max(speed, self._last_speed) * dt
            if moved > c.jump_m + explained:
                self._restart_windows()
                self._surfaces.clear()
                self._rest_z = None
                self.phase = self._reported_phase() or Phase.UNKNOWN
                boundary = self._boundary('odom_jump', f'odometry moved {moved:.2f} m in {dt:.2f} s (its speed '
                                                       f'explains {explained:.2f} m)')
        self._samples.append((t, float(p[0]), float(p[1]), float(p[2])))
        self._last_speed = speed
        horizon = max(c.rest_s + c.touchdown_lookback_s, c.takeoff_window_s) + 0.5
        while self._samples[0][0] < t - horizon:
            self._samples.popleft()
        if math.isfinite(command_vz) and command_vz <= -c.rest_descent_mps:
            if self._descend_since is None:
                self._descend_since = t
        else:
            self._descend_since = None
        if boundary is not None:
            return boundary
        if self.vehicle_known(now):                 # the vehicle's own report decides landings and take-offs
            if self.phase is Phase.LANDED:
                self._track_rest(t)
            return None
        if self.phase is Phase.UNKNOWN:
            self._start(t)
            return None
        if self.phase is Phase.LANDED:
            return self._takeoff(t)
        return self._landing(t)

    # ------------------------------------------------------------------ rules
    def _period(self) -> float:
        """Mean interval between the odometry samples held (0 with fewer than two)."""
        s = self._samples
        return (s[-1][0] - s[0][0]) / (len(s) - 1) if len(s) > 1 else 0.0

    def _redate(self, shift: float) -> None:
        """Move every time held by `shift` (< 0: the clock stepped back; the next sample follows the last one by a
        sample period), so the windows restart from the step instead of waiting for the clock to come back."""
        self._samples = deque((t + shift, x, y, z) for t, x, y, z in self._samples)
        self._surfaces = deque((t + shift, x, y, z) for t, x, y, z in self._surfaces)
        if self._descend_since is not None:
            self._descend_since += shift
        if self._above_since is not None:
            self._above_since += shift

    def _restart_windows(self) -> None:
        self._samples.clear()
        self._descend_since = None
        self._above_since = None

    def _window(self, t: float, span: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(times, positions N x 3) of the samples within `span` before `t`; None until the samples cover it."""
        s = self._samples
        if not s or s[0][0] > t - span + _EPS:
            return None
        rows = [r for r in s if r[0] >= t - span - _EPS]
        if len(rows) < _MIN_SAMPLES:
            return None
        a = np.asarray(rows, dtype=float)
        return a[:, 0], a[:, 1:]

    def _rest(self, t: float) -> tuple[np.ndarray, float] | None:
        """(mean position, fitted speed) of the rest window when the vehicle is at rest in it, else None."""
        w = self._window(t, self.cfg.rest_s)
        if w is None:
            return None
        ts, ps = w
        mean, slope = _fit(ts, ps)
        speed = float(np.linalg.norm(slope))
        spread = float(np.max(np.linalg.norm(ps - mean, axis=1)))
        if speed > self.cfg.rest_speed_mps or spread > self.cfg.rest_radius_m:
            return None
        return mean, speed

    def _start(self, t: float) -> None:
        """Decide landed or flying at the first full window (no boundary)."""
        if self._window(t, self.cfg.rest_s) is None:
            return
        rest = self._rest(t)
        if rest is not None and rest[0][2] < self.cfg.ground_altitude_m:
            self.phase, self._rest_z = Phase.LANDED, float(rest[0][2])
        else:
            self.phase = Phase.FLYING

    def _surface_below(self, t: float, xy: np.ndarray) -> float | None:
        """Highest surface (odom z) the camera saw within surface_radius_m of `xy` lately; None if none."""
        c = self.cfg
        tops = [z for (ts, x, y, z) in self._surfaces
                if ts >= t - c.surface_memory_s and math.hypot(x - xy[0], y - xy[1]) <= c.surface_radius_m]
        return max(tops) if tops else None

    def _landing(self, t: float) -> str | None:
        c = self.cfg
        if self._descend_since is None or t - self._descend_since < c.rest_s - _EPS:
            return None
        rest = self._rest(t)
        if rest is None:
            return None
        mean, speed = rest
        z = float(mean[2])
        surface = self._surface_below(t, mean[:2])
        if surface is not None and z - surface > c.contact_height_m:
            return None                             # well above what the camera sees below: still in the air
        start = t - c.rest_s
        before = [r[3] for r in self._samples if start - c.touchdown_lookback_s <= r[0] < start]
        came_down = max(before) - z if before else 0.0
        if came_down >= c.touchdown_descent_m:
            why = f'came down {came_down:.2f} m'
        elif z <= c.ground_altitude_m:
            why = f'{z:.2f} m over the floor'
        elif surface is not None:
            why = f'{z - surface:.2f} m over the surface seen below'
        else:
            return None                             # no evidence of contact: a hover while the command descends
        self.phase, self._rest_z, self._above_since = Phase.LANDED, z, None
        return self._boundary('landed', f'at rest {c.rest_s:g} s ({speed:.3f} m/s) while the command descended, '
                                        f'{why}')

    def _track_rest(self, t: float) -> None:
        """While landed: the rest altitude follows windows at rest near it (a slow drift, not a climb to a hover)."""
        rest = self._rest(t)
        if rest is not None:
            z = float(rest[0][2])
            if self._rest_z is None or abs(z - self._rest_z) < 0.5 * self.cfg.takeoff_climb_m:
                self._rest_z = z

    def _takeoff(self, t: float) -> str | None:
        c = self.cfg
        self._track_rest(t)
        w = self._window(t, c.takeoff_window_s)
        if w is None:
            return None
        if self._rest_z is None:                    # landed by the vehicle's report before any odometry
            self._rest_z = float(w[1][:, 2].min())
        mean, slope = _fit(*w)
        rise, climb = float(mean[2]) - self._rest_z, float(slope[2])
        if rise <= c.takeoff_climb_m:
            self._above_since = None
            return None
        if self._above_since is None:
            self._above_since = t
        if climb < c.takeoff_speed_mps and t - self._above_since < c.takeoff_hold_s - _EPS:
            return None
        self.phase, self._descend_since, self._above_since = Phase.FLYING, None, None
        return self._boundary('takeoff', f'rose {rise:.2f} m above the rest at {climb:.2f} m/s')
