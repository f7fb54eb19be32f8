"""pymavlink helpers shared by the sim's MAVLink vehicle and the bridge (no rclpy).

- `parse_endpoint` / `open_connection`: only udpin/udpout/tcp/tcpin endpoints and serial devices
  under /dev are accepted, and the pymavlink transport class is picked here, never by
  `mavutil.mavlink_connection`'s guessing (which executes a file whose path contains /bin/ or
  ends in .elf and replays other files as logs).
- `load_signing_key` / `enable_signing`: MAVLink 2 signing from a key file (32 raw bytes or 64
  hex characters; refused when group/world accessible), with the signing timestamp kept on
  the wall clock and a forged frame unable to poison a stream's replay timestamp.
- `next_message`: the next message; on UDP a datagram's leftover partial frame is dropped and
  each datagram's source address can be vetted before parsing (the bridge's address lock).
- `ThrottledLog`: at most one line per key and period, with the count of what it held back.
"""
from __future__ import annotations

import errno
import ipaddress
import logging
import os
import re
import stat
import time
from dataclasses import dataclass
from collections.abc import Callable

os.environ.setdefault('MAVLINK20', '1')
from pymavlink import mavutil

mavlink = mavutil.mavlink

NETWORK_SCHEMES = ('udpin', 'udpout', 'tcp', 'tcpin')
ENDPOINT_FORMS = "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT or a serial device under /dev"
_LABEL = r'[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?'
_HOST_RE = re.compile(rf'(?=.{{1,253}}\Z){_LABEL}(?:\.{_LABEL})*')    # fullmatch: no trailing newline
_DEV_RE = re.compile(r'/dev/[A-Za-z0-9._/+-]+')                   # fullmatch
SIGNING_KEY_BYTES = 32
# MAVLink signing timestamps count 10 us units since 2015-01-01 00:00:00 UTC.
SIGNING_EPOCH_S = 1420070400
# ArduCopter custom_mode numbers (ArduCopter/mode.h).
COPTER_MODES: dict[str, int] = {
    'STABILIZE': 0, 'ACRO': 1, 'ALT_HOLD': 2, 'AUTO': 3, 'GUIDED': 4, 'LOITER': 5, 'RTL': 6,
    'CIRCLE': 7, 'LAND': 9, 'DRIFT': 11, 'SPORT': 13, 'FLIP': 14, 'AUTOTUNE': 15, 'POSHOLD': 16,
    'BRAKE': 17, 'THROW': 18, 'AVOID_ADSB': 19, 'GUIDED_NOGPS': 20, 'SMART_RTL': 21,
}
COPTER_MODE_NAMES: dict[int, str] = {v: k for k, v in COPTER_MODES.items()}
# MAV_CMD_COMPONENT_ARM_DISARM param2 that forces an arm or disarm (ArduPilot's
# magic_force_arm_disarm_value, GCS_Common.cpp).
FORCE_ARM_DISARM_MAGIC = 21196.0


@dataclass(frozen=True)
class Endpoint:
    """A vetted MAVLink endpoint: scheme in NETWORK_SCHEMES or 'serial', host/port or device."""

    scheme: str
    host: str = ''
    port: int = 0
    device: str = ''

    def __str__(self) -> str:
        return self.device if self.scheme == 'serial' else f'{self.scheme}:{self.host}:{self.port}'


def parse_endpoint(url: str) -> Endpoint:
    """Check a connection string; ValueError with one line naming the accepted forms otherwise."""
    if not isinstance(url, str) or not url:
        raise ValueError(f'empty MAVLink endpoint; use {ENDPOINT_FORMS}')
    if url.startswith('/'):
        if not _DEV_RE.fullmatch(url) or '/../' in url + '/' or '/./' in url + '/' or '//' in url:
            raise ValueError(f'serial endpoint {url!r} is not a plain device path under /dev; use {ENDPOINT_FORMS}')
        return Endpoint('serial', device=url)
    scheme, _, rest = url.partition(':')
    if scheme not in NETWORK_SCHEMES or not rest:
        raise ValueError(f'unsupported MAVLink endpoint {url!r}; use {ENDPOINT_FORMS}')
    host, sep, port_s = rest.rpartition(':')
    if not sep or not host or not port_s.isdigit():
        raise ValueError(f'MAVLink endpoint {url!r} needs HOST:PORT; use {ENDPOINT_FORMS}')
    port = int(port_s)
    if not 0 < port < 65536:
        raise ValueError(f'MAVLink endpoint {url!r}: port must be 1-65535')
    try:
        ipaddress.IPv4Address(host)
    except ValueError:
        if not _HOST_RE.fullmatch(host):
            raise ValueError(f'MAVLink endpoint {url!r}: {host!r} is neither an IPv4 address nor a host name') from None
    return Endpoint(scheme, host=host, port=port)


