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
from typing import Any, Iterable, Sequence

import numpy as np

from assist_bridge.teleop_core import KEY_BINDINGS, TeleopConfig

# Browser KeyboardEvent.code -> teleop token (KEY_BINDINGS) ; 'Space' is the stop key.
BROWSER_KEYS: dict[str, str] = {'KeyW': 'w', 'KeyS': 's', 'KeyA': 'a', 'KeyD': 'd',
                                'ArrowUp': 'UP', 'ArrowDown': 'DOWN'}
STOP_KEY = 'Space'
KNOWN_KEYS = frozenset(BROWSER_KEYS) | {STOP_KEY}
MODES = ('practice', 'study', 'free')
MAX_KEYS_PER_MESSAGE = 16


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


def parse_client_message(raw: str | bytes, max_bytes: int) -> KeysMessage:
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
    if obj.get('type') != 'keys':
        raise MessageError('malformed', f"unknown message type {obj.get('type')!r}")
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

    speed: float = TeleopConfig.speed        # m/s, W/S/A/D (same as teleop_keyboard)
    speed_z: float = TeleopConfig.speed_z    # m/s, arrows
    key_timeout_s: float = 1.0               # held keys not refreshed for this long count as released

    def __post_init__(self) -> None:
        for name in ('speed', 'speed_z', 'key_timeout_s'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be a positive finite number, got {v!r}')


class KeyState:
    """The pilot's held keys (thread-safe: written by the web server, read by the ROS timer)."""

    def __init__(self, cfg: StationConfig | None = None):
        self.cfg = cfg or StationConfig()
        self._lock = threading.Lock()
        self._down: tuple[str, ...] = ()
        self._updated = -math.inf

    def set(self, down: Iterable[str], now: float) -> np.ndarray:
        """Replace the held set (a keys message at time `now`); returns the new command."""
        with self._lock:
            self._down = tuple(k for k in down if k in KNOWN_KEYS)
            self._updated = now
            return command_from_keys(self._down, self.cfg.speed, self.cfg.speed_z)

    def release_all(self) -> None:
        """Every key up (blur, socket drop, pilot change)."""
        with self._lock:
            self._down = ()
            self._updated = -math.inf

    def held(self, now: float) -> tuple[str, ...]:
        """Keys held at `now` (none once the browser has been silent for key_timeout_s)."""
        with self._lock:
            if now - self._updated > self.cfg.key_timeout_s:
                self._down = ()
            return self._down

    def command(self, now: float) -> np.ndarray:
        """Body-FLU velocity (m/s) of the keys held at `now`."""
        return command_from_keys(self.held(now), self.cfg.speed, self.cfg.speed_z)


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


LANDING_FIELDS = ('episode', 'goal_index', 'landed_index', 'nearest_index', 'error_m', 'nearest_error_m',
                  'success', 'crash', 'duration_s', 'assisted', 'outcome')


def parse_landing(text: str) -> dict[str, Any]:
    """The contract's /sim/landing JSON -> dict of its known fields; ValueError when unusable."""
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f'/sim/landing is not JSON: {exc}') from None
    if not isinstance(obj, dict) or 'success' not in obj or 'goal_index' not in obj:
        raise ValueError('/sim/landing lacks success/goal_index')
    out = {k: obj[k] for k in LANDING_FIELDS if k in obj}
    for k in ('error_m', 'nearest_error_m', 'duration_s'):
        v = out.get(k)
        if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v)):
            out[k] = None
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
    """An rgb8/bgr8/mono8 image -> (w, h, RGB bytes), at most `max_width` wide (integer stride); ValueError if bad."""
    channels = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}.get(encoding)
    if channels is None:
        raise ValueError(f'unsupported camera encoding {encoding!r} (rgb8, bgr8, mono8)')
    if width <= 0 or height <= 0 or step < width * channels or len(data) < step * height:
        raise ValueError(f'inconsistent image: {width}x{height} step {step}, {len(data)} bytes')
    img = np.frombuffer(bytes(data), np.uint8)[:step * height].reshape(height, step)[:, :width * channels]
    img = img.reshape(height, width, channels)
    if channels == 1:
        img = np.repeat(img, 3, axis=2)
    elif encoding == 'bgr8':
        img = img[:, :, ::-1]
    k = max(1, math.ceil(width / max_width))
    img = np.ascontiguousarray(img[::k, ::k])
    return img.shape[1], img.shape[0], img.tobytes()


def camera_frame_bytes(width: int, height: int, rgb: bytes) -> bytes:
    """Binary WebSocket frame of a camera image: uint16 LE width, height, then RGB rows."""
    return int(width).to_bytes(2, 'little') + int(height).to_bytes(2, 'little') + rgb
