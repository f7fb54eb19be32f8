"""Pilot override: a non-learned arbitration rule that lets a deliberate correction through.

Rule: while the pilot holds a horizontal key (its mean horizontal command over the observation window,
1 s, is faster than ``speed_mps``) and does not command a descent, the assistant's action is replaced:
below ``climb_below_m`` of altitude over the floor by a' = (u_x, u_y, 2 max(u_z, climb) - u_z), so that
the blended V = (u + a') / 2 = (u_x, u_y, max(u_z, climb_mps)): the pilot's correction passes at full
speed and the vehicle rises gently; higher up by a' = 0 (relinquish, V = u). a' is clipped to the
actor's max_speed as any action is.

Why: a pilot who set off for a neighbour pad and sees the mistake low over it (late_correction; the
independent pilots' "sudden late corrections") holds a key toward the right pad. The
nearest-pad behaviour the learned assistant imitates cancels that command over the pad below and pushes
down, so the pilot lands on the wrong pad, or, once the correction wins, the vehicle slides off the pad
still descending and catches its edge (tipped over). The climb is what makes letting go safe: a
multirotor accelerating sideways at 1-1.5 m/s keeps sinking for a while, and low over a pad up to 1.2 m
tall its legs then hit the pad's edge.

Threshold: the paper pilot taps keys near its aim (duty <= 0.5 per axis: <= 0.71 m/s mean on a diagonal),
so its fine corrections never engage the rule; a held key (1 m/s) does within ~0.75 s.

Reversals: a pilot with a reaction delay overshoots its aim with a held key and comes back with another,
held the opposite way; passing those through keeps it oscillating around the pad until time runs out
(delay pilots: 74.5 % success with this exception, 61.8 % without). So a held key that reverses one held
within the last ``reversal_s`` seconds (negative dot product of the window means) is an overshoot being
corrected, not a departure, and the actor keeps helping. A pilot leaving the wrong pad has descended over it for seconds
first, so its held key reverses nothing.

Persistent push (``persist_s`` > 0, 2 s by default): the same yield also engages, descending or not, when
for the last ``persist_s`` the pilot's horizontal command has pointed one way (no sample against its
mean, no held key the other way within ``reversal_s``), its mean along one axis is at least
``persist_speed_mps`` (0.6; ``persist_floor_speed_mps``, 0.4, when the depth image shows bare floor under
every leg: no pad there to hold the pilot on), and the vehicle made less than ``held_back_fraction``
(half) of that speed along it: the assistant has been holding the vehicle back against a pilot who keeps
asking to go somewhere. Not lower than ``persist_min_height_m`` (1 m) over the surface below (pad top or
floor, from the depth under the legs; inside the camera's blind range, the floor guard's remembered pad):
the last metre is landing, and a push there is positioning. Why: the keyboard families descend only
once they believe they are over their aim, and the actor behaves as if a descent meant "this pad" and a
descent over bare floor "the pad is behind". A pilot who descends along a glide path toward a farther
pad, or gets low first and flies on over the nearer pads (ordinary for people; the held-out glide and
low_flyer families), is otherwise held over the first pad it crosses, or pushed back from the start, and
the paper's conformance then drags its own aim onto that pad (without the rule 30 % and 49 % goal-pad
success, worse than unassisted on error; 74.5 % each with it). What it leaves alone: fine positioning
(keyboard taps near the aim: <= 0.5 m/s per axis, and they reverse), an overshoot (the bang-bang family
holds its key past the aim for <= 0.9 s, then reverses), the last metre, and a pilot the assistant is
not holding back.

Held climb (``persist_climb_mps`` > 0, 0.3 m/s by default; timed by ``persist_s``): when for the last
``persist_s`` the pilot has commanded a climb (every sample up, the mean at least ``persist_climb_mps``)
and the vehicle rose at less than ``held_back_fraction`` of it, the same yield engages and holds for as
long as the pilot keeps commanding the climb (no re-timing once the vehicle rises). No height limit: a
climb is never landing. Why: the actor behaves as if being low over a pad meant "land here", so a pilot
cruising low over the nearer pads (the held-out low_flyer family) who climbs back to its height is
otherwise pushed down onto the first pad against its climb (actor a_z -0.6 against u_z +0.5: the vehicle
sinks and lands there). What it leaves alone: a short climb (a keyboard pilot over its aim taps up
for < 2 s), one the vehicle makes, a pilot who also commands down in the window.

Long push (``long_push_s`` > 0, 5 s by default): the same yield also engages when for the last
``long_push_s`` the pilot's horizontal command has pointed one way (no sample against its mean, no held
key the other way within ``reversal_s``) at a mean of at least ``long_push_speed_mps`` (0.35) along one
axis, it commanded no descent at any sample, the vehicle made less than ``held_back_fraction`` of that
speed, and it is at least ``long_push_min_height_m`` (0.3 m) over the surface below. Once engaged it is
held (no re-timing once the vehicle goes along) while the pilot keeps pushing that way at that mean and
its mean vertical command over ``long_push_s`` descends no faster than ``long_push_release_mps`` (0.15);
at a step where the pilot taps a descent on the way the actor's action stands. Why: a beta 0 novice of
the held-out low_flyer family taps its keys at duty 0.5 (0.5 m/s mean, below the persistent push's 0.6,
which keeps keyboard fine positioning out) and cruises 0.5-1.1 m over the pad tops (inside the
persistent push's last metre); without this test the actor cancels each tap over the first pad and holds
it there for 40-50 s, until the paper's conformance drags the pilot's aim onto that pad or time runs out
(low_flyer beta 0: 2 of 10 on the goal pad). What it leaves alone: a pilot descending (landing where it
is: the paper pilot and every keyboard family descend over their aim), positioning that goes both ways,
a pilot the vehicle follows, and the last 0.3 m.

Landing spots (``spot_memory_s`` > 0, 20 s by default): where the pilot commanded a descent while not
going anywhere (its 1 s mean horizontal command under ``spot_speed_mps``, 0.4), the odometry position is
remembered for ``spot_memory_s``. A persistent or long push heading back to such a spot (one within
``spot_radius_m``, 1.2 m, lies ``spot_ahead_m``, 0.2 m, or more ahead along the push), and a held climb
within ``spot_radius_m`` of one, do not engage: the actor keeps its action. The held key is unchanged (a
late correction, a key held at 1 m/s, still passes at once). Why: a pilot who ignores the assistant
(alpha ~ 0, the held-out ignorer family) and misjudges its aim by 0.5-1.3 m off the pad hovers near that
aim, descends whenever it believes it is over it, and, taken back over the pad by the actor, taps its
way back there for 2-5 s with no descent and climbs when low. Without landing spots each of those passes
as a persistent push, a long push or a held climb, so the vehicle goes back to the pilot's aim (off the
pad), the actor takes it back, and the landing times out off the pad (several yields in 30 s). The
nearest-pad reference, which never yields but to a held key, lands such pilots. What it leaves alone:
a pilot leaving a pad it tried (the push points away from the spot: late_correction), a glide path (it
descends while going somewhere, no spot), the first push of a low flyer (no descent before it), anything
more than ``spot_memory_s`` after the descent.

It uses only what the actor observes (u and its window mean), odometry position, altitude and velocity,
the depth image's surface test (assist_policy.safety; the caller passes none with the floor guard off,
the altitude standing in, as evaluate's env and policy_core both do) and time. Pure numpy; no rclpy.
"""
from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from assist_common.settings import check_named, setting
from .scripted import YIELD_SPEED_MPS, holds_key
from .settings import node_param
from .safety import FloorGuard
from .stage import ACTION, Decision, Parts, Rule, Stage, StepContext

