"""The two-machine split over a real network link between two Linux network namespaces.

The vehicle namespace runs an ArduCopter stand-in on UDP loopback (assist_sim.testing.SilentAutopilot, with
position telemetry), mavlink_bridge_node and image_relay on a 30 Hz camera; the base-station namespace
runs a pilot that commands /cmd_vel and watches /odom and the relayed frames. DDS discovers across the
link (UDPv4 only: Fast DDS's shared-memory transport would otherwise carry the data past the link). The test
measures pilot -> setpoint latency (publish on the base station -> the setpoint datagram at the vehicle, by
the kernel's receive stamp; both namespaces share the host clock) on a clean link and on an impaired one
(50 ms delay, 5 % loss each way), then takes the link down: the vehicle must get zero velocity within
the bridge's command timeout, and commands must flow again when the link comes back.

The link is a veth pair impaired with `tc netem` where the kernel has netem; where it has not (some cloud
and microVM kernels are built without it), it is a pair of TUN devices joined by tests/standins/tun_link.py's
forwarder, which applies the same delay and loss in user space. The addresses are the project's own
(10.213.7.0/30); namespaces and devices are created and removed by the test. Needs root and iproute2
(`make test` installs it); skipped, saying why, only where namespaces cannot be created.
"""
from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = [pytest.mark.graph, pytest.mark.slow(seconds=55)]

REPO = Path(__file__).resolve().parents[1]
ROLES = REPO / 'tests' / 'standins' / 'netns_roles.py'
BIN = Path(sys.executable).parent
NET = '10.213.7.'
PORT = 14550
COMMAND_TIMEOUT_S = 0.5      # mavlink_bridge_node's default: no /cmd_vel for this long -> zero velocity
SETPOINT_PERIOD_S = 0.1      # its 10 Hz setpoints


def _ip(*args: str) -> None:
    subprocess.run(['ip', *args], check=True, capture_output=True, text=True, timeout=30)


DELAY_S, LOSS = 0.050, 0.05           # the impaired phase, each way


