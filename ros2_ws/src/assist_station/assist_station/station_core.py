"""Pilot station core: browser key state -> body-FLU velocity, message parsing, view state. No rclpy.

The browser sends its whole set of held keys (``{"type": "keys", "down": ["KeyW", ...], "seq": n}``)
on every change and as a heartbeat; the station turns it into the pilot's velocity with the same
bindings as ``teleop_keyboard`` (assist_bridge.teleop_core.KEY_BINDINGS): W/S forward/back, A/D
left/right, ArrowUp/ArrowDown climb/descend, Space stop. Keys not refreshed within `key_timeout_s`
count as released, so a page that freezes or a socket that dies quietly never leaves a key stuck.
"""
from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass
from typing import Any
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence

import numpy as np

from assist_common.constants import ACCEPTED_CMD_FRAMES
from assist_common.frames import unit_quat_to_matrix
from assist_common.settings import check_named, setting

from assist_bridge.teleop_core import KEY_BINDINGS, IntentError, TeleopConfig, check_goal_estimate, stamp_age_problem

# Browser KeyboardEvent.code -> teleop token (KEY_BINDINGS) ; 'Space' is the stop key.
BROWSER_KEYS: dict[str, str] = {'KeyW': 'w', 'KeyS': 's', 'KeyA': 'a', 'KeyD': 'd',
                                'ArrowUp': 'UP', 'ArrowDown': 'DOWN'}
STOP_KEY = 'Space'
KNOWN_KEYS = frozenset(BROWSER_KEYS) | {STOP_KEY}
MODES = ('practice', 'study', 'free')
MAX_KEYS_PER_MESSAGE = 16


