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
            ws = await s.ws_connect(harness.server.url + 'ws')
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
            pilot = await s.ws_connect(harness.server.url + 'ws')
            assert (await receive_until(pilot, lambda m: m['type'] == 'hello'))['role'] == 'pilot'
            await pilot.send_str(json.dumps({'type': 'keys', 'down': ['KeyA'], 'seq': 1}))
            await receive_until(pilot, lambda m: m['type'] == 'ack')
            second = await s.ws_connect(harness.server.url + 'ws')
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
            ws = await s.ws_connect(harness.server.url + 'ws')
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
    sock.sendall((f'GET /ws HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n'
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
                ws = await s.ws_connect(srv.url + 'ws')
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