def _tun_link():
    """tests/standins/tun_link.py (the suite imports test modules by path, so not as a package)."""
    spec = importlib.util.spec_from_file_location('tun_link', REPO / 'tests' / 'standins' / 'tun_link.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _has_netem(ns: str) -> tuple[bool, str]:
    """Whether `tc netem` works in namespace `ns` (tried on its loopback, then removed); the error if not."""
    probe = subprocess.run(['ip', 'netns', 'exec', ns, 'tc', 'qdisc', 'add', 'dev', 'lo', 'root', 'netem', 'delay',
                            '1ms'], capture_output=True, text=True, timeout=30)
    if probe.returncode == 0:
        subprocess.run(['ip', 'netns', 'exec', ns, 'tc', 'qdisc', 'del', 'dev', 'lo', 'root'], capture_output=True,
                       timeout=30)
    return probe.returncode == 0, probe.stderr.strip()


class Link:
    """The link between the namespaces: veth + netem, or TUN devices + the user-space forwarder."""

    def __init__(self, veh: str, base: str, tag: str) -> None:
        self.veh, self.base = veh, base
        self.tun = None
        netem, why = _has_netem(veh)
        if netem:
            self.kind, self.dev_veh, self.dev_base = 'veth', f'astv{tag}', f'astb{tag}'
            _ip('link', 'add', self.dev_veh, 'type', 'veth', 'peer', 'name', self.dev_base)
            _ip('link', 'set', self.dev_veh, 'netns', veh)
            _ip('link', 'set', self.dev_base, 'netns', base)
            addrs = ((veh, self.dev_veh, [NET + '1/30']), (base, self.dev_base, [NET + '2/30']))
        else:
            tun_link = _tun_link()
            self.kind, self.dev_veh, self.dev_base = 'tun', f'astv{tag}', f'astb{tag}'
            self.no_netem = why
            self.tun = tun_link.TunLink(tun_link.open_tun_in(veh, self.dev_veh),
                                        tun_link.open_tun_in(base, self.dev_base))
            addrs = ((veh, self.dev_veh, [NET + '1', 'peer', NET + '2']),
                     (base, self.dev_base, [NET + '2', 'peer', NET + '1']))
        for ns, dev, addr in addrs:
            _ip('-n', ns, 'addr', 'add', *addr, 'dev', dev)
            _ip('-n', ns, 'link', 'set', 'lo', 'up')
            _ip('-n', ns, 'link', 'set', dev, 'up', 'multicast', 'on')
            _ip('-n', ns, 'route', 'add', '224.0.0.0/4', 'dev', dev)      # DDS discovery multicast
        if self.tun is not None:
            self.tun.start()

    def impair(self) -> str:
        """DELAY_S and LOSS each way; what was applied."""
        if self.tun is not None:
            self.tun.impair(DELAY_S, LOSS)
            return f'user-space netem on a TUN link (this kernel: {self.no_netem}): delay 50ms loss 5%'
        for ns, dev in ((self.base, self.dev_base), (self.veh, self.dev_veh)):
            subprocess.run(['ip', 'netns', 'exec', ns, 'tc', 'qdisc', 'add', 'dev', dev, 'root', 'netem', 'delay',
                            f'{DELAY_S * 1000:.0f}ms', 'loss', f'{LOSS * 100:.0f}%'], check=True, timeout=30)
        return 'netem delay 50ms loss 5%'

    def clear(self) -> None:
        """Back to a clean link."""
        if self.tun is not None:
            self.tun.impair(0.0, 0.0)
            return
        for ns, dev in ((self.base, self.dev_base), (self.veh, self.dev_veh)):
            subprocess.run(['ip', 'netns', 'exec', ns, 'tc', 'qdisc', 'del', 'dev', dev, 'root'], check=True,
                           timeout=30)

    def set_base_end(self, up: bool) -> None:
        """The base station's end of the link down (a pulled cable) or up again."""
        _ip('-n', self.base, 'link', 'set', self.dev_base, 'up' if up else 'down')
        if up:
            _ip('-n', self.base, 'route', 'replace', '224.0.0.0/4', 'dev', self.dev_base)

    def close(self) -> None:
        """Stop the forwarder (its devices go with it)."""
        if self.tun is not None:
            self.tun.close()


@pytest.fixture
def netns_pair():
    """(vehicle namespace, base namespace, the Link between them); all removed at teardown."""
    if shutil.which('ip') is None or shutil.which('tc') is None:
        pytest.skip('NETWORK SPLIT NOT TESTED: iproute2 (ip, tc) is not installed')
    if os.geteuid() != 0:
        pytest.skip('NETWORK SPLIT NOT TESTED: creating network namespaces needs root')
    tag = f'{os.getpid() % 100000}'
    veh, base = f'astveh{tag}', f'astbase{tag}'
    try:
        _ip('netns', 'add', veh)
    except subprocess.CalledProcessError as exc:
        pytest.skip(f'NETWORK SPLIT NOT TESTED: cannot create a network namespace here: {exc.stderr.strip()}')
    link = None
    try:
        _ip('netns', 'add', base)
        link = Link(veh, base, tag)
        yield veh, base, link
    finally:
        if link is not None:
            link.close()
        for ns in (veh, base):
            subprocess.run(['ip', 'netns', 'del', ns], capture_output=True, timeout=30)


class InNamespace:
    """A process inside a network namespace, its own session; output to a log file."""

    def __init__(self, ns: str, cmd: list[str], log: Path, domain: int):
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain), FASTDDS_BUILTIN_TRANSPORTS='UDPv4',
                   ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', PYTHONUNBUFFERED='1')
        self.log = log
        self._fh = open(log, 'w')
        self.proc = subprocess.Popen(['ip', 'netns', 'exec', ns, *cmd], env=env, stdout=self._fh,
                                     stderr=subprocess.STDOUT, start_new_session=True)

    def stop(self, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10)
        self._fh.close()
        return self.proc.returncode


def _latencies(sent: list, setpoints: list, after: float, until: float) -> tuple[np.ndarray, int]:
    """(latency of each command change sent after `after` and seen at the vehicle before `until`, changes never
    seen then: dropped on the way, or superseded by the next change before the bridge's next setpoint)."""
    arr = np.array(setpoints) if setpoints else np.zeros((0, 2))
    lat, lost = [], 0
    for _, t_sent, vx in sent:
        if t_sent < after:
            continue
        hit = arr[(np.abs(arr[:, 1] - vx) < 1e-6) & (arr[:, 0] >= t_sent) & (arr[:, 0] < until)] if len(arr) else arr
        if len(hit):
            lat.append(hit[0, 0] - t_sent)
        else:
            lost += 1
    return np.array(lat), lost