# what the depth image shows below the vehicle, on demand: (bare floor under every leg, height over the
# surface below in m), None where unknown (safety.FloorGuard.surface_below)
Surface = Callable[[], tuple[bool | None, float | None]]


@dataclass
class OverrideConfig:
    """Settings of the pilot override (policy_node parameters pilot_override_* map onto these)."""

    enabled: bool = node_param(True, 'pilot_override', 'Pilot override (assist_policy.override, not learned): while '
                               'the pilot holds a horizontal key and does not descend, its correction passes (the '
                               "vehicle rises gently when low) instead of the actor's action. Default false in mode "
                               'oracle.')
    # window-mean horizontal pilot speed that counts as a held key: the yielding teacher's test and threshold
    # (scripted.holds_key, YIELD_SPEED_MPS: above the paper pilot's fine taps, below a held key)
    speed_mps: float = node_param(YIELD_SPEED_MPS, 'pilot_override_speed_mps', 'Mean horizontal pilot speed over '
                                  'the last second (m/s) above which a key counts as held; keep it below the '
                                  "pilot's key speed (teleop speed, 1 m/s by default).", min=0.0, max=10.0)
    # vertical V while yielding low (the pilot's own climb if faster)
    climb_mps: float = node_param(0.3, 'pilot_override_climb_mps', 'Vertical velocity while the pilot override acts '
                                  "low (m/s; the pilot's own climb if faster).", min=0.0, max=1.0)
    # altitude over the floor below which the yield adds the climb (pads <= 1.2 m)
    climb_below_m: float = node_param(2.0, 'pilot_override_climb_below_m', 'Altitude (odom z over the floor, m) '
                                      'below which the pilot override adds the climb; above it it relinquishes.',
                                      min=0.0, max=20.0)
    # a held key reversing one held within this many seconds does not engage it
    reversal_s: float = node_param(3.0, 'pilot_override_reversal_s', 'A held key reversing one held within this '
                                   'many seconds is an overshoot being corrected: the pilot override stays out (s).',
                                   min=0.0, max=60.0)
    # persistent push (module docstring): a command held against the assistant for persist_s (0 = off)
    persist_s: float = node_param(2.0, 'pilot_override_persist_s', 'Persistent push: a horizontal command held one '
                                  'way this long (s) while the assistant held the vehicle back passes as a held key '
                                  'does, descending or not; 0 = off.', min=0.0, max=60.0)
    # its mean along one axis over a pad (fine positioning: <= 0.5 per axis)
    persist_speed_mps: float = node_param(0.6, 'pilot_override_persist_speed_mps', 'Mean horizontal pilot speed '
                                          'over pilot_override_persist_s (m/s) that counts as a persistent push '
                                          'over a pad (above fine positioning).', min=0.01, max=10.0)
    # ... over bare floor under every leg (no pad to hold the pilot on)
    persist_floor_speed_mps: float = node_param(0.4, 'pilot_override_persist_floor_speed_mps', 'The same over bare '
                                                'floor under every leg in the depth image (m/s).', min=0.01, max=10.0)
    # held back: the vehicle made less than this share of the push's speed
    held_back_fraction: float = setting(0.5, ge=0)
    # not lower than this over the surface below (the last metre: landing)
    persist_min_height_m: float = setting(1.0, ge=0)
    # held climb (module docstring): a climb commanded for persist_s that the vehicle does not make (0 = off)
    # mean climb command over persist_s that counts (keys climb at 0.5)
    persist_climb_mps: float = node_param(0.3, 'pilot_override_persist_climb_mps', 'Held climb: a climb commanded '
                                          'for pilot_override_persist_s at at least this mean (m/s) that the '
                                          'vehicle did not make passes until the pilot stops climbing; 0 = off.',
                                          min=0.0, max=10.0)
    # long push (module docstring): a slower push held longer, with no descent commanded (0 = off)
    long_push_s: float = node_param(5.0, 'pilot_override_long_push_s', 'Long push: a slower horizontal command held '
                                    'one way this long (s), with no descent, while the assistant held the vehicle '
                                    'back passes as a held key does until the pilot stops pushing that way or '
                                    'descends; 0 = off.', min=0.0, max=60.0)
    # its mean along one axis (a novice taps at 0.5 m/s)
    long_push_speed_mps: float = node_param(0.35, 'pilot_override_long_push_speed_mps', 'Mean horizontal pilot '
                                            'speed along one axis over pilot_override_long_push_s (m/s) that counts '
                                            'as a long push.', min=0.01, max=10.0)
    long_push_min_height_m: float = setting(0.3, ge=0)  # not lower than this over the surface below (touching down)
    # latched: released once the mean command over long_push_s descends faster
    long_push_release_mps: float = setting(0.15, ge=0)
    # landing spots (module docstring): where the pilot commanded a descent while not going anywhere (0 = off)
    # such a descent is remembered this long
    spot_memory_s: float = node_param(20.0, 'pilot_override_spot_memory_s', 'Landing spots: where the pilot '
                                      'commanded a descent while not going anywhere is remembered this long (s); a '
                                      'persistent or long push back to such a spot, or a held climb near one, stays '
                                      'with the actor (positioning, not leaving); 0 = off.', min=0.0, max=600.0)
    spot_speed_mps: float = setting(0.4, ge=0)  # ... commanded with a 1 s mean horizontal command slower than this
    # a push toward a spot this close, or a climb this close to one, stays
    spot_radius_m: float = node_param(1.2, 'pilot_override_spot_radius_m', 'A landing spot this close (horizontal '
                                      'm) counts for pilot_override_spot_memory_s.', min=0.0, max=10.0)
    spot_ahead_m: float = setting(0.2, ge=0)  # ... with the actor: 'toward' = the spot this far ahead along the push

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line): the push speeds' lower bounds
        keep a pilot pressing nothing from engaging the rule."""
        check_named(self, type(self).__name__)


def yield_action(cfg: OverrideConfig, u: np.ndarray, altitude_m: float,
                 max_speed: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """The agent action (m/s) while yielding: V = (u_xy, max(u_z, climb)) when low, V = u (a = 0) higher up."""
    if float(altitude_m) >= cfg.climb_below_m:
        return np.zeros(3)
    a = np.array([u[0], u[1], 2.0 * max(float(u[2]), cfg.climb_mps) - u[2]])
    ms = np.asarray(max_speed, dtype=float).reshape(3)
    return np.clip(a, -ms, ms)


def _surface_below(surface: Surface | None, altitude_m: float) -> tuple[bool | None, float]:
    """(bare floor under every leg or None, height over the surface below in m): `surface()`, the altitude
    `altitude_m` standing in for a height it does not know."""
    over_floor, height = (None, None) if surface is None else surface()
    if height is None or not math.isfinite(float(height)):
        return over_floor, float(altitude_m)
    return over_floor, float(height)


class PilotOverride:
    """The rule with its memory of recent held keys (for reversals) and commands (for a persistent push).

    ``reset`` at each new landing. ``mode`` says which test engaged on the last ``apply``: 'held_key',
    'persistent', 'climb', 'long' or None; ``kept`` whether a landing spot turned a push or climb down.
    """

    def __init__(self, cfg: OverrideConfig | None = None):
        self.cfg = cfg or OverrideConfig()
        self._held: deque[tuple[float, float, float]] = deque()    # (time, window-mean x, y) of recent held keys
        # (time, u_x, u_y, v_x, v_y, u_z, v_z)
        self._recent: deque[tuple[float, float, float, float, float, float, float]] = deque()
        self._climbing = False        # a held climb engaged the yield and the pilot still commands a climb
        self._long: np.ndarray | None = None    # a long push engaged: its direction (unit, horizontal)
        self._spots: deque[tuple[float, float, float]] = deque()    # (time, x, y) of landing spots (odom)
        self._xy: np.ndarray | None = None     # the vehicle's odom x, y this step (None: unknown)
        self._near: np.ndarray | None = None   # offsets to the spots within spot_radius_m, this step (on demand)
        self.kept = False             # a landing spot kept the actor's action on the last apply (a push back, a climb)
        self.mode: str | None = None

    def reset(self) -> None:
        """Forget the held keys and commands seen (new landing)."""
        self._held.clear()
        self._recent.clear()
        self._climbing = False
        self._long = None
        self._spots.clear()
        self._xy = None
        self._near = None
        self.kept = False
        self.mode = None

    def _span_s(self) -> float:
        """How far back the recent samples are kept: the longest window a test reads (s)."""
        return max(self.cfg.persist_s, self.cfg.long_push_s)

    def _window(self, span_s: float | None = None) -> np.ndarray | None:
        """The samples of the last `span_s` (persist_s by default) as rows (time, u_x, u_y, v_x, v_y, u_z, v_z).

        None unless the samples kept span that long.
        """
        span = self.cfg.persist_s if span_s is None else span_s
        r = self._recent
        if span <= 0 or len(r) < 2 or r[-1][0] - r[0][0] < span - 1e-6:
            return None
        w = np.array(r)
        start = int(np.searchsorted(w[:, 0], w[-1, 0] - span + 1e-6, side='right')) - 1
        return w[max(start, 0):]

    def persistent_push(self, surface: Surface | None = None, altitude_m: float = math.inf) -> bool:
        """Whether the pilot has pushed one way for persist_s, held back by the assistant (module docstring).

        `surface()` gives (bare floor under every leg, height over the surface below in m; None where
        unknown, the altitude `altitude_m` then stands in for the height); it is read only when every other
        test passes (the env renders a camera frame for it). Lower than persist_min_height_m the vehicle
        is landing, and a push there is positioning.
        """
        c = self.cfg
        window = self._window()
        if window is None:
            return False
        m = window[:, 1:3].mean(axis=0)
        # per axis: keyboard fine positioning taps each axis at <= 0.5 m/s mean (<= 0.71 on a diagonal)
        along = float(np.abs(m).max())
        if along < min(c.persist_floor_speed_mps, c.persist_speed_mps):
            return False
        speed = float(np.hypot(m[0], m[1]))
        if self.toward_spot(m / speed) or not self._held_back(window, m / speed, speed):
            return False
        over_floor, height = _surface_below(surface, altitude_m)
        if not height >= c.persist_min_height_m:
            return False
        return along >= (c.persist_floor_speed_mps if over_floor is True else c.persist_speed_mps)

    def _spot_offsets(self) -> np.ndarray:
        """Horizontal offsets (n, 2) from the vehicle to the remembered landing spots within spot_radius_m.

        Computed once per ``apply`` (the pushes and the climb may all ask); ``apply`` forgets it each step.
        """
        if self._near is None:
            self._near = np.zeros((0, 2))
            if self._xy is not None and self._spots:
                rel = np.array([(x, y) for _, x, y in self._spots]) - self._xy
                self._near = rel[np.hypot(rel[:, 0], rel[:, 1]) <= self.cfg.spot_radius_m]
        return self._near

    def toward_spot(self, d: np.ndarray) -> bool:
        """Whether a push along unit `d` heads back to a landing spot nearby (one spot_ahead_m ahead along it)."""
        rel = self._spot_offsets()
        toward = bool(rel.size) and float((rel @ np.asarray(d, dtype=float)).max()) >= self.cfg.spot_ahead_m
        self.kept = self.kept or toward
        return toward

    def _held_back(self, window: np.ndarray, d: np.ndarray, speed: float) -> bool:
        """Whether a push along unit `d` at `speed` over `window` went one way and the vehicle did not go along.

        One way: no sample of the window and no held key within reversal_s against it (else it corrects an
        overshoot or positions). Not going along: the vehicle's mean velocity along `d` over the window is
        under held_back_fraction of `speed`.
        """
        if float((window[:, 1:3] @ d).min()) < 0.0 or any(hx * d[0] + hy * d[1] < 0.0 for _, hx, hy in self._held):
            return False
        return float(window[:, 3:5].mean(axis=0) @ d) < self.cfg.held_back_fraction * speed

    def held_climb(self) -> bool:
        """Whether the pilot has commanded a climb for persist_s that the vehicle did not make (module docstring)."""
        c = self.cfg
        window = None if c.persist_climb_mps <= 0 else self._window()
        if window is None:
            return False
        uz, vz = window[:, 5], window[:, 6]
        if float(uz.min()) <= 0.0 or float(uz.mean()) < c.persist_climb_mps:
            return False              # not a climb held the whole time
        if len(self._spot_offsets()):
            self.kept = True
            return False              # rising off a spot it tried to land on: positioning, the actor's
        return float(vz.mean()) < c.held_back_fraction * float(uz.mean())

    def long_push(self, surface: Surface | None = None, altitude_m: float = math.inf) -> bool:
        """Whether a slower push held for long_push_s with no descent lets the pilot fly on (module docstring).

        Latched once engaged: it then holds while the pilot keeps pushing that way at long_push_speed_mps
        and does not descend (the mean command over long_push_s) faster than long_push_release_mps.
        """
        c = self.cfg
        window = None if c.long_push_s <= 0 else self._window(c.long_push_s)
        if window is None:
            self._long = None
            return False
        m, uz = window[:, 1:3].mean(axis=0), window[:, 5]
        speed = float(np.hypot(m[0], m[1]))
        if float(np.abs(m).max()) < c.long_push_speed_mps or speed <= 0.0:
            self._long = None
            return False
        d = m / speed
        if self._long is not None:
            if float(self._long @ d) > 0.0 and float(uz.mean()) >= -c.long_push_release_mps:
                self._long = d
                return True
            self._long = None
            return False
        if float(uz.min()) < 0.0:
            return False              # a descent commanded in the window: landing, not flying on
        if self.toward_spot(d) or not self._held_back(window, d, speed):
            return False
        if not _surface_below(surface, altitude_m)[1] >= c.long_push_min_height_m:
            return False
        self._long = d
        return True

    def apply(self, now: float, u: np.ndarray, mean_u: np.ndarray, altitude_m: float,
              max_speed: np.ndarray | tuple[float, float, float], velocity: np.ndarray | None = None,
              surface: Surface | None = None, position: np.ndarray | None = None) -> np.ndarray | None:
        """The agent action (m/s) replacing the actor's at time `now`, or None (the rule does not act).

        `velocity`: the vehicle's (base_link, m/s; None: the persistent-push test is off this step);
        `position`: the vehicle's in odom (m; None: no landing spot is remembered or consulted this step);
        `surface`: what the depth image shows below, read only if needed and at most once (``persistent_push``,
        ``long_push``; None: unknown, the altitude over the floor stands in for the height).
        """
        c = self.cfg
        self.mode = None
        self.kept = False
        self._near = None
        if surface is not None:
            surface = functools.cache(surface)    # both pushes may ask: the depth image is read once a step
        u = np.asarray(u, dtype=float).reshape(3)
        m = np.asarray(mean_u, dtype=float).reshape(3)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(m)) and math.isfinite(float(altitude_m))
                and math.isfinite(float(now))):
            return None               # nothing to judge by: the actor's action stands (the guard still acts)
        if self._held and self._held[-1][0] > now:
            self._held.clear()        # the clock went back (a new run, a replayed bag): old keys do not count
        if self._recent and self._recent[-1][0] > now:
            self._recent.clear()
        if self._spots and self._spots[-1][0] > now:
            self._spots.clear()
        while self._spots and self._spots[0][0] < now - c.spot_memory_s:
            self._spots.popleft()
        xy = None if position is None else np.asarray(position, dtype=float).reshape(-1)[:2]
        self._xy = xy if xy is not None and xy.size == 2 and np.all(np.isfinite(xy)) else None
        if (self._xy is not None and c.spot_memory_s > 0 and u[2] < 0.0
                and float(np.hypot(m[0], m[1])) < c.spot_speed_mps):
            self._spots.append((float(now), float(self._xy[0]), float(self._xy[1])))
        while self._held and self._held[0][0] < now - c.reversal_s:
            self._held.popleft()
        v = None if velocity is None else np.asarray(velocity, dtype=float).reshape(-1)
        if v is None or v.size < 3 or not np.all(np.isfinite(v[:3])):
            self._recent.clear()      # a gap in what it judges by: the push is timed afresh
            self._climbing = False
            self._long = None
        else:
            self._recent.append((float(now), float(u[0]), float(u[1]), float(v[0]), float(v[1]),
                                 float(u[2]), float(v[2])))
            while len(self._recent) > 1 and self._recent[1][0] <= now - self._span_s():
                self._recent.popleft()      # keep one sample at or before the window's start: it spans persist_s
        held = holds_key(m, c.speed_mps)
        if held:
            mx, my = float(m[0]), float(m[1])
            reverses = any(mx * hx + my * hy < 0.0 for _, hx, hy in self._held)
            self._held.append((float(now), mx, my))
            if not c.enabled or reverses:
                return None
            if u[2] >= 0.0:
                self.mode = 'held_key'
                return yield_action(c, u, altitude_m, max_speed)
        if not c.enabled:
            return None
        self._climbing = u[2] > 0.0 and (self._climbing or self.held_climb())
        if self._climbing:
            self.mode = 'climb'       # held until the pilot stops commanding the climb
            return yield_action(c, u, altitude_m, max_speed)
        if self.persistent_push(surface, float(altitude_m)):
            self.mode = 'persistent'
            return yield_action(c, u, altitude_m, max_speed)
        if self.long_push(surface, float(altitude_m)) and u[2] >= 0.0:
            self.mode = 'long'        # latched; a descent tapped on the way is the actor's to judge this step
            return yield_action(c, u, altitude_m, max_speed)
        return None


# ----------------------------------------------------------------------------------------------- stage
_OVERRIDE_REASONS = {'held_key': 'pilot override: the pilot\'s held correction passes',
                     'persistent': 'pilot override: the pilot\'s persistent push passes',
                     'climb': 'pilot override: the pilot\'s held climb passes',
                     'long': 'pilot override: the pilot\'s long push passes'}


class OverrideStage(Stage):
    """2. The pilot override: a deliberate correction passes instead of the actor's action."""

    key, phase, position = 'pilot_override', ACTION, 20
    # /diagnostics value -> the mode it counts
    DIAGNOSTICS = {'pilot_override_persistent_engaged': 'persistent', 'pilot_override_climb_engaged': 'climb',
                   'pilot_override_long_engaged': 'long', 'pilot_override_spot_kept': 'spot_kept'}

    def __init__(self, override: PilotOverride, guard: FloorGuard):
        self.override, self._guard = override, guard

    def reset(self) -> None:
        """Forget held keys, pushes and landing spots."""
        self.override.reset()

    def apply(self, ctx: StepContext, d: Decision) -> Decision | None:
        """The pilot's correction (with a gentle climb when low), or None."""
        # the depth image's surface under the legs, through the floor guard's test (off with the guard: the
        # altitude stands in)
        surface = (None if not self._guard.cfg.enabled or ctx.frame is None
                   else lambda: self._guard.surface_below(ctx.frame.image, ctx.position))
        a = self.override.apply(ctx.t, ctx.u, ctx.mean_u, float(ctx.position[2]), ctx.max_speed, ctx.velocity,
                                surface, ctx.position)
        if a is None:
            return None
        return Decision(a, None, self.key, _OVERRIDE_REASONS.get(self.override.mode, _OVERRIDE_REASONS['held_key']),
                        final=True)           # the pilot's correction: the later action stages leave it

    def modes(self, acted: bool, ran: bool) -> tuple[str, ...]:
        """The override's mode when it acted; 'spot_kept' when a landing spot kept the actor's action."""
        return ((self.override.mode,) if acted and self.override.mode else ()) + (
            ('spot_kept',) if ran and self.override.kept else ())

    def diagnostics(self, modes) -> dict[str, int]:
        """Steps per override mode and with a landing spot kept."""
        return {name: modes[f'{self.key}:{mode}'] for name, mode in self.DIAGNOSTICS.items()}


def _make(cfg: OverrideConfig, parts: Parts, threshold) -> tuple[dict, tuple[Stage, ...]]:
    """The override and its stage (the floor guard's surface test tells it the height over what is below)."""
    override = PilotOverride(cfg)
    return {'override': override}, (OverrideStage(override, parts['guard']),)


RULE = Rule('override', 'pilot_override', 'override', OverrideConfig, goal_agnostic=True, title='pilot override',
            make=_make)