def short_repr(value: Any, limit: int = 40) -> str:
    """repr() of a value from outside, cut to `limit` characters: safe to log (no raw newlines or escapes)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + '...'


class InputError(ValueError):
    """An unusable input message; `reason` is a fixed phrase (one log line per reason), `detail` the value,
    `kind` a short key naming the reason in counters (e.g. 'nonfinite')."""

    def __init__(self, reason: str, detail: str = '', kind: str = ''):
        super().__init__(reason + (f' ({detail})' if detail else ''))
        self.reason, self.detail, self.kind = reason, detail, kind


class OncePerReason:
    """True the first time a reason is seen (log it), False after; at most `max_reasons` remembered."""

    def __init__(self, max_reasons: int = 256):
        self.max_reasons = max_reasons
        self._seen: set[str] = set()
        self._lock = threading.Lock()

    def __call__(self, reason: str) -> bool:
        with self._lock:
            if reason in self._seen or len(self._seen) >= self.max_reasons:
                return False
            self._seen.add(reason)
            return True


class MessageError(ValueError):
    """A client message that cannot be used (malformed, oversized, wrong fields)."""

    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind = kind  # counter name: 'malformed' or 'oversized'


@dataclass(frozen=True)
class KeysMessage:
    """A parsed keys message: known held keys in press order, unknown names, sequence number."""

    down: tuple[str, ...]
    unknown: tuple[str, ...]
    seq: int | None


STUDY_ACTIONS = ('begin', 'consent', 'start', 'stop_practice', 'sus', 'survey')


@dataclass(frozen=True)
class StudyMessage:
    """A user-study step from the page: `action` (STUDY_ACTIONS) and its data (participant, answers)."""

    action: str
    data: dict[str, Any]


def parse_client_message(raw: str | bytes, max_bytes: int) -> KeysMessage | StudyMessage:
    """Parse one WebSocket text message from the browser; MessageError says why it is unusable."""
    size = len(raw.encode('utf-8') if isinstance(raw, str) else raw)
    if size > max_bytes:
        raise MessageError('oversized', f'message of {size} bytes exceeds the {max_bytes}-byte limit')
    if isinstance(raw, bytes):
        raise MessageError('malformed', 'binary messages are not accepted')
    try:
        obj = json.loads(raw)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise MessageError('malformed', f'not JSON: {exc}') from None
    if not isinstance(obj, dict):
        raise MessageError('malformed', f'expected a JSON object, got {type(obj).__name__}')
    if obj.get('type') == 'study':
        action = obj.get('action')
        if action not in STUDY_ACTIONS:
            raise MessageError('malformed', f'unknown study action {short_repr(action)}')
        return StudyMessage(action, {k: v for k, v in obj.items() if k not in ('type', 'action')})
    if obj.get('type') != 'keys':
        raise MessageError('malformed', f"unknown message type {short_repr(obj.get('type'))}")
    down = obj.get('down')
    if not isinstance(down, list) or not all(isinstance(k, str) for k in down):
        raise MessageError('malformed', "'down' must be a list of key names")
    if len(down) > MAX_KEYS_PER_MESSAGE:
        raise MessageError('malformed', f"'down' lists {len(down)} keys (at most {MAX_KEYS_PER_MESSAGE})")
    seq = obj.get('seq')
    if seq is not None and (isinstance(seq, bool) or not isinstance(seq, int)):
        raise MessageError('malformed', "'seq' must be an integer")
    known, unknown = [], []
    for k in down:
        if k in KNOWN_KEYS:
            if k not in known:
                known.append(k)
        else:
            unknown.append(k[:32])
    return KeysMessage(tuple(known), tuple(unknown), seq)


def command_from_keys(down: Sequence[str], speed: float, speed_z: float) -> np.ndarray:
    """Body-FLU velocity (m/s) of the held browser keys; Space held = stop; last key on an axis wins."""
    v = np.zeros(3)
    if STOP_KEY in down:
        return v
    for code in down:                      # press order: a later key overrides an earlier one on its axis
        token = BROWSER_KEYS.get(code)
        if token is None:
            continue
        axis, sign = KEY_BINDINGS[token]
        v[axis] = sign * (speed_z if axis == 2 else speed)
    return v


@dataclass
class StationConfig:
    """Speeds and timing of the pilot's command (node parameters map onto these)."""

    speed: float = setting(TeleopConfig.speed, gt=0)  # m/s, W/S/A/D (same as teleop_keyboard)
    speed_z: float = setting(TeleopConfig.speed_z, gt=0)  # m/s, arrows
    key_timeout_s: float = setting(1.0, gt=0)  # held keys not refreshed for this long count as released

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self)


class KeyState:
    """The pilot's held keys and the stops held by other pages (thread-safe: web server writes, ROS timer reads).

    Any connected page may stop the vehicle: while one holds a stop (refreshed like keys, within
    `key_timeout_s`) the command is zero whatever the pilot holds, and the keys the pilot held
    through the stop stay ignored until the pilot releases them (a stop never ends in a lurch).
    """

    def __init__(self, cfg: StationConfig | None = None):
        self.cfg = cfg or StationConfig()
        self._lock = threading.Lock()
        self._down: tuple[str, ...] = ()
        self._updated = -math.inf
        self._stops: dict[Hashable, float] = {}
        self._suppressed: set[str] = set()

    def set(self, down: Iterable[str], now: float) -> np.ndarray:
        """Replace the held set (a keys message at time `now`); returns the new command."""
        with self._lock:
            self._down = tuple(k for k in down if k in KNOWN_KEYS)
            self._updated = now
            self._suppressed &= set(self._down)
            return self._command(now)

    def release_all(self) -> None:
        """Every key up (blur, socket drop, pilot change)."""
        with self._lock:
            self._down = ()
            self._updated = -math.inf
            self._suppressed.clear()

    def set_stop(self, source: Hashable, held: bool, now: float) -> np.ndarray:
        """A page other than the pilot's holds (or releases) the stop key at `now`; returns the new command."""
        with self._lock:
            if held:
                self._stops[source] = now
            else:
                self._stops.pop(source, None)
            return self._command(now)

    def stopped(self, now: float) -> bool:
        """Whether some page other than the pilot's holds a stop at `now`."""
        with self._lock:
            return self._stopped(now)

    def held(self, now: float) -> tuple[str, ...]:
        """Keys held at `now` (none once the browser has been silent for key_timeout_s)."""
        with self._lock:
            return self._held(now)

    def command(self, now: float) -> np.ndarray:
        """Body-FLU velocity (m/s) of the keys held at `now` (zero while a stop is held)."""
        with self._lock:
            return self._command(now)

    def _held(self, now: float) -> tuple[str, ...]:
        if now - self._updated > self.cfg.key_timeout_s:
            self._down = ()
            self._suppressed.clear()
        return self._down

    def _stopped(self, now: float) -> bool:
        for source, t in list(self._stops.items()):
            if now - t > self.cfg.key_timeout_s:
                del self._stops[source]
        return bool(self._stops)

    def _command(self, now: float) -> np.ndarray:
        down = self._held(now)
        if self._stopped(now):
            self._suppressed |= set(down)
            return np.zeros(3)
        return command_from_keys([k for k in down if k not in self._suppressed], self.cfg.speed, self.cfg.speed_z)


