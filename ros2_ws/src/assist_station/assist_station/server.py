"""HTTP + WebSocket server of the pilot station (aiohttp, its own asyncio thread; no rclpy).

One page (``/`` and ``/static/*``, every asset served from the package: the station works offline)
and one WebSocket (``/ws``). Every request must name the station in its Host header (an allow-list
derived from the bind address and port, see access.py), and a WebSocket's Origin must be one of
those too; a connection without an Origin (not a browser page) is view only. The first page to
connect is the pilot and gets a session token; when its socket drops, the pilot role waits
`pilot_grace_s` for the page to reconnect with that token (``/ws?session=TOKEN``), and every other
page is view only. Any connected page may hold the stop key (Space): the command is zero while it
does. At most `max_connections` WebSockets are open at once (the pilot's reconnect always gets in).
Outgoing data is latest-value only (state, camera) or a short bounded queue (events), so a client
that never reads loses frames (counted) instead of growing memory or blocking anything; one whose
send stalls for `stall_timeout_s` is disconnected. When the pilot's socket goes away (closed,
dropped, stalled, oversized message) every key is released and a zero command goes out at once.
"""
from __future__ import annotations

import asyncio
import hmac
import json
import logging
import math
import secrets
import threading
import time
from collections import Counter, deque
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np
from aiohttp import WSCloseCode, WSMsgType, web

from .access import HostPolicy, allowed_hosts
from .station_core import (STOP_KEY, KeyState, MessageError, StudyMessage, camera_frame_bytes, parse_client_message,
                           short_repr)

_LOG = logging.getLogger('assist_station.server')
WEB_DIR = Path(__file__).resolve().parent / 'web'
CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
       "connect-src 'self'; frame-ancestors 'none'")


@dataclass
class ServerConfig:
    """Address, limits and rates of the web server (node parameters map onto these)."""

    host: str = '127.0.0.1'
    port: int = 8080                      # 0: any free port (see StationServer.url)
    max_message_bytes: int = 1024         # larger client messages are rejected (connection kept)
    hard_max_message_bytes: int = 65536   # larger frames close the connection (aiohttp's limit)
    view_rate_hz: float = 30.0            # state pushes to each page
    stall_timeout_s: float = 5.0          # a send blocked this long disconnects the client
    max_events: int = 32                  # queued events per client (acks, landings, errors)
    allowed_hosts: tuple[str, ...] = ()   # more names the page may be reached by ('name', 'name:port')
    max_connections: int = 16             # open WebSockets at most (the pilot's reconnect is always let in)
    pilot_grace_s: float = 10.0           # the pilot role waits this long for its page to reconnect


class _Client:
    """One connected page: its socket, role and what is waiting to be sent to it."""

    def __init__(self, ws: web.WebSocketResponse, request: web.Request, role: str, max_events: int):
        self.ws, self.request, self.role = ws, request, role
        self.wake = asyncio.Event()
        self.events: deque[str] = deque()
        self.max_events = max_events
        self.state: str | None = None
        self.camera: bytes | None = None
        self.scene_version = -1
        self.study_version = 0
        self.peer = request.remote or '?'
        self.stopping = False             # a view-only page holding the stop key


class _Throttle:
    """At most one log line per key per `period_s`."""

    def __init__(self, period_s: float = 2.0):
        self.period_s, self._last = period_s, {}

    def __call__(self, key: str) -> bool:
        now = time.monotonic()
        if now - self._last.get(key, -1e9) >= self.period_s:
            self._last[key] = now
            return True
        return False


