"""The station's web server over real sockets: page and assets, one pilot, bad input, slow clients."""
import asyncio
import base64
import json
import os
import re
import socket
import threading
import time

import aiohttp
import numpy as np
import pytest

from assist_station.server import WEB_DIR, ServerConfig, StationServer
from assist_station.station_core import KeyState, StationConfig


class Harness:
    """A StationServer on a free loopback port with recorded commands."""

    def __init__(self, **cfg):
        self.commands: list[np.ndarray] = []
        self.lock = threading.Lock()
        self.keys = KeyState(StationConfig(speed=1.0, speed_z=0.5, key_timeout_s=1.0))
        self.server = StationServer(ServerConfig(host='127.0.0.1', port=0, **cfg), self.keys,
                                    lambda: {'pose': None, 'assist': 'off'}, {'mode': 'practice'},
                                    on_command=self._on_command)

    def _on_command(self, v):
        with self.lock:
            self.commands.append(np.asarray(v, float).copy())

    def last_command(self):
        with self.lock:
            return self.commands[-1] if self.commands else None

    def wait(self, predicate, timeout=5.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate():
                return True
            time.sleep(0.02)
        return predicate()


@pytest.fixture
def harness():
    h = Harness(view_rate_hz=30.0, stall_timeout_s=1.0, max_message_bytes=1024, hard_max_message_bytes=8192)
    h.server.start()
    yield h
    h.server.stop()


def origin(url: str) -> dict[str, str]:
    """The Origin header of a page served from `url` (the station's own page)."""
    return {'Origin': url.rstrip('/')}


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 30))