class CommandGate:
    """Which pilot commands go out at once, between the fixed-rate publishes.

    A command goes out at once only when it differs from the last one sent, and at most `burst`
    at once plus `rate_hz` per second after that (a page that toggles keys hundreds of times a
    second cannot flood the topic; the fixed-rate publish still carries the latest command).
    """

    def __init__(self, rate_hz: float = 50.0, burst: int = 10):
        self.rate_hz, self.burst = float(rate_hz), float(burst)
        self._lock = threading.Lock()
        self._last: np.ndarray | None = None
        self._tokens = float(burst)
        self._t = -math.inf

    def immediate(self, v: np.ndarray, now: float) -> bool:
        """Whether a command from the page should be published now (and record it as sent if so)."""
        v = np.asarray(v, dtype=float)
        with self._lock:
            if self._last is not None and np.array_equal(v, self._last):
                return False
            if math.isfinite(self._t):
                self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate_hz)
            self._t = now
            if self._tokens < 1.0:
                return False
            self._tokens -= 1.0
            self._last = v.copy()
            return True

    def sent(self, v: np.ndarray) -> None:
        """Record a command published by the fixed-rate timer."""
        with self._lock:
            self._last = np.asarray(v, dtype=float).copy()


class AssistMonitor:
    """Whether the assistant is live (/assist/agent_cmd fresh) and acting (|a| above the blend threshold)."""

    def __init__(self, timeout_s: float, threshold: float):
        self.timeout_s, self.threshold = float(timeout_s), float(threshold)
        self._lock = threading.Lock()
        self._last = -math.inf
        self._norm = 0.0

    def note(self, a: Sequence[float], now: float) -> bool:
        """Record one agent command; False (ignored) when it is not a finite 3-vector."""
        arr = np.asarray(a, dtype=float).reshape(-1)
        if arr.shape != (3,) or not np.all(np.isfinite(arr)):
            return False
        with self._lock:
            self._last, self._norm = now, float(np.linalg.norm(arr))
        return True

    def state(self, now: float) -> str:
        """'off' (no fresh agent command), 'standby' (live, |a| <= threshold: V = u) or 'acting'."""
        with self._lock:
            if now - self._last > self.timeout_s:
                return 'off'
            return 'acting' if self._norm > self.threshold else 'standby'


# ------------------------------------------------------------------ the assistant's intent cues
CUES = ('goal', 'descent', 'push')     # the page's three cues, each switched by a station parameter cue_<name>
PUSH_MIN_MPS = 0.02                    # a push below this norm is sent as none (V = u)


