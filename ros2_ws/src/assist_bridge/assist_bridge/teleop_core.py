"""Keyboard teleop core: terminal bytes -> key tokens -> held keys -> body-FLU velocity. No rclpy.

The paper's scheme: W/S forward/back, A/D left/right, arrow up/down climb/descend, space stops,
q quits. Terminals report key presses only (no key-up), and a held key repeats after an initial
delay. So a key counts as held for `initial_hold_s` after its first event (longer than the
terminal's auto-repeat delay) and, once it repeats, until its repeats stop for `repeat_timeout_s`.

The assistant's intent (/assist/goal_estimate, /assist/descent_ok) is validated here too
(`check_goal_estimate`, shared with the pilot station) and shown as one status line
(`IntentLine`): where the estimated goal pad lies in body terms and whether descending is safe.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from assist_common.frames import enu_to_flu, heading
from assist_common.settings import check_named, setting

# Key bindings as data: token -> (axis in FLU (0=x forward, 1=y left, 2=z up), direction).
KEY_BINDINGS: dict[str, tuple[int, int]] = {
    'w': (0, +1), 's': (0, -1),
    'a': (1, +1), 'd': (1, -1),
    'UP': (2, +1), 'DOWN': (2, -1),
}
STOP_KEYS = frozenset({' '})
QUIT_KEYS = frozenset({'q', 'CTRL_C', 'CTRL_D'})
# Escape sequences of the arrow keys (normal and application cursor mode).
ESCAPES = {'\x1b[A': 'UP', '\x1b[B': 'DOWN', '\x1b[C': 'RIGHT', '\x1b[D': 'LEFT',
           '\x1bOA': 'UP', '\x1bOB': 'DOWN', '\x1bOC': 'RIGHT', '\x1bOD': 'LEFT'}
CONTROL = {'\x03': 'CTRL_C', '\x04': 'CTRL_D'}
HELP = 'W/S forward/back  A/D left/right  Up/Down climb/descend  space stop  q quit'


@dataclass
class TeleopConfig:
    """Speeds and key timing (node parameters map onto these)."""

    speed: float = setting(1.0, gt=0)  # m/s horizontal (W/S/A/D)
    speed_z: float = setting(0.5, gt=0)  # m/s vertical (arrows)
    rate_hz: float = setting(20.0, gt=0)  # publish rate of /pilot/cmd_vel
    initial_hold_s: float = setting(0.6, gt=0)  # > terminal auto-repeat delay (typically 0.25-0.6 s)
    repeat_timeout_s: float = setting(0.15, gt=0)  # > auto-repeat period (typically 0.03-0.05 s)

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self)


class KeyDecoder:
    """Incremental decoder of terminal input (handles escape sequences split across reads)."""

    def __init__(self) -> None:
        self._pending = ''

    def feed(self, data: str) -> list[str]:
        """Decode characters into tokens: 'w', ' ', 'UP', 'CTRL_C', ... (letters lower-cased)."""
        s = self._pending + data
        self._pending = ''
        out: list[str] = []
        i = 0
        while i < len(s):
            c = s[i]
            if c == '\x1b':
                seq = s[i:i + 3]
                if seq in ESCAPES:
                    out.append(ESCAPES[seq])
                    i += 3
                    continue
                if len(seq) < 3 and any(e.startswith(seq) for e in ESCAPES):
                    self._pending = seq      # incomplete sequence: wait for the rest
                    break
                out.append('ESC')
                i += 1
                continue
            out.append(CONTROL.get(c, c.lower()))
            i += 1
        return out


@dataclass
class _Held:
    first: float
    last: float
    repeats: int = 0


@dataclass
class TeleopCore:
    """Held-key state machine producing the pilot's body-FLU velocity."""

    cfg: TeleopConfig = field(default_factory=TeleopConfig)

    def __post_init__(self) -> None:
        self._held: dict[str, _Held] = {}
        self.quit = False
        self.last_key = ''

    def press(self, token: str, now: float) -> None:
        """One key event (a press or an auto-repeat)."""
        self.last_key = token
        if token in QUIT_KEYS:
            self.quit = True
            self._held.clear()
        elif token in STOP_KEYS:
            self._held.clear()
        elif token in KEY_BINDINGS:
            axis = KEY_BINDINGS[token][0]
            for other in [k for k in self._held if KEY_BINDINGS[k][0] == axis and k != token]:
                del self._held[other]          # the newest key on an axis wins
            h = self._held.get(token)
            if h is None:
                self._held[token] = _Held(now, now)
            else:
                h.last = now
                h.repeats += 1

    def _is_held(self, h: _Held, now: float) -> bool:
        if h.repeats == 0:
            return now - h.first <= self.cfg.initial_hold_s
        return now - h.last <= self.cfg.repeat_timeout_s

    def velocity(self, now: float) -> np.ndarray:
        """Body-FLU velocity (m/s) of the keys held at `now` (released keys are forgotten)."""
        for k in [k for k, h in self._held.items() if not self._is_held(h, now)]:
            del self._held[k]
        v = np.zeros(3)
        for k in self._held:
            axis, sign = KEY_BINDINGS[k]
            v[axis] = sign * (self.cfg.speed_z if axis == 2 else self.cfg.speed)
        return v

    def held_keys(self) -> list[str]:
        """Keys currently counted as held (as of the last velocity() call)."""
        return sorted(self._held)

    def status_line(self, now: float, width: int | None = None) -> str:
        """One-line live status for the terminal, at most `width - 1` characters (no wrap) when given.

        The key help is dropped first when the terminal is narrow, then the line is cut.
        """
        v = self.velocity(now)
        keys = ','.join(self.held_keys()) or '-'
        line = f'vx {v[0]:+.2f}  vy {v[1]:+.2f}  vz {v[2]:+.2f} m/s  keys [{keys}]'
        full = f'{line}   ({HELP})'
        if width is None:
            return full
        room = max(int(width) - 1, 0)   # the last column would wrap on some terminals
        return full if len(full) <= room else line[:room]