async def receive_until(ws, predicate, timeout=5.0):
    """Messages until one matches; returns it (fails on timeout)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        msg = await ws.receive(timeout=max(0.01, end - time.monotonic()))
        if msg.type == aiohttp.WSMsgType.TEXT:
            obj = json.loads(msg.data)
            if predicate(obj):
                return obj
        elif msg.type in (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSED, aiohttp.WSMsgType.ERROR):
            return {'type': '_closed', 'code': ws.close_code}
    raise AssertionError('expected message not received')


def test_serves_the_page_and_its_assets_from_the_package_only(harness):
    async def main():
        async with aiohttp.ClientSession() as s:
            async with s.get(harness.server.url) as r:
                html = await r.text()
                assert r.status == 200 and "default-src 'self'" in r.headers['Content-Security-Policy']
            refs = re.findall(r'(?:src|href)="([^"]+)"', html)
            assert refs and all(ref.startswith('/static/') for ref in refs)
            for ref in refs:
                async with s.get(harness.server.url.rstrip('/') + ref) as r:
                    assert r.status == 200 and len(await r.read()) > 100
            async with s.get(harness.server.url + 'static/../server.py') as r:
                assert r.status in (403, 404)
    run(main())
    for f in WEB_DIR.iterdir():   # no CDN or any other host: the station works offline
        assert not re.search(r'https?://|//cdn|@import', f.read_text()), f.name


def test_pilot_keys_become_commands_and_a_dropped_socket_releases_them(harness):
    async def main():
        async with aiohttp.ClientSession() as s:
            ws = await s.ws_connect(harness.server.url + 'ws', headers=origin(harness.server.url))
            hello = await receive_until(ws, lambda m: m['type'] == 'hello')
            assert hello['role'] == 'pilot' and hello['mode'] == 'practice'
            await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyW', 'ArrowUp'], 'seq': 5}))
            ack = await receive_until(ws, lambda m: m['type'] == 'ack')
            assert ack['seq'] == 5
            np.testing.assert_allclose(harness.last_command(), [1.0, 0, 0.5])
            state = await receive_until(ws, lambda m: m['type'] == 'state')
            assert state['pilot'] is True and state['clients'] == 1
            ws._response.connection.transport.abort()      # the socket drops, no close frame
        assert harness.wait(lambda: not harness.server.pilot_connected)
        np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
        np.testing.assert_allclose(harness.keys.command(time.monotonic()), [0, 0, 0])
        assert harness.server.stats['pilot_disconnects'] == 1
    run(main())


def test_second_browser_is_view_only_and_told_so(harness):
    async def main():
        async with aiohttp.ClientSession() as s:
            pilot = await s.ws_connect(harness.server.url + 'ws', headers=origin(harness.server.url))
            assert (await receive_until(pilot, lambda m: m['type'] == 'hello'))['role'] == 'pilot'
            await pilot.send_str(json.dumps({'type': 'keys', 'down': ['KeyA'], 'seq': 1}))
            await receive_until(pilot, lambda m: m['type'] == 'ack')
            second = await s.ws_connect(harness.server.url + 'ws', headers=origin(harness.server.url))
            hello = await receive_until(second, lambda m: m['type'] == 'hello')
            assert hello['role'] == 'spectator' and 'another pilot' in hello['reason']
            await second.send_str(json.dumps({'type': 'keys', 'down': ['KeyS', 'ArrowDown'], 'seq': 1}))
            state = await receive_until(second, lambda m: m['type'] == 'state')   # still gets the view
            assert state['clients'] == 2
            assert harness.wait(lambda: harness.server.stats['spectator_keys'] == 1)
            np.testing.assert_allclose(harness.last_command(), [0, 1.0, 0])       # the pilot's keys only
            await second.close()
            await pilot.close()
        assert harness.server.stats['second_browser_refused'] == 1
    run(main())


def test_bad_messages_are_rejected_counted_and_the_pilot_keeps_flying(harness):
    async def main():
        async with aiohttp.ClientSession() as s:
            ws = await s.ws_connect(harness.server.url + 'ws', headers=origin(harness.server.url))
            await receive_until(ws, lambda m: m['type'] == 'hello')
            await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyD'], 'seq': 1}))
            await receive_until(ws, lambda m: m['type'] == 'ack')
            for bad in ('{{{', '"just a string"', json.dumps({'type': 'keys', 'down': 'KeyW'}),
                        json.dumps({'type': 'keys', 'down': ['KeyW'], 'pad': 'x' * 2000})):
                await ws.send_str(bad)
                err = await receive_until(ws, lambda m: m['type'] == 'error')
                assert err['kind'] in ('malformed', 'oversized')
            await ws.send_bytes(b'\x00' * 10)
            assert (await receive_until(ws, lambda m: m['type'] == 'error'))['kind'] == 'malformed'
            np.testing.assert_allclose(harness.last_command(), [0, -1.0, 0])     # unchanged by the junk
            await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyW', 'KeyZ', 'F13'], 'seq': 2}))
            await receive_until(ws, lambda m: m['type'] == 'ack')
            np.testing.assert_allclose(harness.last_command(), [1.0, 0, 0])
            st = harness.server.stats
            assert st['ws_malformed'] == 4 and st['ws_oversized'] == 1 and st['ws_unknown_keys'] == 2
            # above the hard limit the connection is closed, and the keys are released
            await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyW'], 'pad': 'x' * 20000}))
            closed = await receive_until(ws, lambda m: m['type'] == '_closed')
            assert closed['code'] == 1009
        assert harness.wait(lambda: not harness.server.pilot_connected)
        np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
        assert harness.server.stats['ws_oversized_closed'] == 1
    run(main())


def test_foreign_origin_is_refused(harness):
    async def main():
        async with aiohttp.ClientSession() as s:
            with pytest.raises(aiohttp.WSServerHandshakeError) as err:
                await s.ws_connect(harness.server.url + 'ws', headers={'Origin': 'http://evil.example'})
            assert err.value.status == 403
            ws = await s.ws_connect(harness.server.url + 'ws',
                                    headers={'Origin': harness.server.url.rstrip('/')})
            assert (await receive_until(ws, lambda m: m['type'] == 'hello'))['role'] == 'pilot'
            await ws.close()
    run(main())
    assert harness.server.stats['ws_origin_rejected'] == 1


def raw_ws_client(port: int) -> socket.socket:
    """A WebSocket client on a plain socket that sends one keys frame and then never reads."""
    sock = socket.create_connection(('127.0.0.1', port))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall((f'GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nOrigin: http://127.0.0.1:{port}\r\n'
                  f'Upgrade: websocket\r\nConnection: Upgrade\r\n'
                  f'Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n').encode())
    head = b''
    while b'\r\n\r\n' not in head:
        head += sock.recv(1)
    assert b' 101 ' in head
    payload = json.dumps({'type': 'keys', 'down': ['KeyW']}).encode()
    mask = os.urandom(4)
    sock.sendall(bytes([0x81, 0x80 | len(payload)]) + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))
    return sock


def test_a_client_that_never_reads_loses_frames_is_dropped_and_never_blocks_the_others(harness):
    srv = harness.server
    sock = raw_ws_client(srv.port)                        # first: it is the pilot, holding W
    assert harness.wait(lambda: harness.last_command() is not None and harness.last_command()[0] == 1.0)
    stop = threading.Event()

    def camera_feed():                                    # ~48 KB frames at 50 Hz fill its buffers fast
        while not stop.is_set():
            srv.set_camera(128, 128, os.urandom(128 * 128 * 3))
            time.sleep(0.02)
    feeder = threading.Thread(target=camera_feed, daemon=True)
    feeder.start()
    try:
        async def spectator():
            async with aiohttp.ClientSession() as s:
                ws = await s.ws_connect(srv.url + 'ws', headers=origin(srv.url))
                n_states, n_frames, t0 = 0, 0, time.monotonic()
                while time.monotonic() - t0 < 4.0:
                    msg = await ws.receive(timeout=2.0)
                    if msg.type == aiohttp.WSMsgType.BINARY:
                        n_frames += 1
                    elif msg.type == aiohttp.WSMsgType.TEXT and json.loads(msg.data)['type'] == 'state':
                        n_states += 1
                await ws.close()
                return n_states, n_frames
        n_states, n_frames = run(spectator())
        # the reader-less pilot never blocked the others: ~30 states/s and camera frames kept coming
        assert n_states >= 40 and n_frames >= 20, (n_states, n_frames)
        assert harness.wait(lambda: srv.stats['slow_clients_closed'] == 1, timeout=10.0), dict(srv.stats)
        assert srv.stats['frames_dropped'] + srv.stats['camera_frames_dropped'] > 0
        assert harness.wait(lambda: not srv.pilot_connected)
        np.testing.assert_allclose(harness.last_command(), [0, 0, 0])     # its keys were released
    finally:
        stop.set()
        feeder.join()
        sock.close()


# ---------------------------------------------------------------------- who may connect, and as what
def harness_with(**cfg):
    base = dict(view_rate_hz=30.0, stall_timeout_s=1.0, max_message_bytes=1024, hard_max_message_bytes=8192)
    h = Harness(**dict(base, **cfg))
    h.server.start()
    return h


async def pilot_page(s, url, session=None, **headers):
    """A page of the station on `url` (its Origin), optionally presenting a session token; returns (ws, hello)."""
    query = f'?session={session}' if session else ''
    ws = await s.ws_connect(url + 'ws' + query, headers=dict(origin(url), **headers))
    return ws, await receive_until(ws, lambda m: m['type'] == 'hello')


async def until(predicate, timeout=5.0):
    """Poll `predicate` without blocking the client's event loop; True once it holds."""
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            return False
        await asyncio.sleep(0.02)
    return True