@dataclass
class CueConfig:
    """Validation and timing of the assistant's intent cues (node parameters map onto these)."""

    timeout_s: float = setting(0.5, gt=0)           # older estimate / blended command, silent descent_ok: unknown
    max_sigma_m: float = setting(0.5, gt=0)         # sqrt(max(var_x, var_y)) above this: the goal cue is unsure
    pad_tolerance_m: float = setting(0.8, gt=0)     # farther than this from every pad top centre: unknown pad
    stamp_tolerance_s: float = setting(0.25, ge=0)  # a stamp this far ahead of the clock is still accepted

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self)


@dataclass(frozen=True)
class GoalEstimate:
    """A validated /assist/goal_estimate: position (odom), xy sigma, matched pad id, clock time it is dated by."""

    p: tuple[float, float, float]
    sigma_m: float
    pad: int | None
    t: float


def pad_top_centres(platforms: Iterable[dict[str, Any]]) -> list[tuple[int, np.ndarray]]:
    """(pad id, centre of its top surface in odom) of each platform box of the page's scene (scene_from_boxes)."""
    out = []
    for b in platforms:
        up = unit_quat_to_matrix(b['q']) @ np.array([0.0, 0.0, float(b['s'][2]) / 2.0])
        out.append((int(b['id']), np.asarray(b['p'], dtype=float) + up))
    return out


def match_pad(p: Sequence[float], pads: Sequence[tuple[int, np.ndarray]], tolerance_m: float) -> int | None:
    """Id of the pad whose top centre is nearest `p` (horizontally) among those within `tolerance_m` of it
    horizontally and vertically; None when there is none."""
    best, best_d = None, math.inf
    for pad_id, top in pads:
        d = math.hypot(float(p[0]) - top[0], float(p[1]) - top[1])
        if d <= tolerance_m and abs(float(p[2]) - top[2]) <= tolerance_m and d < best_d:
            best, best_d = pad_id, d
    return best


def parse_goal_estimate(frame_id: str, stamp_s: float | None, position: Sequence[float],
                        orientation: Sequence[float], covariance: Sequence[float], now_s: float,
                        pads: Sequence[tuple[int, np.ndarray]] | None, cfg: CueConfig) -> GoalEstimate:
    """A /assist/goal_estimate (PoseWithCovarianceStamped fields) -> GoalEstimate; InputError (its `kind`:
    nonfinite, frame, variance, future_stamp, stale_stamp, unknown_pad) when it must not be drawn.

    The stamp is judged against `now_s` (the node's clock: sim time under use_sim_time); an unset stamp
    (None) is dated by the arrival. With `pads` (the current scene's pad top centres) the position must
    lie within cfg.pad_tolerance_m of one of them; without a scene any position is accepted.
    """
    try:        # the rules teleop_keyboard applies too (assist_bridge.teleop_core)
        pos, sigma, t = check_goal_estimate(frame_id, stamp_s, position, orientation, covariance, now_s,
                                            cfg.timeout_s, cfg.stamp_tolerance_s)
    except IntentError as exc:
        raise InputError(f'/assist/goal_estimate: {exc.reason}', exc.detail, kind=exc.kind) from None
    pad = None
    if pads:
        pad = match_pad(pos, pads, cfg.pad_tolerance_m)
        if pad is None:
            raise InputError('/assist/goal_estimate is not on any pad of the scene',
                             short_repr([round(float(x), 2) for x in pos], 80), kind='unknown_pad')
    return GoalEstimate((float(pos[0]), float(pos[1]), float(pos[2])), sigma, pad, t)


def parse_blended(frame_id: str, stamp_s: float | None, v: Sequence[float], now_s: float,
                  cfg: CueConfig) -> tuple[float, np.ndarray]:
    """A /cmd_vel (the blended V) -> (clock time it is dated by, body-FLU velocity); InputError (kind nonfinite,
    frame, future_stamp, stale_stamp) when it cannot give the assistant's push."""
    arr = np.asarray(v, dtype=float).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise InputError('/cmd_vel is not a finite 3-vector', kind='nonfinite')
    if frame_id not in ACCEPTED_CMD_FRAMES:
        raise InputError('/cmd_vel is not in base_link', short_repr(frame_id), kind='frame')
    stale = stamp_age_problem(stamp_s, now_s, cfg.timeout_s, cfg.stamp_tolerance_s)
    if stale is not None:
        raise InputError(f'/cmd_vel: {stale.reason}', stale.detail, kind=stale.kind)
    return (now_s if stamp_s is None else min(stamp_s, now_s)), arr


