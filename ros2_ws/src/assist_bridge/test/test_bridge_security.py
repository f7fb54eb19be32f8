"""Bridge core against a hostile or broken link: endpoint vetting, vehicle lock,
signing, zero velocity on link loss, non-finite telemetry, setpoint rate limit, throttled errors."""
import functools
import logging
import math
import os
import socket
import stat
import threading
import time

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil

from assist_bridge.bridge_core import BridgeConfig, MavlinkBridge
from assist_bridge.mavlink_bridge_node import PARAMS
from assist_common.mavlink_io import COPTER_MODES
from assist_sim.mavlink_vehicle import MavlinkVehicle, MavlinkVehicleConfig
from assist_sim.testing import KinematicWorld, VehicleThread as _VehicleThread, free_udp_port

mavlink = mavutil.mavlink
KEY = bytes(range(1, 33))


def wait_for(pred, timeout=10.0, what='condition'):
    """Poll pred() until true; the timeout only bounds a hang, it is not the assertion."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.01)
    raise AssertionError(f'timed out waiting for {what}')


def heartbeat_frame(mode='LOITER', armed=True, system=1, component=1) -> bytes:
    """A valid ArduCopter HEARTBEAT frame from (system, component)."""
    m = mavlink.MAVLink(None, system, component)
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    return bytes(m.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base,
                                    COPTER_MODES[mode], mavlink.MAV_STATE_ACTIVE).pack(m))


# the stand-in with this file's timing (keywords given at a call still win)
VehicleThread = functools.partial(_VehicleThread, ekf_ready_delay_s=0.3, heartbeat_interval_s=0.25)


@pytest.fixture
def make_link():
    made = []

    def _make(bridge_cfg=None, vehicle_cfg=None):
        port = free_udp_port()
        bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}', link_timeout_s=1.5,
                                            takeoff_altitude_m=1.0, **(bridge_cfg or {})))
        bridge.start()
        vt = VehicleThread(port, **(vehicle_cfg or {}))
        made.append((bridge, vt))
        return bridge, vt, port
    yield _make
    for bridge, vt in made:
        vt.stop()
        bridge.close()


def fly(bridge, vt):
    """Arm (retrying until the stand-in's EKF is ready) and take off to 1 m."""
    assert bridge.wait_heartbeat(5.0)
    wait_for(lambda: bridge.arm()[0], what='armed')
    ok, msg = bridge.takeoff(1.0)
    assert ok, msg
    wait_for(lambda: not bridge.snapshot()['taking_off'], what='takeoff climb')


# ---------------------------------------------------------------------- item 7: endpoints
def test_default_endpoint_is_loopback():
    assert BridgeConfig().connection == 'udpin:127.0.0.1:14550'
    assert PARAMS['connection'].default == 'udpin:127.0.0.1:14550'


@pytest.mark.parametrize('url', ['/usr/bin/python3', 'flight.elf', '/tmp/flight.tlog', 'flight.bin', 'csv:x.csv',
                                 'udp:127.0.0.1:14550', 'udpbcast:255.255.255.255:14550', 'wsserver:0.0.0.0:80',
                                 'mcast:', 'uds:/tmp/sock', 'tcp:127.0.0.1', 'tcp:127.0.0.1:0', 'udpin:a b:1',
                                 'udpin:127.0.0.1:99999', '/dev/../usr/bin/python3', '/dev/tty;rm', 'ttyACM0',
                                 'COM3', ''])
def test_only_network_and_dev_endpoints_are_accepted(url):
    with pytest.raises(ValueError) as err:
        BridgeConfig(connection=url)
    assert '\n' not in str(err.value)


def test_an_executable_named_as_endpoint_is_never_run(tmp_path):
    marker = tmp_path / 'ran'
    exe = tmp_path / 'bin' / 'autopilot'
    exe.parent.mkdir()
    exe.write_text(f'#!/bin/sh\ntouch {marker}\n')
    exe.chmod(0o755)
    with pytest.raises((ValueError, ConnectionError)):
        MavlinkBridge(BridgeConfig(connection=str(exe)))
    time.sleep(0.3)
    assert not marker.exists()


def test_a_dev_path_that_is_not_a_serial_device_is_refused(tmp_path):
    shm = '/dev/shm'
    if not os.path.isdir(shm):
        pytest.skip('no /dev/shm')
    path = os.path.join(shm, f'h2_bridge_test_{os.getpid()}.elf')
    with open(path, 'w') as f:
        f.write('#!/bin/sh\n')
    try:
        with pytest.raises(ConnectionError, match='not a character device'):
            MavlinkBridge(BridgeConfig(connection=path))
    finally:
        os.unlink(path)


def test_receive_loop_errors_are_throttled(make_link, caplog):
    bridge, vt, _ = make_link()
    assert bridge.wait_heartbeat(5.0)
    calls = []

    def broken_poll():
        calls.append(1)
        raise OSError('device went away')
    caplog.set_level(logging.ERROR, logger='assist_bridge')
    bridge.poll = broken_poll
    time.sleep(1.5)
    lines = [r for r in caplog.records if 'MAVLink loop error' in r.getMessage()]
    assert bridge.counters['loop_errors'] >= 10 and len(calls) >= 10
    assert 1 <= len(lines) <= 2, len(lines)


# ---------------------------------------------------------------------- item 3: lock, mode, signing
def test_spoofed_heartbeats_from_another_port_are_ignored_and_get_nothing(make_link):
    bridge, vt, port = make_link()
    assert bridge.wait_heartbeat(5.0)
    spoof = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spoof.bind(('127.0.0.1', 0))
    spoof.settimeout(0.05)
    got = []
    try:
        end = time.monotonic() + 2.5               # > 2 of the bridge's own 1 Hz heartbeats
        while time.monotonic() < end:
            spoof.sendto(heartbeat_frame('LOITER', armed=True), ('127.0.0.1', port))
            try:
                got.append(spoof.recv(4096))
            except TimeoutError:
                pass
    finally:
        spoof.close()
    assert got == [], 'the bridge sent to a sender it is not locked onto'
    assert bridge.snapshot()['mode'] == 'STABILIZE' and not bridge.snapshot()['armed']
    assert bridge.counters['rx_foreign_address'] >= 10


def test_spoofed_heartbeats_do_not_keep_a_lost_link_up(make_link):
    bridge, vt, port = make_link()
    assert bridge.wait_heartbeat(5.0)
    spoof = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    spoof.bind(('127.0.0.2', 0))                   # another host
    stop = threading.Event()

    def spoofer():
        while not stop.is_set():
            spoof.sendto(heartbeat_frame('GUIDED'), ('127.0.0.1', port))
            time.sleep(0.05)
    t = threading.Thread(target=spoofer, daemon=True)
    t.start()
    try:
        vt.stop()                                  # the real vehicle goes silent
        wait_for(lambda: bridge.snapshot()['link'] == 'lost', 5.0, 'link declared lost')
        time.sleep(1.0)
        assert bridge.snapshot()['link'] == 'lost'
        assert bridge.counters['vehicle_relocks'] == 0 and bridge.counters['rx_foreign_address'] > 10
    finally:
        stop.set()
        t.join()
        spoof.close()


def test_after_a_declared_loss_the_same_host_may_come_back_on_a_new_port(make_link):
    bridge, vt, port = make_link()
    assert bridge.wait_heartbeat(5.0)
    first = bridge.peer.address
    vt.stop()
    wait_for(lambda: bridge.snapshot()['link'] == 'lost', 5.0, 'link declared lost')
    vt2 = VehicleThread(port)                      # restarted: new source port, same ids
    try:
        wait_for(lambda: bridge.snapshot()['link'] == 'up', 5.0, 'relocked')
        assert bridge.peer.address != first and bridge.counters['vehicle_relocks'] == 1
    finally:
        vt2.stop()


def test_no_relock_when_disabled(make_link):
    bridge, vt, port = make_link(bridge_cfg={'address_relock': False})
    assert bridge.wait_heartbeat(5.0)
    vt.stop()
    wait_for(lambda: bridge.snapshot()['link'] == 'lost', 5.0, 'link declared lost')
    vt2 = VehicleThread(port)
    try:
        time.sleep(2.0)
        assert bridge.snapshot()['link'] == 'lost' and bridge.counters['rx_foreign_address'] > 0
    finally:
        vt2.stop()


def test_other_system_ids_on_the_vehicle_address_are_ignored(make_link):
    bridge, vt, port = make_link()
    assert bridge.wait_heartbeat(5.0)
    sock = vt.vehicle._conn.port                   # the locked address, another system id
    for _ in range(5):
        sock.sendto(heartbeat_frame('LAND', system=7), ('127.0.0.1', port))
    wait_for(lambda: bridge.counters['rx_foreign_id'] >= 5, 5.0, 'foreign ids counted')
    assert bridge.snapshot()['mode'] == 'STABILIZE'


def test_never_switches_mode_without_a_request(make_link):
    bridge, vt, _ = make_link()
    fly(bridge, vt)
    assert bridge.set_mode('LOITER')[0]
    wait_for(lambda: bridge.snapshot()['mode'] == 'LOITER', what='LOITER heartbeat')
    def mode_commands():
        prefix = f'ack_{mavlink.MAV_CMD_DO_SET_MODE}_'
        return sum(n for k, n in vt.vehicle.counters.items() if k.startswith(prefix))
    before = mode_commands()      # the stand-in counts an ACK before sending it
    for _ in range(50):                            # commands arrive in LOITER
        bridge.set_command([0.5, 0.0, 0.0])
        time.sleep(0.02)
    assert vt.vehicle.mode == 'LOITER' and mode_commands() == before, 'the bridge changed the mode by itself'
    assert bridge.guided()[0] and vt.vehicle.mode == 'GUIDED'


def _key_file(tmp_path, data: bytes, mode=0o600):
    p = tmp_path / 'mavlink.key'
    p.write_bytes(data)
    p.chmod(mode)
    return str(p)


def test_signing_key_file_formats_and_permissions(tmp_path):
    from assist_common.mavlink_io import load_signing_key
    assert load_signing_key(_key_file(tmp_path, KEY)) == KEY
    assert load_signing_key(_key_file(tmp_path, KEY.hex().encode() + b'\n')) == KEY
    for data, mode, words in ((KEY, 0o644, 'chmod 600'), (KEY, 0o640, 'chmod 600'), (KEY[:31], 0o600, '32 raw bytes'),
                              (b'zz' * 32, 0o600, '64 hex'), (bytes(32), 0o600, 'all-zero')):
        with pytest.raises(ValueError, match=words) as err:
            load_signing_key(_key_file(tmp_path, data, mode))
        assert '\n' not in str(err.value)
    with pytest.raises(ValueError, match='No such file'):
        load_signing_key(str(tmp_path / 'missing.key'))
    assert stat.S_IMODE(os.stat(_key_file(tmp_path, KEY)).st_mode) == 0o600


def test_signed_link_flies_and_unsigned_or_wrong_key_frames_are_dropped(make_link, tmp_path):
    key = _key_file(tmp_path, KEY)
    bridge, vt, _ = make_link(bridge_cfg={'signing_key_file': key}, vehicle_cfg={'signing_key_file': key})
    fly(bridge, vt)
    assert bridge.snapshot()['signing'] is True and vt.vehicle.counters.get('rx_bad_signature', 0) == 0
    # an unsigned vehicle, and one signing with another key, never get a link
    other = tmp_path / 'other'
    other.mkdir()
    other_key = _key_file(other, bytes(range(2, 34)))
    for vehicle_cfg in ({}, {'signing_key_file': other_key}):
        b2, _, _ = make_link(bridge_cfg={'signing_key_file': key}, vehicle_cfg=vehicle_cfg)
        time.sleep(1.5)
        assert b2.snapshot()['link'] == 'waiting' and b2.peer is None
        assert b2.counters['rx_bad_signature'] > 0


def test_a_forged_frame_cannot_poison_a_signed_stream():
    from assist_common.mavlink_io import enable_signing, open_connection
    rx = open_connection(f'udpin:127.0.0.1:{free_udp_port()}')
    try:
        enable_signing(rx, KEY)

        def signed(key, timestamp):
            m = mavlink.MAVLink(None, 1, 1)
            m.signing.secret_key, m.signing.sign_outgoing, m.signing.link_id = key, True, 0
            m.signing.timestamp = timestamp
            return bytes(m.heartbeat_encode(2, 3, 0, 0, 3).pack(m))
        t0 = rx.mav.signing.timestamp
        assert rx.mav.parse_char(signed(KEY, t0 + 1)).get_type() == 'HEARTBEAT'
        forged = rx.mav.parse_char(signed(bytes(32 * [7]), 2 ** 47))     # far future, wrong key
        assert forged.get_type() == 'BAD_DATA'
        assert rx.mav.parse_char(signed(KEY, t0 + 2)).get_type() == 'HEARTBEAT'
    finally:
        rx.close()


# ---------------------------------------------------------------------- item 4: link loss
def test_link_loss_sends_zero_velocity_while_the_pilot_keeps_commanding(make_link):
    bridge, vt, _ = make_link(vehicle_cfg={'guid_timeout_s': 30.0})   # only the bridge can stop it
    fly(bridge, vt)
    stop = threading.Event()

    def pilot():
        while not stop.is_set():
            bridge.set_command([1.0, 0.0, 0.0])
            time.sleep(0.05)
    t = threading.Thread(target=pilot, daemon=True)
    t.start()
    try:
        wait_for(lambda: vt.world.vel[0] > 0.9, what='flying forward')
        vt.vehicle.set_telemetry_muted(True)       # one-way loss: the vehicle still hears the bridge
        wait_for(lambda: bridge.snapshot()['link'] == 'lost', 5.0, 'link declared lost')
        t_lost = time.monotonic()
        wait_for(lambda: np.linalg.norm(vt.world.vel) == 0.0, 5.0, 'vehicle braked')
        assert time.monotonic() - t_lost < 2.0      # at the declaration (not after a 30 s GUID_TIMEOUT)
        n = bridge.counters['setpoints_link_lost']
        time.sleep(1.6)                            # still commanded, still zero, resent at 2 Hz
        assert np.linalg.norm(vt.world.vel) == 0.0
        assert bridge.counters['setpoints_link_lost'] - n >= 2
        assert bridge.last_setpoint['vx'] == 0.0 and bridge.last_setpoint['vy'] == 0.0
    finally:
        stop.set()
        t.join()


# ---------------------------------------------------------------------- item 5: telemetry
def test_non_finite_local_position_is_rejected_and_counted():
    port = free_udp_port()
    odoms = []
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}'), on_odometry=odoms.append)
    ap = mavutil.mavlink_connection(f'udpout:127.0.0.1:{port}', source_system=1, source_component=1,
                                    dialect='ardupilotmega')
    try:
        ap.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 4, 3)
        ap.mav.attitude_send(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for bad in ((math.nan, 0, -1, 0, 0, 0), (0, 0, -1, math.inf, 0, 0), (0, 0, -1, 0, 0, -math.inf)):
            ap.mav.local_position_ned_send(0, *bad)
        ap.mav.local_position_ned_send(0, 1.0, 2.0, -3.0, 0.0, 0.0, 0.0)
        time.sleep(0.2)
        bridge.poll()
        assert bridge.counters['rx_non_finite'] == 3 and bridge.counters['rx_rejected'] == 3
        assert len(odoms) == 1 and np.all(np.isfinite(odoms[0].position))
        np.testing.assert_allclose(odoms[0].position, [2.0, 1.0, 3.0])
    finally:
        ap.close()
        bridge.close()


# ---------------------------------------------------------------------- item 6: setpoint rate
class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def flying_bridge(clock, rate_hz=10.0):
    """A bridge whose vehicle state says GUIDED, armed, level: every setpoint would be sent."""
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{free_udp_port()}', setpoint_rate_hz=rate_hz,
                                        heartbeat_rate_hz=1.0, link_timeout_s=30.0), clock=clock)
    st = bridge.status
    st.link_up, st.mode, st.armed, st.attitude, st.last_heartbeat = True, 'GUIDED', True, (0.0, 0.0, 0.0), clock()
    st.last_position = clock()
    return bridge


