"""Keyboard teleop core: terminal bytes -> key tokens -> held keys -> body-FLU velocity. No rclpy.

The paper's scheme: W/S forward/back, A/D left/right, arrow up/down climb/descend, space stops,
q quits. Terminals report key presses only (no key-up), and a held key repeats after an initial
delay. So a key counts as held for `initial_hold_s` after its first event (longer than the
terminal's auto-repeat delay) and, once it repeats, until its repeats stop for `repeat_timeout_s`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

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
