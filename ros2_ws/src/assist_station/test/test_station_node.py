"""pilot_station as an rclpy node in this process (its timers not spun, so every publish is counted exactly):
bad messages on its topics never kill it, and the page's key messages publish only on a change; each unusable
message on /assist/goal_estimate and /cmd_vel is counted by reason, and the view state carries the intent cues
only while the assistant is live and the cue's parameter is on."""
import asyncio
import json
import math
import random
import threading
import time

import aiohttp
import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped, TwistStamped
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image
from std_msgs.msg import Bool, String
from visualization_msgs.msg import Marker, MarkerArray

from assist_common.ros_io import sec_to_stamp
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


# ---------------------------------------------------------------------- the intent cues
def stamped(node, msg, frame, offset_s=0.0):
    msg.header.frame_id = frame
    sec_to_stamp(node.get_clock().now().nanoseconds * 1e-9 + offset_s, msg.header.stamp)
    return msg


def estimate(node, p, var=0.01, frame='odom', offset_s=0.0):
    g = PoseWithCovarianceStamped()
    g.pose.pose.position.x, g.pose.pose.position.y, g.pose.pose.position.z = p
    g.pose.pose.orientation.w = 1.0
    cov = [0.0] * 36
    cov[0] = cov[7] = cov[14] = var
    cov[21] = cov[28] = cov[35] = 1e6
    g.pose.covariance = cov
    return stamped(node, g, frame, offset_s)


def twist(node, v, frame='base_link', offset_s=0.0):
    t = TwistStamped()
    t.twist.linear.x, t.twist.linear.y, t.twist.linear.z = v
    return stamped(node, t, frame, offset_s)


def scene():
    m = Marker(ns='platforms', id=0, type=Marker.CUBE, action=Marker.ADD)
    m.pose.position.x, m.pose.position.y, m.pose.position.z = 4.0, 1.0, 0.5
    m.pose.orientation.w = 1.0
    m.scale.x, m.scale.y, m.scale.z = 1.0, 1.0, 1.0
    return MarkerArray(markers=[m])


def test_unusable_intent_messages_are_counted_by_reason(station):
    callback(station, '/sim/scene')(scene())
    on_goal, on_cmd = callback(station, '/assist/goal_estimate'), callback(station, '/cmd_vel')
    on_goal(estimate(station, (4.0, 1.0, 1.0)))                           # on pad 0's top: fine
    on_goal(estimate(station, (math.nan, 1.0, 1.0)))
    on_goal(estimate(station, (4.0, 1.0, 1.0), frame='map'))
    on_goal(estimate(station, (4.0, 1.0, 1.0), var=-0.1))
    on_goal(estimate(station, (4.0, 1.0, 1.0), offset_s=-3.0))
    on_goal(estimate(station, (4.0, 1.0, 1.0), offset_s=3.0))
    on_goal(estimate(station, (0.0, 0.0, 1.0)))
    on_cmd(twist(station, (1.0, 0.0, 0.0), frame='odom'))
    on_cmd(twist(station, (math.inf, 0.0, 0.0)))
    for kind in ('nonfinite', 'frame', 'variance', 'stale_stamp', 'future_stamp', 'unknown_pad'):
        assert station.diag.get(f'goal_estimate_rejected_{kind}') == 1, kind
    assert station.diag.get('cmd_vel_rejected_frame') == 1 and station.diag.get('cmd_vel_rejected_nonfinite') == 1
    assert station.diag.get('goal_estimate_errors') == 0 and station.diag.get('cmd_vel_errors') == 0


def test_the_view_state_carries_cues_only_while_assisted_and_switched_on(station):
    callback(station, '/sim/scene')(scene())
    callback(station, '/assist/goal_estimate')(estimate(station, (4.1, 0.9, 1.0)))
    callback(station, '/assist/descent_ok')(Bool(data=False))
    callback(station, '/cmd_vel')(twist(station, (0.0, 0.4, 0.0)))      # the station published no u yet: u = 0
    assert station._state()['cues'] == {'goal': None, 'descent': None, 'push': None}     # no agent_cmd yet
    callback(station, '/assist/agent_cmd')(twist(station, (0.1, 0.0, 0.0)))
    cues = station._state()['cues']
    assert cues['goal']['pad'] == 0 and cues['goal']['state'] == 'sure' and cues['goal']['p'] == [4.1, 0.9, 1.0]
    assert cues['descent'] == 'hold' and cues['push'] == [0.0, 0.4, 0.0]
    station._publish([0.0, 0.4, 0.0])                                     # the pilot's own u: no push left
    assert station._state()['cues']['push'] is None
    results = station.set_parameters([Parameter('cue_goal', value=False), Parameter('cue_descent', value=False)])
    assert all(r.successful for r in results)
    cues = station._state()['cues']
    assert cues['goal'] is None and cues['descent'] is None
    refused = station.set_parameters([Parameter('cue_push', value=3)])
    assert not refused[0].successful and station.p['cue_push'] is True