class StationServer:
    """The station's web server; feed it state with the set_* methods from any thread."""

    def __init__(self, cfg: ServerConfig, keys: KeyState, state_fn: Callable[[], dict[str, Any]],
                 hello: dict[str, Any], on_command: Callable[[np.ndarray], None] | None = None,
                 count: Callable[[str], None] | None = None, web_dir: Path = WEB_DIR,
                 on_study: Callable[[StudyMessage], None] | None = None,
                 on_pilot_lost: Callable[[], None] | None = None):
        self.cfg, self.keys, self._state_fn, self._hello = cfg, keys, state_fn, dict(hello)
        self._on_command = on_command or (lambda v: None)
        self._on_study = on_study
        self._on_pilot_lost = on_pilot_lost or (lambda: None)
        self._sink = count
        self.stats: Counter[str] = Counter()
        self._web_dir = web_dir
        self._clients: set[_Client] = set()
        self._pilot: _Client | None = None
        self._session: str | None = None          # the pilot page's token
        self._reserved_until = -math.inf          # the pilot role waits for its page until then
        self._n_ws = 0                            # WebSockets open or opening
        self._policy: HostPolicy | None = None
        self._lock = threading.Lock()
        self._scene: str | None = None
        self._scene_version = 0
        self._camera: bytes | None = None
        self._camera_version = 0
        self._study: str | None = None
        self._study_version = 0
        self._pending_events: list[str] = []
        self._throttle = _Throttle()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._tasks: list[asyncio.Task] = []
        self.port: int | None = None

    # ------------------------------------------------------------------ feed (any thread)
    def set_scene(self, scene: dict[str, Any]) -> None:
        """Latest scene (sent to every page, never dropped: a newer one replaces it)."""
        with self._lock:
            self._scene = json.dumps(scene)
            self._scene_version += 1

    def set_study(self, view: dict[str, Any] | None) -> None:
        """Latest user-study view (sent to every page, a newer one replaces it; None: no study)."""
        with self._lock:
            self._study = None if view is None else json.dumps(view)
            self._study_version += 1

    def set_camera(self, width: int, height: int, rgb: bytes) -> None:
        """Latest camera inset frame (RGB bytes)."""
        with self._lock:
            self._camera = camera_frame_bytes(width, height, rgb)
            self._camera_version += 1

    def push_event(self, event: dict[str, Any]) -> None:
        """An event for every page (e.g. a landing result)."""
        with self._lock:
            self._pending_events.append(json.dumps(event))

    @property
    def pilot_connected(self) -> bool:
        """Whether a pilot page is connected now."""
        return self._pilot is not None

    @property
    def n_clients(self) -> int:
        """Connected pages (pilot and spectators)."""
        return len(self._clients)

    @property
    def policy(self) -> HostPolicy:
        """The Host/Origin allow-list (derived from host, port and allowed_hosts once the port is bound)."""
        if self._policy is None:
            self._policy = HostPolicy(allowed_hosts(self.cfg.host, self.port or self.cfg.port, self.cfg.allowed_hosts))
        return self._policy

    @property
    def url(self) -> str:
        """http://HOST:PORT/ of the running server (127.0.0.1 for a wildcard bind)."""
        host = {'': '127.0.0.1', '0.0.0.0': '127.0.0.1', '::': '::1'}.get(self.cfg.host, self.cfg.host)
        host = host if ':' not in host else f'[{host}]'
        return f'http://{host}:{self.port}/'

    def _count(self, key: str, n: int = 1) -> None:
        self.stats[key] += n
        if self._sink is not None:
            for _ in range(n):
                self._sink(key)

    # ------------------------------------------------------------------ app
    def make_app(self) -> web.Application:
        """The aiohttp application (also used directly by tests with aiohttp's test client)."""
        app = web.Application(middlewares=[self._headers])
        app.router.add_get('/', self._index)
        app.router.add_get('/ws', self._ws_handler)
        app.router.add_static('/static/', self._web_dir, follow_symlinks=False)
        app.on_startup.append(self._on_startup)
        app.on_shutdown.append(self._on_shutdown)
        return app

    @web.middleware
    async def _headers(self, request: web.Request, handler):
        host = request.headers.get('Host')
        if not self.policy.host_ok(host):
            self._count('http_host_rejected')
            if self._throttle('host'):
                _LOG.warning('request for host %s from %s refused (allowed: %s)', short_repr(host),
                             request.remote, self.policy.describe())
            resp = web.Response(status=403, text='unknown host')
        else:
            resp = await handler(request)
        resp.headers.setdefault('Content-Security-Policy', CSP)
        resp.headers.setdefault('Cache-Control', 'no-store')
        resp.headers.setdefault('X-Content-Type-Options', 'nosniff')
        return resp

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(self._web_dir / 'index.html')

    async def _on_startup(self, app: web.Application) -> None:
        self._tasks.append(asyncio.get_running_loop().create_task(self._broadcast_loop()))

    async def _on_shutdown(self, app: web.Application) -> None:
        for t in self._tasks:
            t.cancel()
        for c in list(self._clients):
            await self._abort(c)

    # ------------------------------------------------------------------ websocket
    def _claims_pilot(self, request: web.Request, now: float) -> bool:
        """Whether the request carries the pilot's session token while that session holds or awaits the role."""
        token = request.query.get('session', '')
        if not token or self._session is None or request.headers.get('Origin') is None:
            return False
        if self._pilot is None and now > self._reserved_until:
            return False
        return hmac.compare_digest(token.encode(), self._session.encode())

    def _role(self, request: web.Request, now: float) -> tuple[str, str | None]:
        """('pilot', None) or ('spectator', why) for a new connection."""
        if request.headers.get('Origin') is None:
            return 'spectator', 'no Origin header (not a browser page): view only'
        if self._claims_pilot(request, now):
            return 'pilot', None
        if self._pilot is not None:
            return 'spectator', 'another pilot is connected: this page is view only (Space stops the vehicle)'
        if now <= self._reserved_until:
            return 'spectator', 'the pilot is reconnecting: this page is view only (Space stops the vehicle)'
        return 'pilot', None

    async def _ws_handler(self, request: web.Request) -> web.StreamResponse:
        origin = request.headers.get('Origin')
        if origin is not None and not self.policy.origin_ok(origin):
            self._count('ws_origin_rejected')
            if self._throttle('origin'):
                _LOG.warning('WebSocket from foreign origin %s refused', short_repr(origin, 100))
            return web.Response(status=403, text='foreign origin')
        if self._n_ws >= self.cfg.max_connections and not self._claims_pilot(request, time.monotonic()):
            self._count('ws_connections_refused')
            if self._throttle('capacity'):
                _LOG.warning('WebSocket from %s refused: %d connections open (max_connections)',
                             request.remote, self._n_ws)
            return web.Response(status=503, text='too many connections')
        self._n_ws += 1
        try:
            return await self._serve_ws(request)
        finally:
            self._n_ws -= 1

    async def _serve_ws(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(max_msg_size=self.cfg.hard_max_message_bytes, compress=False)
        await ws.prepare(request)
        now = time.monotonic()
        role, reason = self._role(request, now)      # decided here: nothing awaited until the role is taken
        client = _Client(ws, request, role, self.cfg.max_events)
        self._clients.add(client)
        hello = dict(self._hello, type='hello', role=role)
        if role == 'pilot':
            previous = self._pilot
            reclaim = self._claims_pilot(request, now)
            if not reclaim:
                self._session = secrets.token_urlsafe(24)
            self._pilot = client
            self._reserved_until = -math.inf
            self.keys.release_all()
            hello['session'] = self._session
            if reclaim:
                self._count('pilot_reclaims')
                _LOG.info('pilot reconnected from %s', client.peer)
            else:
                self._count('pilot_connects')
                _LOG.info('pilot connected from %s', client.peer)
            if previous is not None:               # the same session from a new socket: the old one is demoted
                previous.role = 'spectator'
                self._on_pilot_lost()              # the pilot's page changed (e.g. reloaded) under it
                self._enqueue(previous, json.dumps(dict(self._hello, type='hello', role='spectator',
                                                        reason='the pilot role moved to another page')))
        else:
            no_origin = request.headers.get('Origin') is None
            self._count('ws_no_origin' if no_origin else 'second_browser_refused')
            hello['reason'] = reason
            if self._throttle('no_origin' if no_origin else 'spectator'):
                _LOG.warning('page from %s is view only: %s', client.peer, reason)
        self._enqueue(client, json.dumps(hello))
        writer = asyncio.get_running_loop().create_task(self._writer(client))
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    self._on_text(client, msg.data)
                elif msg.type == WSMsgType.BINARY:
                    self._reject(client, 'malformed', 'binary messages are not accepted')
                elif msg.type == WSMsgType.ERROR:
                    exc = ws.exception()
                    if getattr(exc, 'code', None) == WSCloseCode.MESSAGE_TOO_BIG:
                        self._count('ws_oversized_closed')
                    else:
                        self._count('ws_errors')
                    _LOG.warning('WebSocket error from %s, connection closed: %s', client.peer, exc)
        finally:
            writer.cancel()
            self._disconnect(client, 'socket closed')
        return ws

    def _disconnect(self, client: _Client, why: str) -> None:
        if client not in self._clients:
            return
        self._clients.discard(client)
        if client.stopping:
            client.stopping = False
            self._on_command(self.keys.set_stop(client, False, time.monotonic()))
        if self._pilot is client:
            self._pilot = None
            self._reserved_until = time.monotonic() + self.cfg.pilot_grace_s
            self.keys.release_all()
            self._on_command(np.zeros(3))
            self._on_pilot_lost()
            self._count('pilot_disconnects')
            _LOG.info('pilot %s disconnected (%s): all keys released, zero command; the role waits %.1f s '
                      'for its page', client.peer, why, self.cfg.pilot_grace_s)

    def _reject(self, client: _Client, kind: str, reason: str) -> None:
        self._count(f'ws_{kind}')
        if self._throttle(kind):
            _LOG.warning('rejected message from %s (%s): %s', client.peer, kind, reason)
        self._enqueue(client, json.dumps({'type': 'error', 'kind': kind, 'message': reason}))

    def _on_text(self, client: _Client, data: str) -> None:
        try:
            msg = parse_client_message(data, self.cfg.max_message_bytes)
        except MessageError as exc:
            self._reject(client, exc.kind, str(exc))
            return
        if isinstance(msg, StudyMessage):
            if client is not self._pilot:
                self._reject(client, 'study_not_pilot', 'study steps are taken from the pilot page only')
            elif self._on_study is None:
                self._reject(client, 'no_study', 'no study is configured on this station')
            else:
                self._count('study_messages')
                self._on_study(msg)
            return
        if msg.unknown:
            self._count('ws_unknown_keys', len(msg.unknown))
            if self._throttle('unknown'):
                _LOG.warning('unknown keys from %s ignored: %s', client.peer,
                             ', '.join(short_repr(k) for k in msg.unknown))
        now = time.monotonic()
        if client is not self._pilot:
            stop = STOP_KEY in msg.down
            if stop or client.stopping:
                if stop and not client.stopping:
                    self._count('spectator_stops')
                    _LOG.warning('view-only page %s holds the stop key: zero command', client.peer)
                client.stopping = stop
                self._on_command(self.keys.set_stop(client, stop, now))
            if any(k != STOP_KEY for k in msg.down):
                self._count('spectator_keys')
                if self._throttle('spectator_keys'):
                    _LOG.warning('keys from view-only page %s ignored (only Space, stop, is taken)', client.peer)
        else:
            self._on_command(self.keys.set(msg.down, now))
        if msg.seq is not None:
            self._enqueue(client, json.dumps({'type': 'ack', 'seq': msg.seq}))

    def _enqueue(self, client: _Client, text: str) -> None:
        if len(client.events) >= client.max_events:
            client.events.popleft()
            self._count('events_dropped')
        client.events.append(text)
        client.wake.set()

    async def _writer(self, client: _Client) -> None:
        """Send what is waiting for one client; a send stalled past stall_timeout_s drops it."""
        ws = client.ws
        while not ws.closed:
            await client.wake.wait()
            client.wake.clear()
            out: list[str | bytes] = []
            with self._lock:
                if self._scene is not None and client.scene_version != self._scene_version:
                    out.append(self._scene)
                    client.scene_version = self._scene_version
                if self._study is not None and client.study_version != self._study_version:
                    out.append(self._study)
                    client.study_version = self._study_version
            while client.events:
                out.append(client.events.popleft())
            if client.state is not None:
                out.append(client.state)
                client.state = None
            if client.camera is not None:
                out.append(client.camera)
                client.camera = None
            for item in out:
                send = ws.send_bytes(item) if isinstance(item, bytes) else ws.send_str(item)
                try:
                    await asyncio.wait_for(send, self.cfg.stall_timeout_s)
                except TimeoutError:
                    self._count('slow_clients_closed')
                    _LOG.warning('%s stopped reading for %.1f s: disconnected', client.peer, self.cfg.stall_timeout_s)
                    await self._abort(client)
                    return
                except (ConnectionError, RuntimeError) as exc:  # closing/closed transport
                    _LOG.info('send to %s failed: %s', client.peer, exc)
                    self._disconnect(client, 'send failed')
                    return
                except Exception as exc:  # noqa: BLE001 - a writer must not die silently
                    self._count('send_errors')
                    _LOG.error('send to %s failed unexpectedly: %r', client.peer, exc)
                    await self._abort(client)
                    return

    async def _abort(self, client: _Client) -> None:
        transport = client.request.transport
        self._disconnect(client, 'aborted')
        if transport is not None:
            transport.abort()

    async def _broadcast_loop(self) -> None:
        """At view_rate_hz: the latest state, new camera frames and events to every page."""
        period = 1.0 / self.cfg.view_rate_hz
        camera_seen = 0
        next_t = time.monotonic()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            if time.monotonic() - next_t > 1.0:
                next_t = time.monotonic()
            if not self._clients:
                continue
            try:
                state = self._state_fn()
                state_text = json.dumps(dict(state, type='state', clients=len(self._clients),
                                             pilot=self._pilot is not None))
            except Exception as exc:  # noqa: BLE001 - never let a bad value kill the server loop
                self._count('state_errors')
                if self._throttle('state'):
                    _LOG.error('state snapshot failed: %r', exc)
                continue
            with self._lock:
                camera = self._camera if self._camera_version != camera_seen else None
                camera_seen = self._camera_version
                events, self._pending_events = self._pending_events, []
            for c in list(self._clients):
                if c.state is not None:
                    self._count('frames_dropped')
                c.state = state_text
                if camera is not None:
                    if c.camera is not None:
                        self._count('camera_frames_dropped')
                    c.camera = camera
                for e in events:
                    self._enqueue(c, e)
                c.wake.set()

    # ------------------------------------------------------------------ thread
    def start(self, timeout: float = 10.0) -> str:
        """Start serving on the server's own thread; returns the URL (OSError if it cannot bind)."""
        ready: Future = Future()
        self._thread = threading.Thread(target=self._run, args=(ready,), name='pilot_station_http', daemon=True)
        self._thread.start()
        ready.result(timeout=timeout)
        return self.url

    def _run(self, ready: Future) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            self._runner = web.AppRunner(self.make_app(), access_log=None, handle_signals=False)
            loop.run_until_complete(self._runner.setup())
            site = web.TCPSite(self._runner, self.cfg.host, self.cfg.port, reuse_address=True)
            loop.run_until_complete(site.start())
            self.port = int(self._runner.addresses[0][1])
            self._policy = HostPolicy(allowed_hosts(self.cfg.host, self.port, self.cfg.allowed_hosts))
        except BaseException as exc:  # noqa: BLE001 - hand the failure to start()
            ready.set_exception(exc)
            loop.close()
            return
        ready.set_result(self.port)
        try:
            loop.run_forever()
        finally:
            loop.run_until_complete(self._runner.cleanup())
            loop.close()

    def stop(self, timeout: float = 5.0) -> None:
        """Close every socket, stop the server thread."""
        if self._loop is not None and self._thread is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=timeout)