async def send_keys(ws, down, seq):
    await ws.send_str(json.dumps({'type': 'keys', 'down': down, 'seq': seq}))
    await receive_until(ws, lambda m: m['type'] == 'ack' and m['seq'] == seq)


def test_dns_rebinding_name_is_refused_for_the_page_and_the_socket(harness):
    port = harness.server.port
    rebind = f'rebind.example:{port}'

    async def main():
        async with aiohttp.ClientSession() as s:
            async with s.get(harness.server.url, headers={'Host': rebind}) as r:
                assert r.status == 403
            async with s.get(harness.server.url + 'static/station.js', headers={'Host': rebind}) as r:
                assert r.status == 403
            with pytest.raises(aiohttp.WSServerHandshakeError) as err:
                await s.ws_connect(harness.server.url + 'ws', headers={'Host': rebind, 'Origin': f'http://{rebind}'})
            assert err.value.status == 403
            # a page of the station itself whose socket names a foreign host: refused too
            with pytest.raises(aiohttp.WSServerHandshakeError) as err:
                await s.ws_connect(harness.server.url + 'ws', headers={'Origin': f'http://{rebind}'})
            assert err.value.status == 403
            assert not harness.server.pilot_connected
    run(main())
    assert harness.server.stats['http_host_rejected'] == 3 and harness.server.stats['ws_origin_rejected'] == 1


