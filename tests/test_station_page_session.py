"""The station page in headless Chromium against the web server alone (no ROS graph): the pilot page keeps
its role across a dropped socket and a reload while another client waits for it, and a view-only page stops
the vehicle with Space. Chromium is a Debian package (`make browser`); the test fails, never skips, without it."""
from __future__ import annotations

import asyncio
import json
import threading
import time

import aiohttp
import numpy as np
import pytest

from assist_station import testing
from assist_station.testing import wait_for
from assist_station.server import ServerConfig, StationServer
from assist_station.station_core import KeyState, StationConfig


class Intruder:
    """A client with a valid Origin that keeps connecting to /ws on its own thread (the audited local poller)."""

    def __init__(self, url: str):
        self.url, self.roles, self.stop = url, [], threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)
        self.thread.start()

    async def _main(self):
        async with aiohttp.ClientSession() as s:
            while not self.stop.is_set():
                try:
                    ws = await s.ws_connect(self.url + 'ws', headers={'Origin': self.url.rstrip('/')})
                    while True:
                        msg = await ws.receive(timeout=5.0)
                        if msg.type == aiohttp.WSMsgType.TEXT and json.loads(msg.data)['type'] == 'hello':
                            self.roles.append(json.loads(msg.data)['role'])
                            break
                    await ws.send_str(json.dumps({'type': 'keys', 'down': ['KeyW', 'ArrowDown']}))
                    await ws.close()
                except (TimeoutError, aiohttp.ClientError):
                    pass
                await asyncio.sleep(0.05)


@pytest.fixture
def served(tmp_path):
    cmds, lock = [], threading.Lock()

    def on_command(v):
        with lock:
            cmds.append(np.asarray(v, float).copy())
    keys = KeyState(StationConfig(speed=1.0, speed_z=0.5, key_timeout_s=1.0))
    server = StationServer(ServerConfig(host='127.0.0.1', port=0), keys,
                           lambda: {'pose': None, 'odom_age_s': None, 'assist': 'off', 'keys': [], 'cmd': [0, 0, 0]},
                           {'mode': 'practice', 'show_goal': True, 'camera': False,
                            'chase': {'back_m': 3.5, 'up_m': 2.0, 'fov_deg': 60.0}}, on_command=on_command)
    url = server.start()
    try:
        driver = testing.start_browser(tmp_path / 'chromium')
    except FileNotFoundError as exc:
        server.stop()
        pytest.fail(str(exc))
    try:
        yield server, driver, url, lambda: (cmds[-1] if cmds else None)
    finally:
        driver.quit()
        server.stop()


def drop_pilot_socket(server: StationServer) -> None:
    """The pilot's TCP connection dies (no close frame), as on a network hiccup."""
    pilot = server._pilot
    server._loop.call_soon_threadsafe(pilot.request.transport.abort)


def test_the_pilot_page_keeps_its_role_and_a_view_only_page_can_stop(served):
    from selenium.webdriver.common.action_chains import ActionChains
    server, d, url, last = served
    d.get(url)
    stats = lambda: testing.page_stats(d)  # noqa: E731
    assert wait_for(lambda: stats()['role'] == 'pilot' and stats()['ws'] == 'open', 30), stats()
    intruder = Intruder(url)
    try:
        for _ in range(2):                      # a dropped socket, then a reload: the page reclaims the role
            drop_pilot_socket(server)
            assert wait_for(lambda: not server.pilot_connected, 5)
            assert wait_for(lambda: server.pilot_connected and stats()['role'] == 'pilot' and stats()['ws'] == 'open',
                            20), stats()
            d.refresh()
            assert wait_for(lambda: stats() is not None and stats()['role'] == 'pilot' and stats()['ws'] == 'open',
                            20), stats()
        assert wait_for(lambda: len(intruder.roles) >= 3, 10)
    finally:
        intruder.stop.set()
        intruder.thread.join(10)
    assert intruder.roles and set(intruder.roles) == {'spectator'}, intruder.roles
    assert server.stats['pilot_connects'] == 1 and server.stats['pilot_reclaims'] >= 2
    ActionChains(d).key_down('w').perform()
    assert wait_for(lambda: last() is not None and np.allclose(last(), [1.0, 0, 0]), 5), last()
    pilot_tab = d.current_window_handle
    d.switch_to.new_window('tab')               # the pilot's tab is hidden: its keys are released
    try:
        d.get(url)
        assert wait_for(lambda: stats()['role'] == 'spectator', 15), stats()
        assert 'Space stops the vehicle' in d.find_element('id', 'banner').text
        ActionChains(d).key_down(' ').perform()                 # the view-only page holds Space: stopped
        assert wait_for(lambda: server.keys.stopped(time.monotonic()), 5), dict(server.stats)
        assert server.stats['spectator_stops'] == 1 and np.allclose(last(), 0)
        ActionChains(d).key_up(' ').perform()
        assert wait_for(lambda: not server.keys.stopped(time.monotonic()), 5)
    finally:
        d.close()
        d.switch_to.window(pilot_tab)
    ActionChains(d).key_up('w').perform()
    assert wait_for(lambda: stats()['role'] == 'pilot', 5)