class IntentCues:
    """What the page shows of the assistant's intent: the goal pad it believes in, the descent light, its push.

    Inputs are noted with the node's clock (`now_s`, sim-aware) and validated here; `view` decides what
    the page may draw: nothing at all while assistance is off, nothing of a cue that is switched off, a
    goal cue 'unknown' (grey) once its estimate is older than cfg.timeout_s or the latest one was
    rejected, the descent light 'unknown' once descent_ok has been silent that long. A cue going grey
    is counted (`cue_goal_unknown`, `cue_descent_unknown`) through `count`. Thread-safe.
    """

    def __init__(self, cfg: CueConfig | None = None, count: Callable[[str], None] | None = None):
        self.cfg = cfg or CueConfig()
        self._count = count or (lambda key: None)
        self._lock = threading.Lock()
        self._pads: list[tuple[int, np.ndarray]] | None = None
        self._goal: GoalEstimate | None = None
        self._goal_valid = False
        self._descent: tuple[float, bool] | None = None
        self._blended: tuple[float, np.ndarray] | None = None
        self._pilot = np.zeros(3)
        self._shown: dict[str, str | None] = {'goal': None, 'descent': None}

    def set_scene(self, platforms: Iterable[dict[str, Any]]) -> None:
        """A new scene: its pads validate the estimates from now on; the estimate of the old scene is forgotten."""
        pads = pad_top_centres(platforms)
        with self._lock:
            self._pads = pads or None
            self._goal, self._goal_valid = None, False

    def note_goal(self, frame_id: str, stamp_s: float | None, position: Sequence[float],
                  orientation: Sequence[float], covariance: Sequence[float], now_s: float) -> GoalEstimate:
        """One /assist/goal_estimate; InputError when unusable (the cue then shows 'unknown' until a good one)."""
        with self._lock:
            pads = self._pads
        try:
            est = parse_goal_estimate(frame_id, stamp_s, position, orientation, covariance, now_s, pads, self.cfg)
        except InputError:
            with self._lock:
                self._goal_valid = False
            raise
        with self._lock:
            self._goal, self._goal_valid = est, True
        return est

    def note_descent(self, ok: bool, now_s: float) -> None:
        """One /assist/descent_ok (no header: dated by its arrival at `now_s`)."""
        with self._lock:
            self._descent = (float(now_s), bool(ok))

    def note_blended(self, frame_id: str, stamp_s: float | None, v: Sequence[float], now_s: float) -> None:
        """One /cmd_vel (the blended V that flies); InputError when unusable (the push then shows nothing)."""
        try:
            dated = parse_blended(frame_id, stamp_s, v, now_s, self.cfg)
        except InputError:
            with self._lock:
                self._blended = None
            raise
        with self._lock:
            self._blended = dated

    def note_pilot(self, u: Sequence[float]) -> None:
        """The pilot command u the station published last (body FLU, m/s)."""
        arr = np.asarray(u, dtype=float).reshape(-1)
        if arr.shape == (3,) and np.all(np.isfinite(arr)):
            with self._lock:
                self._pilot = arr.copy()

    def _fresh(self, t: float, now_s: float) -> bool:
        return -self.cfg.stamp_tolerance_s <= now_s - t <= self.cfg.timeout_s

    def view(self, now_s: float, assist_live: bool, show: Mapping[str, bool]) -> dict[str, Any]:
        """The cues for the page at `now_s`: {'goal': None | {state sure/unsure/unknown, p, pad, sigma_m},
        'descent': None | 'ok' / 'hold' / 'unknown', 'push': None | V - u (body FLU, m/s)}; all None while
        assistance is off (`assist_live` False), a cue None while `show[name]` is False."""
        out: dict[str, Any] = {'goal': None, 'descent': None, 'push': None}
        with self._lock:
            if assist_live:
                goal = self._goal
                if show.get('goal') and goal is not None:
                    if not (self._goal_valid and self._fresh(goal.t, now_s)):
                        state = 'unknown'
                    else:
                        state = 'unsure' if goal.sigma_m > self.cfg.max_sigma_m else 'sure'
                    out['goal'] = {'state': state, 'p': [round(x, 3) for x in goal.p], 'pad': goal.pad,
                                   'sigma_m': round(goal.sigma_m, 3)}
                if show.get('descent'):
                    d = self._descent
                    out['descent'] = ('unknown' if d is None or not self._fresh(d[0], now_s)
                                      else ('ok' if d[1] else 'hold'))
                b = self._blended
                if show.get('push') and b is not None and self._fresh(b[0], now_s):
                    push = b[1] - self._pilot
                    if float(np.linalg.norm(push)) >= PUSH_MIN_MPS:
                        out['push'] = [round(float(x), 3) for x in push]
            states = {'goal': out['goal'] and out['goal']['state'], 'descent': out['descent']}
            went_grey = [k for k, s in states.items() if s == 'unknown' and self._shown[k] not in (None, 'unknown')]
            self._shown = states
        for k in went_grey:
            self._count(f'cue_{k}_unknown')
        return out