def _check_serial_device(path: str) -> None:
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ValueError(f'serial device {path!r}: {exc.strerror or exc}') from exc
    if not stat.S_ISCHR(st.st_mode):
        raise ValueError(f'{path!r} is not a character device (a serial port); use {ENDPOINT_FORMS}')


def open_connection(url: str, *, baud: int = 57600, source_system: int = 255, source_component: int = 0,
                    autoreconnect: bool = True):
    """Open a vetted endpoint with pymavlink (ardupilotmega dialect, robust parsing); ValueError or OSError."""
    ep = parse_endpoint(url)
    mavutil.set_dialect('ardupilotmega')
    ids = dict(source_system=source_system, source_component=source_component)
    addr = f'{ep.host}:{ep.port}'
    if ep.scheme == 'udpin':
        conn = mavutil.mavudp(addr, input=True, **ids)
    elif ep.scheme == 'udpout':
        conn = mavutil.mavudp(addr, input=False, **ids)
    elif ep.scheme == 'tcp':
        conn = mavutil.mavtcp(addr, autoreconnect=autoreconnect, **ids)
    elif ep.scheme == 'tcpin':
        conn = mavutil.mavtcpin(addr, **ids)
    else:
        _check_serial_device(ep.device)
        conn = mavutil.mavserial(ep.device, baud=baud, autoreconnect=autoreconnect, **ids)
    conn.mav.robust_parsing = True
    return conn


# ---------------------------------------------------------------------- signing
def load_signing_key(path: str) -> bytes:
    """The 32-byte MAVLink 2 signing key in `path` (32 raw bytes, or 64 hex characters and optional newline).

    Refuses a key file that other users can read or write (chmod 600 it), and anything but a regular
    file: the type is checked before opening (a FIFO, socket or device is never opened), and again
    on the descriptor, opened without blocking, in case the path was swapped meanwhile; so a wrong
    path cannot hang start-up. ValueError, one line.
    """
    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f'signing key file {path!r} is not a regular file ({_file_kind(st.st_mode)})')
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise ValueError(f'signing key file {path!r}: {exc.strerror or exc}') from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f'signing key file {path!r} is not a regular file ({_file_kind(st.st_mode)})')
        data = os.read(fd, 1024)
    except OSError as exc:
        raise ValueError(f'signing key file {path!r}: {exc.strerror or exc}') from exc
    finally:
        os.close(fd)
    if st.st_mode & 0o077:
        mode = stat.S_IMODE(st.st_mode)
        raise ValueError(f'signing key file {path!r} is accessible by other users (mode {mode:03o}); '
                         f'run: chmod 600 {path}')
    if len(data) == SIGNING_KEY_BYTES:
        key = data
    else:
        text = data.strip()
        if len(text) != 2 * SIGNING_KEY_BYTES or not re.fullmatch(rb'[0-9A-Fa-f]+', text):
            raise ValueError(f'signing key file {path!r} must hold 32 raw bytes or 64 hex characters '
                             f'(got {len(data)} bytes)')
        key = bytes.fromhex(text.decode('ascii'))
    if key == bytes(SIGNING_KEY_BYTES):
        raise ValueError(f'signing key file {path!r} holds the all-zero key (which means "signing off")')
    return key