def test_a_900_hz_command_stream_leaves_at_most_twice_the_setpoint_rate():
    clock = FakeClock()
    bridge = flying_bridge(clock, rate_hz=10.0)
    try:
        k = 0
        for ms in range(3000):                      # 3 s: tick every ms, a new command ~900 times a second
            clock.t = 100.0 + ms * 1e-3
            while k * (1.0 / 900.0) <= ms * 1e-3:
                bridge.set_command([0.5 + 0.4 * math.sin(k * 0.01), 0.0, 0.0])
                k += 1
            bridge.tick()
        sent = bridge.counters['setpoints_sent']
        assert k > 2600
        assert 30 <= sent <= 2 * 10 * 3 + 2, sent
        assert bridge.counters['setpoints_immediate'] <= 31
        # the latest command is what the vehicle flies after the next scheduled send
        last = bridge._cmd.copy()
        clock.t += 0.1
        bridge.tick()
        assert bridge._sent_velocity is not None and np.array_equal(bridge._sent_velocity, last)
    finally:
        bridge.close()


def test_a_change_after_a_quiet_period_goes_out_at_once():
    clock = FakeClock()
    bridge = flying_bridge(clock)
    try:
        bridge.set_command([0.2, 0.0, 0.0])
        for _ in range(5):
            clock.t += 0.1
            bridge.tick()
        n = bridge.counters['setpoints_sent']
        bridge.set_command([0.2, 0.0, 0.0])          # unchanged: waits for the schedule
        assert bridge.counters['setpoints_sent'] == n
        bridge.set_command([0.6, 0.0, 0.0])          # changed: sent now
        assert bridge.counters['setpoints_sent'] == n + 1
        bridge.set_command([0.7, 0.0, 0.0])          # second change in the same period: deferred
        assert bridge.counters['setpoints_sent'] == n + 1 and bridge.counters['commands_deferred'] == 1
        clock.t += 0.1
        bridge.tick()
        assert bridge.counters['setpoints_sent'] == n + 2
        assert bridge.last_setpoint['vx'] == pytest.approx(0.7)   # heading North (yaw 0 NED): FLU x = NED x
    finally:
        bridge.close()


