"""A stand-in for ArduPilot SITL's side of the JSON physics link, for tests and the bench.

Written from the protocol (ArduPilot libraries/SITL/SIM_JSON.{h,cpp} at commit 90700977c553 and
examples/JSON/readme.md), independently of assist_sim.json_backend, so tests check the backend
against the protocol rather than against itself:

* sends `<HHI16H` servo packets (magic 18458, frame_rate, frame_count, pwm[16]) over UDP;
* receives replies the way SIM_JSON::recv_fdm does: every "\\n" becomes NUL and the text between
  the last two NULs is parsed, with SIM_JSON::parse_sensors' strstr + sscanf rules (a key must be
  followed by `":` and the value; vectors `[%f, %f, %f]`), required fields and attitude/quaternion;
* increments frame_count only after a parsed reply and keeps SITL's clock rule
  (time += timestamp - last_timestamp; a timestamp going backwards adds 0).
"""
from __future__ import annotations

import json
import re
import socket
import struct
from dataclasses import dataclass, field

_NUM = r'[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?'
_VEC3 = re.compile(r'\[\s*(' + _NUM + r'),\s*(' + _NUM + r'),\s*(' + _NUM + r')')
_VEC4 = re.compile(r'\[\s*(' + _NUM + r'),\s*(' + _NUM + r'),\s*(' + _NUM + r'),\s*(' + _NUM + r')')
_SCALAR = re.compile(r'\s*(' + _NUM + r')')

# SIM_JSON.h keytable: (section, key, kind, required)
KEYTABLE = (
    ('', 'timestamp', 'double', True),
    ('imu', 'gyro', 'vec3', True),
    ('imu', 'accel_body', 'vec3', True),
    ('', 'position', 'vec3', True),
    ('', 'attitude', 'vec3', False),
    ('', 'quaternion', 'quat', False),
    ('', 'velocity', 'vec3', True),
    ('', 'rng_1', 'double', False),
)


def sitl_parse(text: str) -> dict | None:
    """Parse one reply the way SIM_JSON::parse_sensors does; None when SITL would reject it."""
    out: dict = {}
    for section, key, kind, required in KEYTABLE:
        p = text.find(section) if section else 0          # strstr(json, "") == json
        if p < 0:
            if required:
                return None
            continue
        p += len(section) + 1
        q = text.find(key, p)
        if q < 0:
            if required:
                return None
            continue
        q += len(key) + 2                                  # skip `":`
        rest = text[q:]
        if kind == 'double':
            m = _SCALAR.match(rest)
            if m is None:
                return None
            out[key] = float(m.group(1))
        else:
            m = (_VEC4 if kind == 'quat' else _VEC3).match(rest)
            if m is None:
                return None
            out[key] = [float(x) for x in m.groups()]
    if 'attitude' not in out and 'quaternion' not in out:
        return None
    return out


@dataclass
class SitlStandIn:
    """SITL's end of the JSON link: servo packets out, sensor replies in, SITL's frame and time rules."""

    port: int
    host: str = '127.0.0.1'
    frame_rate: int = 400
    frame_count: int = 0
    time_s: float = 0.0                  # SITL's clock, advanced by the reply timestamps
    last_timestamp: float = 0.0
    buffer: bytearray = field(default_factory=bytearray)
    raw: bytes = b''                     # last datagram received

    def __post_init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(('127.0.0.1', 0))

    def send(self, pwm, frame_count: int | None = None, frame_rate: int | None = None,
             magic: int = 18458) -> None:
        """Send one servo packet (16 channels; missing channels 0)."""
        vals = [int(x) for x in pwm] + [0] * 16
        count = self.frame_count if frame_count is None else frame_count
        rate = self.frame_rate if frame_rate is None else frame_rate
        self.sock.sendto(struct.pack('<HHI16H', magic, rate, count, *vals[:16]), (self.host, self.port))

    def send_raw(self, data: bytes) -> None:
        """Send arbitrary bytes to the backend."""
        self.sock.sendto(data, (self.host, self.port))

    def receive(self, timeout: float = 5.0) -> dict | None:
        """Wait for one reply and parse it as SITL would; None on timeout or rejection."""
        self.sock.settimeout(timeout)
        try:
            data, _ = self.sock.recvfrom(65000)
        except TimeoutError:
            return None
        self.raw = data
        self.buffer += data.replace(b'\n', b'\0')
        p2 = self.buffer.rfind(b'\0')
        if p2 <= 0:
            return None
        p1 = self.buffer.rfind(b'\0', 0, p2)
        if p1 < 0:
            return None
        text = self.buffer[p1 + 1:p2].decode('ascii')
        del self.buffer[:p2]
        parsed = sitl_parse(text)
        if parsed is None:
            return None
        parsed['json'] = json.loads(text)
        ts = parsed['timestamp']
        self.time_s += 0.0 if ts < self.last_timestamp else ts - self.last_timestamp
        self.last_timestamp = ts
        self.frame_count += 1
        return parsed

    def exchange(self, pwm, timeout: float = 5.0, pump=None) -> dict | None:
        """Send the current frame and wait for its reply; `pump()` runs between (single-thread tests)."""
        self.send(pwm)
        if pump is not None:
            pump()
        return self.receive(timeout)

    def restart(self) -> None:
        """SITL restarted: frame_count and clock from zero."""
        self.frame_count = 0
        self.time_s = 0.0
        self.last_timestamp = 0.0
        self.buffer.clear()

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()


__all__ = ['SitlStandIn', 'sitl_parse', 'KEYTABLE']