# ---------------------------------------------------------------------- the assistant's intent
INTENT_FRAMES = ('', 'odom')      # /assist/goal_estimate frame_id: the contract's odom ('' read as odom)


class IntentError(ValueError):
    """An unusable intent message: `reason` a fixed phrase (one log line per reason), `detail` the value,
    `kind` the reason's short key for counters (nonfinite, frame, variance, future_stamp, stale_stamp, shape)."""

    def __init__(self, kind: str, reason: str, detail: str = ''):
        super().__init__(reason + (f' ({detail})' if detail else ''))
        self.kind, self.reason, self.detail = kind, reason, detail


def stamp_age_problem(stamp_s: float | None, now_s: float, max_age_s: float,
                      tolerance_s: float) -> IntentError | None:
    """Why a header stamp makes a message unusable at `now_s` (the node's clock, sim or wall), else None; an unset
    stamp (None) is dated by its arrival. The rule of assist_common.ros_io.stamp_problem (which needs rclpy)."""
    if stamp_s is None:
        return None
    if stamp_s - now_s > tolerance_s:
        return IntentError('future_stamp', 'stamped ahead of the clock',
                           f'{stamp_s - now_s:.3f} s, tolerance {tolerance_s:g} s')
    if now_s - stamp_s > max_age_s:
        return IntentError('stale_stamp', 'stamped too long ago',
                           f'{now_s - stamp_s:.3f} s, older than {max_age_s:g} s')
    return None


def check_goal_estimate(frame_id: str, stamp_s: float | None, position: Sequence[float],
                        orientation: Sequence[float], covariance: Sequence[float], now_s: float, max_age_s: float,
                        tolerance_s: float) -> tuple[np.ndarray, float, float]:
    """A /assist/goal_estimate (PoseWithCovarianceStamped fields) -> (position in odom, xy sigma
    sqrt(max(var x, var y)), the clock time it is dated by); IntentError when it must not be shown: a
    non-finite value anywhere, a frame other than odom, a negative variance, a stamp ahead of `now_s` by
    more than `tolerance_s` or older than `max_age_s`."""
    pos, quat, cov = (np.asarray(x, dtype=float).reshape(-1) for x in (position, orientation, covariance))
    if pos.shape != (3,) or quat.shape != (4,) or cov.shape != (36,):
        raise IntentError('shape', 'fields of the wrong size', f'{pos.size}, {quat.size}, {cov.size}')
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat)) and np.all(np.isfinite(cov))):
        raise IntentError('nonfinite', 'a non-finite value')
    if frame_id not in INTENT_FRAMES:
        raise IntentError('frame', 'not in odom', repr(frame_id)[:40])
    if min(float(cov[0]), float(cov[7]), float(cov[14])) < 0:
        raise IntentError('variance', 'a negative variance', f'{cov[0]:g}, {cov[7]:g}, {cov[14]:g}')
    problem = stamp_age_problem(stamp_s, now_s, max_age_s, tolerance_s)
    if problem is not None:
        raise problem
    t = now_s if stamp_s is None else min(stamp_s, now_s)
    return pos, math.sqrt(max(float(cov[0]), float(cov[7]))), t


