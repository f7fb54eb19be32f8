"""Which host names the pilot station answers to: the Host / Origin allow-list (no rclpy, no aiohttp).

A page can choose the name it reaches the station by (DNS rebinding points a foreign name at
127.0.0.1), and then its Host and Origin headers agree with each other. So both headers are
checked against a fixed list of (host, port) pairs derived from the address the server binds to
and its port, plus names the operator adds (`allowed_hosts`):

* a loopback bind (127.x.x.x, ::1, localhost): 127.0.0.1, localhost and [::1] on the port;
* a wildcard bind (0.0.0.0, ::): those plus this machine's host name, its fully qualified name and
  the addresses that name resolves to;
* any other address or name: that address or name.

Names compare case-insensitively, IP addresses in canonical form, a missing port is the scheme's
default (80 for http, 443 for https).
"""
from __future__ import annotations

import ipaddress
import re
import socket
from collections.abc import Iterable

LOOPBACK_NAMES = ('127.0.0.1', 'localhost', '::1')
WILDCARD_BINDS = ('', '0.0.0.0', '::')
DEFAULT_PORTS = {'http': 80, 'https': 443}
_HOST_RE = re.compile(r'(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<name>[A-Za-z0-9._-]+))(?::(?P<port>[0-9]{1,5}))?')
_ORIGIN_RE = re.compile(r'(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://(?P<host>[^/?#@\s]+)')   # both: fullmatch

HostPort = tuple[str, int]


def canonical_host(host: str) -> str:
    """A host name lower-cased without a trailing dot, or an IP address in canonical form."""
    host = host.strip().lower().rstrip('.')
    if host.startswith('[') and host.endswith(']'):
        host = host[1:-1]
    try:
        return ipaddress.ip_address(host).compressed
    except ValueError:
        return host


def parse_host(text: str, default_port: int = 80) -> HostPort:
    """A Host header value (``name[:port]``, ``[v6][:port]``) -> (canonical host, port); ValueError if malformed."""
    m = _HOST_RE.fullmatch(text.strip()) if len(text) <= 300 else None
    if m is None:
        raise ValueError('malformed host')
    host = m.group('v6') or m.group('name')
    port = int(m.group('port')) if m.group('port') else default_port
    if not 0 < port <= 65535:
        raise ValueError('port out of range')
    if m.group('v6'):
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError('malformed IPv6 address') from None
    return canonical_host(host), port


def parse_origin(text: str) -> HostPort:
    """An Origin header value (``http://host[:port]``) -> (canonical host, port); ValueError otherwise."""
    m = _ORIGIN_RE.fullmatch(text.strip()) if len(text) <= 300 else None
    if m is None:
        raise ValueError('malformed origin')
    scheme = m.group('scheme').lower()
    if scheme not in DEFAULT_PORTS:
        raise ValueError(f'scheme {scheme!r} is not http or https')
    return parse_host(m.group('host'), DEFAULT_PORTS[scheme])


def _machine_names() -> set[str]:
    names: set[str] = set()
    for name in (socket.gethostname(), socket.getfqdn()):
        if name:
            names.add(name)
            try:
                names.update(info[4][0] for info in socket.getaddrinfo(name, None))
            except OSError:
                pass
    return names


def allowed_hosts(bind_host: str, port: int, extra: Iterable[str] = ()) -> frozenset[HostPort]:
    """The (host, port) pairs a page may use to reach a server bound to `bind_host`:`port`.

    `extra` entries are ``name``, ``name:port`` or ``[v6]:port`` (without a port: `port`);
    ValueError names a malformed entry.
    """
    if not 0 < int(port) <= 65535:
        raise ValueError(f'port {port} is not a bound TCP port')
    bind = canonical_host(bind_host)
    names: set[str] = set()
    if bind in WILDCARD_BINDS:
        names.update(LOOPBACK_NAMES)
        names.update(_machine_names())
    elif bind == 'localhost' or _is_loopback(bind):
        names.update(LOOPBACK_NAMES)
        names.add(bind)
    else:
        names.add(bind)
    out = {(canonical_host(n), int(port)) for n in names}
    for entry in extra:
        try:
            out.add(parse_host(entry, int(port)))
        except ValueError as exc:
            raise ValueError(f'allowed host {entry!r}: {exc}') from None
    return frozenset(out)


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class HostPolicy:
    """Checks Host and Origin header values against the allow-list."""

    def __init__(self, allowed: Iterable[HostPort]):
        self.allowed = frozenset(allowed)

    def host_ok(self, header: str | None) -> bool:
        """Whether a Host header names this station (a missing one does not)."""
        if header is None:
            return False
        try:
            return parse_host(header) in self.allowed
        except ValueError:
            return False

    def origin_ok(self, header: str) -> bool:
        """Whether an Origin header is a page served by this station."""
        try:
            return parse_origin(header) in self.allowed
        except ValueError:
            return False

    def describe(self) -> str:
        """The allow-list as ``host:port`` words, for the start-up log."""
        return ', '.join(f'[{h}]:{p}' if ':' in h else f'{h}:{p}' for h, p in sorted(self.allowed))
