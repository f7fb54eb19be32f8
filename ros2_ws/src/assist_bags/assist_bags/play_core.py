"""Pure timing of bag playback: which bag time is due at which wall time (rate, start offset, loop)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PlayClock:
    """Maps bag time (ns) to wall time (s) for one pass: wall = start_wall + (t - first) / rate."""

    first_ns: int          # bag time played at start_wall (bag start + start offset)
    start_wall: float      # monotonic seconds
    rate: float = 1.0

    def due(self, t_ns: int) -> float:
        """Monotonic wall time at which a message recorded at t_ns is published."""
        return self.start_wall + (t_ns - self.first_ns) * 1e-9 / self.rate

    def bag_time(self, wall: float) -> int:
        """Bag time (ns) corresponding to monotonic wall time `wall` (for /clock)."""
        return self.first_ns + int(round((wall - self.start_wall) * self.rate * 1e9))


def parse_remaps(items: list[str]) -> dict[str, str]:
    """['/a:=/b', ...] -> {'/a': '/b'}; ValueError on a malformed item."""
    out = {}
    for item in items:
        if ':=' not in item:
            raise ValueError(f"remap {item!r} is not of the form /from:=/to")
        src, dst = item.split(':=', 1)
        if not src.startswith('/') or not dst.startswith('/') or len(dst) < 2:
            raise ValueError(f"remap {item!r}: both topics must be absolute (start with /)")
        out[src] = dst
    return out