LANDING_FIELDS = ('episode', 'goal_index', 'landed_index', 'nearest_index', 'error_m', 'nearest_error_m',
                  'success', 'crash', 'duration_s', 'assisted', 'outcome')
MAX_LANDING_CHARS = 16384
_LANDING_INDICES = ('goal_index', 'landed_index', 'nearest_index')   # pad indices: int >= 0 (goal) or null
_LANDING_FLOATS = ('error_m', 'nearest_error_m', 'duration_s')
_LANDING_BOOLS = ('success', 'crash', 'assisted')


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def parse_landing(text: str) -> dict[str, Any]:
    """The contract's /sim/landing JSON -> dict of its known fields, types checked; InputError when unusable.

    Pad indices are integers >= 0 (`landed_index`, `nearest_index` may be null), `success`, `crash`
    and `assisted` booleans, `episode` an integer; a distance or duration that is not a finite
    number becomes null, an `outcome` that is not a short string is dropped.
    """
    if len(text) > MAX_LANDING_CHARS:
        raise InputError('/sim/landing message too long', f'{len(text)} characters')
    try:
        obj = json.loads(text)
    except (json.JSONDecodeError, RecursionError):
        raise InputError('/sim/landing is not JSON') from None
    if not isinstance(obj, dict) or 'success' not in obj or 'goal_index' not in obj:
        raise InputError('/sim/landing lacks success/goal_index')
    out = {k: obj[k] for k in LANDING_FIELDS if k in obj}
    for k in _LANDING_INDICES:
        v = out.get(k)
        if (v is None and k != 'goal_index') or (_is_int(v) and 0 <= v < 1_000_000):
            continue
        raise InputError(f'/sim/landing {k} is not a pad index', short_repr(v))
    for k in _LANDING_BOOLS:
        if k in out and not isinstance(out[k], bool):
            raise InputError(f'/sim/landing {k} is not true/false', short_repr(out[k]))
    if 'episode' in out and out['episode'] is not None and not _is_int(out['episode']):
        raise InputError('/sim/landing episode is not an integer', short_repr(out['episode']))
    for k in _LANDING_FLOATS:
        v = out.get(k)
        if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)):
            out[k] = None
    if 'outcome' in out and not (isinstance(out['outcome'], str) and len(out['outcome']) <= 32):
        del out['outcome']
    return out