@pytest.mark.parametrize('name', ['127.0.0.1', 'localhost', 'LOCALHOST', '[::1]'])
def test_the_loopback_names_of_a_loopback_bind_are_served(harness, name):
    url = f'http://{name}:{harness.server.port}/'

    async def main():
        async with aiohttp.ClientSession() as s:
            host = {'Host': f'{name}:{harness.server.port}'}
            async with s.get(harness.server.url, headers=host) as r:
                assert r.status == 200
            ws = await s.ws_connect(harness.server.url + 'ws', headers={**host, **origin(url)})
            assert (await receive_until(ws, lambda m: m['type'] == 'hello'))['role'] == 'pilot'
            await ws.close()
    run(main())


def test_an_extra_allowed_host_is_served_and_other_names_are_not():
    h = harness_with(allowed_hosts=('station.lan', 'other.lan:9999'))
    try:
        async def main():
            async with aiohttp.ClientSession() as s:
                for host, status in ((f'station.lan:{h.server.port}', 200), (f'station.lan:{h.server.port + 1}', 403),
                                     ('other.lan:9999', 200), (f'other.lan:{h.server.port}', 403),
                                     (f'evil@127.0.0.1:{h.server.port}', 403), ('', 403)):
                    async with s.get(h.server.url, headers={'Host': host}) as r:
                        assert r.status == status, host
        run(main())
    finally:
        h.server.stop()


def test_a_connection_without_origin_is_never_the_pilot(harness):
    async def main():
        async with aiohttp.ClientSession() as s:
            tool = await s.ws_connect(harness.server.url + 'ws')          # no Origin: not a browser page
            hello = await receive_until(tool, lambda m: m['type'] == 'hello')
            assert hello['role'] == 'spectator' and 'Origin' in hello['reason'] and 'session' not in hello
            await send_keys(tool, ['KeyW', 'ArrowDown'], 1)
            assert harness.last_command() is None and not harness.server.pilot_connected
            page, hello = await pilot_page(s, harness.server.url)          # the real page still gets the role
            assert hello['role'] == 'pilot'
            await send_keys(page, ['KeyS'], 1)
            np.testing.assert_allclose(harness.last_command(), [-1.0, 0, 0])
            await tool.close()
            await page.close()
    run(main())
    assert harness.server.stats['ws_no_origin'] == 1 and harness.server.stats['spectator_keys'] == 1


