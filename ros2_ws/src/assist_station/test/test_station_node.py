"""pilot_station as an rclpy node in this process (its timers not spun, so every publish is counted exactly):
bad messages on its topics never kill it, and the page's key messages publish only on a change."""
import asyncio
import json
import random
import threading
import time

import aiohttp
import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import String

from assist_station.pilot_station import PilotStation

LANDING = {'episode': 1, 'goal_index': 2, 'landed_index': 2, 'nearest_index': 2, 'error_m': 0.1,
           'nearest_error_m': 0.1, 'success': True, 'crash': False, 'duration_s': 12.0, 'assisted': False}


class Recorder:
    """Stands in for the /pilot/cmd_vel publisher: records every published command."""

    def __init__(self):
        self.lock, self.cmds = threading.Lock(), []

    def publish(self, msg):
        with self.lock:
            self.cmds.append(np.array([msg.twist.linear.x, msg.twist.linear.y, msg.twist.linear.z]))

    def count(self):
        with self.lock:
            return len(self.cmds)


@pytest.fixture
def station():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=random.randint(80, 89))
    node = PilotStation(context=ctx, parameter_overrides=[Parameter('port', value=0)])
    node.pub_cmd = Recorder()
    try:
        yield node
    finally:
        node.close()
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def callback(node, topic):
    """The callback rclpy calls for a message on `topic` (the node's own subscription)."""
    return next(s.callback for s in node.subscriptions if s.topic_name == topic)


async def page(node, session):
    url = node.server.url
    ws = await session.ws_connect(url + 'ws', headers={'Origin': url.rstrip('/')})
    while True:
        msg = await ws.receive(timeout=5.0)
        if msg.type == aiohttp.WSMsgType.TEXT and json.loads(msg.data)['type'] == 'hello':
            return ws


async def receive(ws, predicate, timeout=5.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        msg = await ws.receive(timeout=max(0.01, end - time.monotonic()))
        if predicate(msg):
            return msg
    raise AssertionError('expected message not received')


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 30))


def test_malformed_landings_are_counted_and_the_node_goes_on(station):
    on_landing = callback(station, '/sim/landing')
    audited = dict(LANDING, success=False, landed_index=3, goal_index='two')   # ValueError in the old feedback
    for bad in (audited, dict(LANDING, success=False, landed_index='x'), 'not json'):
        on_landing(String(data=bad if isinstance(bad, str) else json.dumps(bad)))
    assert station.diag.get('landing_rejected') == 3
    on_landing(String(data=json.dumps(LANDING)))                 # a good one afterwards is shown
    assert any('Landed on the goal platform' in e for e in station.server._pending_events)


def test_a_1x70000_mono8_image_is_subsampled_and_the_node_goes_on(station):
    on_camera = callback(station, '/camera/color/image_raw')

    async def main():
        async with aiohttp.ClientSession() as s:
            ws = await page(station, s)                          # the inset is only made while a page is open
            img = Image(width=1, height=70000, encoding='mono8', step=1, data=bytes(range(256)) * 273 + bytes(112))
            on_camera(img)
            frame = await receive(ws, lambda m: m.type == aiohttp.WSMsgType.BINARY)
            w, h = int.from_bytes(frame.data[:2], 'little'), int.from_bytes(frame.data[2:4], 'little')
            assert (w, h) == (1, 160) and len(frame.data) == 4 + 3 * 160
            station._last_camera = -1e9
            on_camera(Image(width=4, height=4, encoding='rgb16', step=24, data=bytes(96)))
            await ws.close()
    run(main())
    assert station.diag.get('camera_rejected') == 1


def test_an_unexpected_error_in_a_callback_is_counted_not_fatal(station, monkeypatch):
    def broken(event):
        raise RuntimeError('boom\nforged line')
    monkeypatch.setattr(station.server, 'push_event', broken)
    on_landing = callback(station, '/sim/landing')
    on_landing(String(data=json.dumps(LANDING)))
    on_landing(String(data=json.dumps(LANDING)))
    assert station.diag.get('landing_errors') == 2


def test_unchanged_keys_from_the_page_are_not_published_per_message(station):
    rec = station.pub_cmd

    async def main():
        async with aiohttp.ClientSession() as s:
            ws = await page(station, s)
            for seq in range(1, 301):                            # a page sending the same held set, fast
                await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyW'], 'seq': seq}))
            await receive(ws, lambda m: m.type == aiohttp.WSMsgType.TEXT and json.loads(m.data) == {'type': 'ack',
                                                                                                       'seq': 300})
            assert rec.count() == 1                              # one immediate publish for the one change
            np.testing.assert_allclose(rec.cmds[-1], [1.0, 0, 0])
            await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyW', 'KeyA'], 'seq': 301}))
            await receive(ws, lambda m: m.type == aiohttp.WSMsgType.TEXT and json.loads(m.data)['type'] == 'ack')
            assert rec.count() == 2
            np.testing.assert_allclose(rec.cmds[-1], [1.0, 1.0, 0])
            station._tick()                                      # the fixed-rate timer publishes the held command
            assert rec.count() == 3
            await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyW', 'KeyA'], 'seq': 302}))
            await receive(ws, lambda m: m.type == aiohttp.WSMsgType.TEXT and json.loads(m.data)['type'] == 'ack')
            assert rec.count() == 3
            await ws.close()
        while station.server.pilot_connected:                    # the socket closing releases the keys at once
            await asyncio.sleep(0.02)
    run(main())
    assert rec.count() == 4 and np.allclose(rec.cmds[-1], 0)