@dataclass
class IntentConfig:
    """Timing and wording of the intent line (node parameters map onto these)."""

    timeout_s: float = setting(0.5, gt=0)          # an estimate stamped, or odom / descent_ok received, longer ago
    max_sigma_m: float = setting(0.5, gt=0)        # xy sigma above this: the goal pad is "unsure"
    stamp_tolerance_s: float = setting(0.25, ge=0)  # a stamp this far ahead of the clock is still accepted

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self)


def _distance_words(d: float, positive: str, negative: str) -> str:
    return f'{abs(d):.1f} m {positive if d >= 0 else negative}'


class IntentLine:
    """The assistant's intent as one terminal line: 'goal pad 2.3 m ahead, 0.4 m left, 1.9 m below  descend: ok'.

    Times are the node's clock (`now_s`). The goal part needs an estimate stamped within cfg.timeout_s
    (and odometry received within it, for the body-relative offset); the descent part says ok / hold,
    or '?' once descent_ok has been silent that long. With neither arrived within the timeout the line
    is empty: nothing about intent.
    """

    def __init__(self, cfg: IntentConfig | None = None):
        self.cfg = cfg or IntentConfig()
        self._odom: tuple[float, np.ndarray, float] | None = None     # (arrival, position, heading)
        self._goal: tuple[float, np.ndarray, float] | None = None     # (dated by, position, sigma)
        self._goal_ok = False
        self._descent: tuple[float, bool] | None = None

    def note_odom(self, position: Sequence[float], orientation: Sequence[float], now_s: float) -> bool:
        """The vehicle's pose (odom ENU); False (ignored) when not finite or the quaternion is zero."""
        p, q = np.asarray(position, dtype=float).reshape(-1), np.asarray(orientation, dtype=float).reshape(-1)
        if p.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))) \
                or float(q @ q) < 1e-12:
            return False
        self._odom = (float(now_s), p, heading(q / math.sqrt(float(q @ q))))
        return True

    def note_goal(self, frame_id: str, stamp_s: float | None, position: Sequence[float],
                  orientation: Sequence[float], covariance: Sequence[float], now_s: float) -> None:
        """One /assist/goal_estimate; IntentError when unusable (the goal part then shows '?' until a good one)."""
        try:
            p, sigma, t = check_goal_estimate(frame_id, stamp_s, position, orientation, covariance, now_s,
                                              self.cfg.timeout_s, self.cfg.stamp_tolerance_s)
        except IntentError:
            self._goal_ok = False
            raise
        self._goal, self._goal_ok = (t, p, sigma), True

    def note_descent(self, ok: bool, now_s: float) -> None:
        """One /assist/descent_ok (no header: dated by its arrival at `now_s`)."""
        self._descent = (float(now_s), bool(ok))

    def _fresh(self, t: float, now_s: float) -> bool:
        return -self.cfg.stamp_tolerance_s <= now_s - t <= self.cfg.timeout_s

    def goal_text(self, now_s: float) -> str | None:
        """'goal pad 2.3 m ahead, 0.4 m left, 1.9 m below' (+ ' (unsure)'), 'goal pad ?' when the estimate is
        stale or was rejected, 'goal pad ? (no /odom)' without fresh odometry; None when none arrived in time."""
        g = self._goal
        if g is None or not self._fresh(g[0], now_s):
            return None
        if not self._goal_ok:              # the latest estimate was rejected
            return 'goal pad ?'
        o = self._odom
        if o is None or not self._fresh(o[0], now_s):
            return 'goal pad ? (no /odom)'
        d = enu_to_flu(g[1] - o[1], o[2])
        text = (f"goal pad {_distance_words(d[0], 'ahead', 'behind')}, {_distance_words(d[1], 'left', 'right')}, "
                f"{_distance_words(-d[2], 'below', 'above')}")
        return text + (' (unsure)' if g[2] > self.cfg.max_sigma_m else '')

    def descent_text(self, now_s: float) -> str:
        """'descend: ok', 'descend: hold', or 'descend: ?' when descent_ok has been silent for the timeout."""
        d = self._descent
        if d is None or not self._fresh(d[0], now_s):
            return 'descend: ?'
        return 'descend: ok' if d[1] else 'descend: hold'

    def line(self, now_s: float, width: int | None = None) -> str:
        """The intent line at `now_s`, at most `width - 1` characters when given; '' when no intent arrived within
        the timeout (no goal estimate and no descent_ok)."""
        goal = self.goal_text(now_s)
        d = self._descent
        if goal is None and (d is None or not self._fresh(d[0], now_s)):
            return ''
        text = (goal or 'goal pad ?') + '   ' + self.descent_text(now_s)
        return text if width is None else text[:max(int(width) - 1, 0)]