def test_the_pilot_keeps_the_role_across_a_reconnect_and_any_page_can_stop(harness):
    """The audited attack: another client connects during the pilot page's reconnect and flies forward and down."""
    url = harness.server.url

    async def main():
        async with aiohttp.ClientSession() as s:
            pilot, hello = await pilot_page(s, url)
            token = hello['session']
            assert hello['role'] == 'pilot' and len(token) >= 20
            await send_keys(pilot, ['KeyW'], 1)
            pilot._response.connection.transport.abort()                  # the pilot's socket drops
            assert await until(lambda: not harness.server.pilot_connected)
            np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
            intruder, hello = await pilot_page(s, url)                    # within the reconnect gap
            assert hello['role'] == 'spectator' and 'reconnecting' in hello['reason'] and 'session' not in hello
            await send_keys(intruder, ['KeyW', 'ArrowDown'], 1)
            np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
            guess, hello = await pilot_page(s, url, session='x' * len(token))
            assert hello['role'] == 'spectator'
            back, hello = await pilot_page(s, url, session=token)          # the pilot's page reconnects
            assert hello['role'] == 'pilot' and hello['session'] == token
            await send_keys(back, ['KeyW', 'KeyA'], 1)
            np.testing.assert_allclose(harness.last_command(), [1.0, 1.0, 0])
            # any page may stop: the view-only page holds Space, the command is zero at once and stays so
            await send_keys(intruder, ['Space'], 2)
            np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
            await send_keys(back, ['KeyW', 'KeyA'], 2)                     # the pilot's heartbeat: still stopped
            np.testing.assert_allclose(harness.keys.command(time.monotonic()), [0, 0, 0])
            await send_keys(intruder, [], 3)                               # stop released: held keys stay ignored
            np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
            await send_keys(back, ['KeyA'], 3)                              # ... until released and pressed again
            np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
            await send_keys(back, [], 4)
            await send_keys(back, ['KeyA', 'KeyW'], 5)
            np.testing.assert_allclose(harness.last_command(), [1.0, 1.0, 0])
            await send_keys(guess, ['Space'], 1)                           # a stopping page that drops releases it
            np.testing.assert_allclose(harness.last_command(), [0, 0, 0])
            guess._response.connection.transport.abort()
            assert await until(lambda: np.allclose(harness.last_command(), [0, 0, 0]))
            for ws in (intruder, back):
                await ws.close()
    run(main())
    st = harness.server.stats
    assert st['pilot_connects'] == 1 and st['pilot_reclaims'] == 1 and st['spectator_stops'] == 2


def test_the_reserved_pilot_role_is_freed_after_the_grace_period():
    h = harness_with(pilot_grace_s=0.3)
    try:
        async def main():
            async with aiohttp.ClientSession() as s:
                first, hello = await pilot_page(s, h.server.url)
                token = hello['session']
                await first.close()
                assert await until(lambda: not h.server.pilot_connected)
                await asyncio.sleep(0.5)
                other, hello = await pilot_page(s, h.server.url)            # grace over: a new pilot
                assert hello['role'] == 'pilot' and hello['session'] != token
                late, hello = await pilot_page(s, h.server.url, session=token)   # the old token no longer works
                assert hello['role'] == 'spectator'
                await other.close()
                await late.close()
        run(main())
    finally:
        h.server.stop()


def test_a_second_socket_of_the_pilot_session_takes_the_role_and_the_old_one_is_told():
    h = harness_with()
    try:
        async def main():
            async with aiohttp.ClientSession() as s:
                old, hello = await pilot_page(s, h.server.url)
                new, hello2 = await pilot_page(s, h.server.url, session=hello['session'])
                assert hello2['role'] == 'pilot'
                demoted = await receive_until(old, lambda m: m['type'] == 'hello')
                assert demoted['role'] == 'spectator'
                await send_keys(old, ['KeyW'], 1)
                await send_keys(new, ['KeyD'], 1)
                np.testing.assert_allclose(h.last_command(), [0, -1.0, 0])
                await old.close()
                await new.close()
        run(main())
    finally:
        h.server.stop()


def test_connections_beyond_max_connections_are_refused_but_the_pilot_always_gets_back_in():
    h = harness_with(max_connections=3)
    try:
        async def main():
            async with aiohttp.ClientSession() as s:
                pilot, hello = await pilot_page(s, h.server.url)
                others = [(await pilot_page(s, h.server.url))[0] for _ in range(2)]
                for _ in range(5):                                          # full: refused, cheaply
                    with pytest.raises(aiohttp.WSServerHandshakeError) as err:
                        await pilot_page(s, h.server.url)
                    assert err.value.status == 503
                pilot._response.connection.transport.abort()
                assert await until(lambda: not h.server.pilot_connected)
                others.append((await pilot_page(s, h.server.url))[0])      # takes the freed slot, view only
                with pytest.raises(aiohttp.WSServerHandshakeError):
                    await pilot_page(s, h.server.url)
                back, hello2 = await pilot_page(s, h.server.url, session=hello['session'])
                assert hello2['role'] == 'pilot' and h.server.n_clients == 4
                await send_keys(back, ['ArrowUp'], 1)
                np.testing.assert_allclose(h.last_command(), [0, 0, 0.5])
                for ws in others + [back]:
                    await ws.close()
        run(main())
    finally:
        h.server.stop()
    assert h.server.stats['ws_connections_refused'] == 6