def landing_feedback(landing: dict[str, Any], mode: str) -> dict[str, Any]:
    """What the page shows after a landing: the result in practice/free mode, only 'recorded' in study mode."""
    if mode == 'study':  # the paper's study: no feedback about performance
        return {'type': 'landing', 'show': False, 'episode': landing.get('episode'), 'text': 'Landing recorded'}
    if landing.get('success'):
        head = 'Landed on the goal platform'
    elif landing.get('crash'):
        head = 'Crashed'
    elif landing.get('landed_index') is not None:
        head = f"Landed on platform {int(landing['landed_index']) + 1}, goal was {int(landing['goal_index']) + 1}"
    else:
        head = 'Landing missed'
    err = landing.get('error_m')
    text = head + (f' - {err:.2f} m from the goal centre' if isinstance(err, (int, float)) else '')
    return {'type': 'landing', 'show': True, 'episode': landing.get('episode'), 'text': text,
            'success': bool(landing.get('success')), 'crash': bool(landing.get('crash')), 'error_m': err}


MAX_BOXES = 64


def scene_from_boxes(boxes: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """Validated platform boxes ({ns, id, p, q, s, c}) -> the page's scene: platforms + goal index."""
    platforms, goal = [], None
    for b in boxes:
        vals = list(b['p']) + list(b['q']) + list(b['s']) + list(b['c'])
        if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in vals) or min(b['s']) <= 0:
            raise ValueError(f"box {b.get('ns')}/{b.get('id')} has a non-finite or non-positive field")
        if b['ns'] == 'platforms':
            platforms.append({'id': int(b['id']), 'p': [float(x) for x in b['p']], 'q': [float(x) for x in b['q']],
                              's': [float(x) for x in b['s']], 'c': [float(x) for x in b['c'][:3]]})
        elif b['ns'] == 'goal':
            goal = int(b['id'])
        if len(platforms) > MAX_BOXES:
            raise ValueError(f'more than {MAX_BOXES} platforms')
    platforms.sort(key=lambda x: x['id'])
    if goal is not None and goal not in {p['id'] for p in platforms}:
        goal = None
    return {'type': 'scene', 'platforms': platforms, 'goal': goal}


def camera_payload(width: int, height: int, encoding: str, step: int, data: bytes,
                   max_width: int) -> tuple[int, int, bytes]:
    """An rgb8/bgr8/mono8 image -> (w, h, RGB bytes), subsampled (integer stride) to at most `max_width` pixels
    on either side (a tall image too); InputError if unusable."""
    channels = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}.get(encoding)
    if channels is None:
        raise InputError('unsupported camera encoding (rgb8, bgr8, mono8)', short_repr(encoding))
    if width <= 0 or height <= 0 or step < width * channels or len(data) < step * height:
        raise InputError('inconsistent image size', f'{width}x{height} step {step}, {len(data)} bytes')
    img = np.frombuffer(bytes(data), np.uint8)[:step * height].reshape(height, step)[:, :width * channels]
    img = img.reshape(height, width, channels)
    if channels == 1:
        img = np.repeat(img, 3, axis=2)
    elif encoding == 'bgr8':
        img = img[:, :, ::-1]
    k = max(1, math.ceil(width / max_width), math.ceil(height / max_width))
    img = np.ascontiguousarray(img[::k, ::k])
    return img.shape[1], img.shape[0], img.tobytes()


MAX_FRAME_SIDE = 65535


def camera_frame_bytes(width: int, height: int, rgb: bytes) -> bytes:
    """Binary WebSocket frame of a camera image: uint16 LE width, height, then RGB rows; InputError if it cannot be."""
    if not (0 < width <= MAX_FRAME_SIDE and 0 < height <= MAX_FRAME_SIDE) or len(rgb) != width * height * 3:
        raise InputError('camera frame does not fit the inset format', f'{width}x{height}, {len(rgb)} bytes')
    return int(width).to_bytes(2, 'little') + int(height).to_bytes(2, 'little') + rgb