def _file_kind(mode: int) -> str:
    """What a non-regular file is, in words."""
    for test, kind in ((stat.S_ISFIFO, 'a FIFO'), (stat.S_ISDIR, 'a directory'), (stat.S_ISSOCK, 'a socket'),
                       (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device')):
        if test(mode):
            return kind
    return 'not a plain file'


def signing_timestamp_now() -> int:
    """Wall-clock MAVLink signing timestamp (10 us units since 2015-01-01)."""
    return int(max(0.0, time.time() - SIGNING_EPOCH_S) * 100_000)


def enable_signing(conn, key: bytes, link_id: int = 0) -> None:
    """Sign everything sent on `conn` and accept only correctly signed MAVLink 2 frames.

    pymavlink records a frame's timestamp as its stream's newest before checking the signature,
    so one forged frame with a far-future timestamp would make every genuine frame of that stream
    "old" from then on; here a failed check restores the stream's previous timestamp.
    """
    if len(key) != SIGNING_KEY_BYTES:
        raise ValueError('signing key must be 32 bytes')
    conn.setup_signing(key, sign_outgoing=True, allow_unsigned_callback=None,
                       initial_timestamp=signing_timestamp_now(), link_id=link_id)
    mav = conn.mav
    original = mav.check_signature
    stamps = mav.signing.stream_timestamps

    def check_signature(msgbuf, src_system, src_component):
        stream = (msgbuf[-13], src_system, src_component)
        had, before = stream in stamps, stamps.get(stream)
        ok = original(msgbuf, src_system, src_component)
        if not ok:
            if had:
                stamps[stream] = before
            else:
                stamps.pop(stream, None)
        return ok

    mav.check_signature = check_signature


def refresh_signing_timestamp(conn) -> None:
    """Move the outgoing signing timestamp up to the wall clock (as ArduPilot does from its RTC).

    pymavlink only adds 1 per frame sent, so a long-running sender would fall further and further
    behind real time, and a peer that (re)starts would reject its stream as more than a minute old.
    """
    signing = conn.mav.signing
    if signing.secret_key is not None:
        signing.timestamp = max(signing.timestamp, signing_timestamp_now())


# ---------------------------------------------------------------------- receiving
def _recv_datagram(conn) -> tuple[bytes, tuple | None]:
    try:
        data, addr = conn.port.recvfrom(mavutil.UDP_MAX_PACKET_LEN)
    except OSError as e:
        if e.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
            return b'', None
        raise
    return data, addr


def next_message(conn, on_truncated: Callable[[], None] | None = None,
                 accept_datagram: Callable[[tuple], bool] | None = None, max_datagrams: int = 64):
    """Next parsed message from `conn` or None; on UDP a datagram's leftover partial frame is dropped.

    MAVLink over UDP carries whole frames per datagram, so bytes left after a datagram are a
    truncated frame; keeping them (as a serial parser must) would swallow the next good frame.
    On UDP, `accept_datagram(address)` (if given) vets each datagram's source before it is parsed
    (a refused one is dropped unparsed) and the caller manages `conn.clients` (where udpin sends);
    without it every sender becomes a client, as in pymavlink. Each message from UDP carries its
    datagram's source as `msg.src_address` (None on streams). At most `max_datagrams` are read per
    call (then None), so a flood of refused datagrams cannot hold the caller's loop.
    """
    if not isinstance(conn, mavutil.mavudp):
        msg = conn.recv_msg()
        if msg is not None:
            msg.src_address = None
        return msg
    mav = conn.mav
    for _ in range(max_datagrams):
        msg = mav.parse_char(b'')
        if msg is not None:
            msg.src_address = getattr(conn, 'assist_rx_address', None)
            return msg
        if mav.buf_len() > 0:
            mav.buf, mav.buf_index, mav.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
            if on_truncated is not None:
                on_truncated()
        data, addr = _recv_datagram(conn)
        if addr is None:
            return None         # nothing pending
        if not data:
            continue            # an empty datagram
        if accept_datagram is not None:
            if not accept_datagram(addr):
                continue
        elif conn.udp_server:
            conn.clients.add(addr)
            conn.clients_last_alive[addr] = time.time()
        conn.assist_rx_address = addr
        msg = mav.parse_char(data)
        if msg is not None:
            msg.src_address = addr
            return msg
    return None


class ThrottledLog:
    """Log at most one line per key every `period_s`; the next line says how many were held back."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0, clock: Callable[[], float] = time.monotonic):
        self._logger = logger
        self._period = float(period_s)
        self._clock = clock
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def log(self, level: int, key: str, message: str, *args) -> bool:
        """Log `message % args` at `level` unless `key` was logged within the period; True if logged."""
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self._period:
            self._held[key] = self._held.get(key, 0) + 1
            return False
        self._last[key] = now
        held = self._held.pop(key, 0)
        if held:
            message += f' ({held} more like this in the last {now - last:.0f} s)'
        self._logger.log(level, message, *args)
        return True