# ---------------------------------------------------------------------- run-time limits
def test_set_limits_validated_and_applied():
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{free_udp_port()}'))
    try:
        bridge.set_limits(velocity_scale=0.5)
        np.testing.assert_allclose(bridge.set_command([1.0, 0.0, 0.0]), [0.5, 0.0, 0.0])
        for bad in (dict(velocity_scale=0.0), dict(velocity_scale=1.5), dict(max_speed_mps=-1.0),
                    dict(max_climb_mps=math.nan), dict(setpoint_rate_hz=5.0)):
            with pytest.raises(ValueError):
                bridge.set_limits(**bad)
        assert bridge.cfg.velocity_scale == 0.5 and bridge.cfg.setpoint_rate_hz == 10.0
    finally:
        bridge.close()


# ---------------------------------------------------------------------- /odom rate against the stand-in
def test_stand_in_caps_telemetry_at_its_step_rate_and_says_so(caplog):
    """30 Hz requested from a vehicle stepped at 20 Hz: 20 Hz arrive, and its log says why."""
    clock = FakeClock()
    port = free_udp_port()
    gcs = mavutil.mavlink_connection(f'udpin:127.0.0.1:{port}', source_system=255, source_component=191,
                                     dialect='ardupilotmega')
    vehicle = MavlinkVehicle(KinematicWorld(), f'udpout:127.0.0.1:{port}',
                             MavlinkVehicleConfig(ekf_ready_delay_s=0.0), clock=clock)
    caplog.set_level(logging.INFO, logger='assist_sim.mavlink_vehicle')
    try:
        vehicle.step(0.05)                                  # the GCS learns the vehicle's address
        time.sleep(0.05)
        while gcs.recv_msg() is not None:
            pass
        gcs.mav.command_long_send(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                  float(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED), 1e6 / 30.0, 0, 0, 0, 0, 0)
        time.sleep(0.05)
        n = 0
        for _ in range(40):                                 # 2 s of vehicle time at 20 Hz
            clock.t += 0.05
            vehicle.step(0.05)
            time.sleep(0.002)
            while (m := gcs.recv_msg()) is not None:
                n += m.get_type() == 'LOCAL_POSITION_NED'
        assert 38 <= n <= 41, n                             # 20 Hz, not 30
        assert any('requested faster than this vehicle steps (20 Hz)' in r.getMessage() for r in caplog.records)
    finally:
        vehicle.close()
        gcs.close()


def test_receive_loop_sleeps_between_events(make_link):
    """The loop waits in select() (<= 20 ms) whatever the link state: it never spins and starves /cmd_vel."""
    def loop_rate(bridge) -> float:
        calls = []
        real_poll = bridge.poll
        bridge.poll = lambda: calls.append(1) or real_poll()
        time.sleep(1.0)
        bridge.poll = real_poll
        return len(calls)
    port = free_udp_port()
    waiting = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}'))
    waiting.start()
    try:
        assert loop_rate(waiting) < 150                 # no vehicle yet
    finally:
        waiting.close()
    bridge, vt, _ = make_link()
    assert bridge.wait_heartbeat(5.0)
    assert loop_rate(bridge) < 150                      # link up, no command
    vt.stop()
    wait_for(lambda: bridge.snapshot()['link'] == 'lost', 5.0, 'link declared lost')
    assert loop_rate(bridge) < 150                      # lost, vehicle disarmed