def test_key_names_reach_the_log_escaped(harness, caplog):
    forged = 'KeyQ\n2031-01-01 00:00:00 [INFO] pilot_station: operator approved'

    async def main():
        async with aiohttp.ClientSession() as s:
            ws, _ = await pilot_page(s, harness.server.url)
            await send_keys(ws, ['KeyW', forged[:32], '\x1b[2J'], 1)
            await ws.close()
    with caplog.at_level('WARNING', logger='assist_station.server'):
        run(main())
    lines = [r.getMessage() for r in caplog.records if 'unknown keys' in r.getMessage()]
    assert len(lines) == 1 and '\n' not in lines[0] and '\x1b' not in lines[0], lines
    assert repr(forged[:32]) in lines[0] and r"'\x1b[2J'" in lines[0]


def test_study_steps_come_from_the_pilot_page_only_and_views_reach_every_page():
    steps = []
    h = Harness(view_rate_hz=30.0)
    h.server._on_study = steps.append
    h.server.start()
    try:
        async def main():
            async with aiohttp.ClientSession() as s:
                url = h.server.url
                pilot = await s.ws_connect(url + 'ws', headers=origin(url))
                await receive_until(pilot, lambda m: m['type'] == 'hello' and m['role'] == 'pilot')
                other = await s.ws_connect(url + 'ws', headers=origin(url))
                await receive_until(other, lambda m: m['type'] == 'hello')
                await other.send_str(json.dumps({'type': 'study', 'action': 'begin', 'participant': 'X1'}))
                err = await receive_until(other, lambda m: m['type'] == 'error')
                assert err['kind'] == 'study_not_pilot'
                await pilot.send_str(json.dumps({'type': 'study', 'action': 'launch_missiles'}))
                assert (await receive_until(pilot, lambda m: m['type'] == 'error'))['kind'] == 'malformed'
                await pilot.send_str(json.dumps({'type': 'study', 'action': 'begin', 'participant': 'P07'}))
                assert h.wait(lambda: len(steps) == 1)
                assert steps[0].action == 'begin' and steps[0].data == {'participant': 'P07'}
                h.server.set_study({'type': 'study', 'phase': 'consent', 'participant': 'P07'})
                for ws in (pilot, other):
                    view = await receive_until(ws, lambda m: m['type'] == 'study')
                    assert view['phase'] == 'consent'
                await other.close()
                await pilot.close()
        run(main())
    finally:
        h.server.stop()
    assert h.server.stats['ws_study_not_pilot'] == 1 and h.server.stats['study_messages'] == 1


def test_a_station_without_a_study_refuses_study_steps(harness):
    async def main():
        async with aiohttp.ClientSession() as s:
            ws = await s.ws_connect(harness.server.url + 'ws', headers=origin(harness.server.url))
            await receive_until(ws, lambda m: m['type'] == 'hello')
            await ws.send_str(json.dumps({'type': 'study', 'action': 'consent'}))
            assert (await receive_until(ws, lambda m: m['type'] == 'error'))['kind'] == 'no_study'
            await ws.close()
    run(main())


def test_the_study_hears_when_the_pilot_page_goes_or_is_replaced():
    lost = []
    h = Harness(view_rate_hz=30.0)
    h.server._on_pilot_lost = lambda: lost.append(time.monotonic())
    h.server.start()
    try:
        async def main():
            async with aiohttp.ClientSession() as s:
                url = h.server.url
                first, hello = await pilot_page(s, url)
                token = hello['session']
                second, hello2 = await pilot_page(s, url, session=token)      # the same page, a new socket
                assert hello2['role'] == 'pilot' and len(lost) == 1
                await first.close()                                          # the demoted socket: no news
                await asyncio.sleep(0.3)
                assert len(lost) == 1
                await second.close()
                assert h.wait(lambda: len(lost) == 2)
        run(main())
    finally:
        h.server.stop()