def test_split_over_a_network_link_with_delay_loss_and_a_link_cut(netns_pair, tmp_path, domain_id):
    veh, base, link = netns_pair
    py = sys.executable
    procs = []

    def start(ns, cmd, name):
        p = InNamespace(ns, cmd, tmp_path / f'{name}.log', domain_id)
        procs.append(p)
        return p
    start(veh, [py, str(ROLES), 'vehicle', str(tmp_path / 'vehicle.json'), str(PORT), '120'], 'vehicle')
    start(veh, [str(BIN / 'mavlink_bridge_node'), '--ros-args', '-p', f'connection:=udpin:127.0.0.1:{PORT}'],
          'bridge')
    start(veh, [str(BIN / 'image_relay')], 'relay')
    results = {}
    try:
        def fly(name: str, seconds: float, during=None) -> dict:
            out = tmp_path / f'{name}.json'
            pilot = start(base, [py, str(ROLES), 'pilot', str(out), str(seconds)], name)
            if during is not None:
                during()
            pilot.proc.wait(seconds + 60)
            assert out.exists(), pilot.log.read_text()[-3000:]
            return json.loads(out.read_text())
        results['clean'] = fly('clean', 12.0)
        impaired = link.impair()
        results['netem'] = fly('netem', 12.0)
        link.clear()
        cut = {}

        def cut_link():
            time.sleep(6.0)
            cut['down'] = time.time()
            link.set_base_end(up=False)
            time.sleep(3.0)
            cut['up'] = time.time()
            link.set_base_end(up=True)
        results['cut'] = fly('cut', 16.0, cut_link)     # back up ~9 s in; commands flowed again within 0.1 s of it
    finally:
        for p in reversed(procs):
            p.stop()
    setpoints = json.loads((tmp_path / 'vehicle.json').read_text())['setpoints']
    assert setpoints, (tmp_path / 'bridge.log').read_text()[-3000:]
    report = {}
    for phase in ('clean', 'netem'):
        r = results[phase]
        lat, lost = _latencies(r['sent'], setpoints, after=r['sent'][0][1] + 4.0,   # discovery settles first
                               until=r['sent'][-1][1] + 2.0)
        assert len(lat) >= 20, (phase, lost, (tmp_path / 'bridge.log').read_text()[-2000:])
        frames = np.array(r['frames'])
        age = frames[:, 1] - frames[:, 0] if len(frames) else np.zeros(0)     # camera -> base station, relay included
        report[phase] = {'p50_ms': round(1e3 * float(np.median(lat)), 1),
                         'p99_ms': round(1e3 * float(np.percentile(lat, 99)), 1),
                         'changes': len(lat) + lost, 'lost': lost, 'odom': r['odom'], 'frames': len(r['frames']),
                         'frame_age_p50_ms': round(1e3 * float(np.median(age)), 1) if len(age) else None,
                         'frame_age_p99_ms': round(1e3 * float(np.percentile(age, 99)), 1) if len(age) else None}
        assert r['odom'] > 50 and len(r['frames']) > 50, (phase, r['odom'], len(r['frames']))
    assert report['clean']['p99_ms'] < 500 and report['clean']['lost'] == 0, report
    report['link'], report['impairment'] = link.kind, impaired
    assert 50 <= report['netem']['p50_ms'] < 400, report            # one way: the 50 ms delay at least
    assert report['netem']['frame_age_p50_ms'] >= 50, report
    # link down: the bridge's command timeout -> zero velocity at the vehicle; back up: commands again
    arr = np.array(setpoints)
    after_down = arr[arr[:, 0] > cut['down']]
    zero = after_down[np.abs(after_down[:, 1]) < 1e-9]
    assert len(zero), report
    stop_s = float(zero[0, 0] - cut['down'])
    assert stop_s <= COMMAND_TIMEOUT_S + SETPOINT_PERIOD_S + 0.3, (stop_s, report)
    moving_again = arr[(arr[:, 0] > cut['up']) & (np.abs(arr[:, 1]) > 1e-9)]
    assert len(moving_again), 'commands never reached the vehicle again after the link came back'
    report['cut'] = {'zero_velocity_after_s': round(stop_s, 3),
                     'commands_again_after_s': round(float(moving_again[0, 0] - cut['up']), 2)}
    print('NETNS_REPORT', json.dumps(report))
    (tmp_path / 'report.json').write_text(json.dumps(report, indent=1))
