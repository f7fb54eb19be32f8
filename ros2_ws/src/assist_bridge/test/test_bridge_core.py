"""Bridge core: limits, setpoint encoding, and the full protocol against the sim's ArduCopter stand-in."""
import functools
import math
import os
import socket
import time
from types import SimpleNamespace

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil

from assist_bridge.bridge_core import (TYPE_MASK_VELOCITY_YAW, BridgeConfig, MavlinkBridge,
                                       limit_velocity, velocity_setpoint)
from assist_sim.testing import VehicleThread as _VehicleThread, free_udp_port

mavlink = mavutil.mavlink


def wait_for(pred, timeout=10.0, what='condition'):
    """Poll pred() until true; the timeout only bounds a hang, it is not the assertion."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.01)
    raise AssertionError(f'timed out waiting for {what}')


# ---------------------------------------------------------------------- pure functions
def test_limit_velocity_scale_axis_and_total_clamps():
    cfg = BridgeConfig(velocity_scale=0.5, max_speed_x_mps=1.0, max_speed_y_mps=0.8, max_climb_mps=0.5,
                       max_descent_mps=0.3, max_speed_mps=10.0)
    np.testing.assert_allclose(limit_velocity([1.0, -1.0, 0.4], cfg), [0.5, -0.5, 0.2])
    np.testing.assert_allclose(limit_velocity([4.0, -4.0, -4.0], cfg), [1.0, -0.8, -0.3])
    cfg = BridgeConfig(max_speed_mps=1.0)
    v = limit_velocity([2.0, 2.0, 0.0], cfg)
    assert np.linalg.norm(v) == pytest.approx(1.0) and v[0] == pytest.approx(v[1])
    for bad in ([math.nan, 0, 0], [0, math.inf, 0], [1.0, 2.0]):
        with pytest.raises(ValueError):
            limit_velocity(bad, cfg)


def test_bad_config_rejected():
    with pytest.raises(ValueError):
        BridgeConfig(velocity_scale=0.0)
    with pytest.raises(ValueError):
        BridgeConfig(setpoint_rate_hz=-1.0)
    with pytest.raises(ValueError):
        BridgeConfig(connection='')


def test_velocity_setpoint_fixed_vectors():
    assert TYPE_MASK_VELOCITY_YAW == 0x09C7
    sp = velocity_setpoint([1.0, 0.0, 0.5], 0.0)            # sim vehicle faces East
    assert sp['coordinate_frame'] == mavlink.MAV_FRAME_LOCAL_NED
    assert (sp['vx'], sp['vy'], sp['vz']) == pytest.approx((0.0, 1.0, -0.5))
    assert sp['yaw'] == pytest.approx(math.pi / 2)
    sp = velocity_setpoint([0.0, 1.0, 0.0], math.pi / 2)     # facing North, left = West
    assert (sp['vx'], sp['vy'], sp['vz']) == pytest.approx((0.0, -1.0, 0.0), abs=1e-12)
    assert sp['yaw'] == pytest.approx(0.0)


def test_unopenable_connection_is_a_clear_error():
    with pytest.raises(ConnectionError, match='cannot open MAVLink connection'):
        MavlinkBridge(BridgeConfig(connection='udpin:256.1.1.1:1'))


# ---------------------------------------------------------------------- against the stand-in
# the stand-in with this file's timing (keywords given at a call still win)
VehicleThread = functools.partial(_VehicleThread, ekf_ready_delay_s=0.5)


@pytest.fixture
def link():
    port = free_udp_port()
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}', link_timeout_s=2.5,
                                        takeoff_altitude_m=1.0, max_speed_mps=3.0))
    bridge.start()
    vt = VehicleThread(port)
    yield SimpleNamespace(bridge=bridge, vt=vt, port=port)
    vt.stop()
    bridge.close()


def test_full_flight_arm_takeoff_fly_timeout_land(link):
    b, w = link.bridge, link.vt.world
    assert b.wait_heartbeat(5.0)
    ok, msg = b.arm()                       # EKF not ready yet (0.5 s): honest refusal
    if not ok:
        assert 'PreArm' in msg or 'requires position' in msg, msg
        time.sleep(0.6)
        ok, msg = b.arm()
    assert ok, msg
    assert w.armed and link.vt.vehicle.mode == 'GUIDED'
    ok, msg = b.takeoff()
    assert ok, msg
    wait_for(lambda: not b.snapshot()['taking_off'], what='takeoff climb')
    assert w.pos[2] == pytest.approx(1.0, abs=0.2)
    x0 = w.pos.copy()
    for _ in range(25):                     # forward (FLU +x) at 1 m/s for 0.5 s of commands
        b.set_command([1.0, 0.0, 0.0])
        time.sleep(0.02)
    wait_for(lambda: w.pos[0] - x0[0] > 0.3, what='forward motion')
    assert abs(w.pos[1] - x0[1]) < 0.05     # forward = ENU +x for the East-facing sim vehicle
    assert w.yaw_target == pytest.approx(0.0, abs=1e-6)   # heading held (not turned to travel)
    # command timeout: the bridge sends zero velocity and the vehicle stops
    wait_for(lambda: b.last_setpoint is not None and b.last_setpoint['vy'] == 0.0, what='zero setpoint')
    wait_for(lambda: np.linalg.norm(w.vel) == 0.0, what='vehicle stopped')
    assert b.counters['setpoints_zero_timeout'] > 0
    ok, msg = b.land()
    assert ok, msg
    wait_for(lambda: not w.armed, what='disarm on touchdown')
    assert w.pos[2] == 0.0


def test_non_finite_command_rejected_and_last_good_kept(link):
    b = link.bridge
    b.set_command([0.5, 0.0, 0.0])
    with pytest.raises(ValueError):
        b.set_command([math.nan, 0.0, 0.0])
    np.testing.assert_allclose(b.current_command(), [0.5, 0.0, 0.0])


def test_disarmed_or_not_guided_no_setpoints_and_mode_changed_only_on_request(link):
    b, v = link.bridge, link.vt.vehicle
    assert b.wait_heartbeat(5.0)
    for _ in range(10):
        b.set_command([1.0, 0.0, 0.0])
        time.sleep(0.01)
    assert b.counters['setpoints_sent'] == 0        # disarmed, STABILIZE
    time.sleep(0.6)
    assert b.arm()[0] and b.takeoff(1.0)[0]
    wait_for(lambda: not b.snapshot()['taking_off'], what='takeoff climb')
    assert b.set_mode('LOITER')[0]
    wait_for(lambda: b.snapshot()['mode'] == 'LOITER', what='LOITER heartbeat')
    sent, mode_acks = b.counters['setpoints_sent'], v.counters.get(f'ack_{mavlink.MAV_CMD_DO_SET_MODE}_0', 0)
    for _ in range(60):                              # commands in LOITER: nothing sent, no mode change
        b.set_command([0.5, 0.0, 0.0])
        time.sleep(0.02)
    assert v.mode == 'LOITER' and b.counters['setpoints_sent'] == sent
    assert v.counters.get(f'ack_{mavlink.MAV_CMD_DO_SET_MODE}_0', 0) == mode_acks
    assert b.arm() == (True, 'arm: already armed (mode LOITER; mode not changed)')
    assert v.mode == 'LOITER'
    ok, msg = b.guided()                             # the pilot asks (/uav/guided): now GUIDED
    assert ok, msg
    assert v.mode == 'GUIDED'
    assert b.land()[0]
    wait_for(lambda: b.snapshot()['mode'] == 'LAND', what='LAND heartbeat')
    for _ in range(30):
        b.set_command([0.5, 0.0, 0.0])
        time.sleep(0.02)
    assert v.mode == 'LAND'


def test_link_loss_reported_setpoints_stop_and_recovery(link):
    b = link.bridge
    assert b.wait_heartbeat(5.0)
    events = []
    b._on_link = lambda up, why: events.append(up)
    link.vt.stop()
    wait_for(lambda: b.snapshot()['link'] == 'lost', what='link lost')
    sent = b.counters['setpoints_sent']
    b.set_command([1.0, 0.0, 0.0])
    assert b.counters['setpoints_sent'] == sent and b.counters['setpoints_suppressed_link'] >= 1
    requests = b.counters['stream_requests']
    link.vt = VehicleThread(link.port)               # the vehicle comes back (rebooted)
    wait_for(lambda: b.snapshot()['link'] == 'up', what='link recovered')
    # the state flips before the callback runs on the bridge thread: wait for the event itself
    wait_for(lambda: events[-2:] == [False, True], what='link-up event after the loss')
    assert b.counters['stream_requests'] > requests   # telemetry re-requested after recovery
    wait_for(lambda: b.status.position_ned is not None and b.status.last_position is not None,
             what='telemetry after recovery')


def test_garbage_on_the_bridge_port_never_crashes_it(link):
    b = link.bridge
    assert b.wait_heartbeat(5.0)
    rng = np.random.default_rng(1)
    good = mavlink.MAVLink(None, 1, 1).heartbeat_encode(2, 3, 0, 0, 3)
    frame = bytearray(good.pack(mavlink.MAVLink(None, 1, 1)))
    bad_crc = bytes(frame[:-2]) + bytes([frame[-2] ^ 0x55, frame[-1] ^ 0x55])
    payloads = [rng.bytes(int(n)) for n in rng.integers(1, 1500, 200)]
    payloads += [bytes(frame[:5]), bytes(frame[:-1]), bad_crc, b'\xfd' * 4000, rng.bytes(65000), b'']
    # from anywhere else (dropped unparsed: the bridge is locked onto the vehicle's address) ...
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for pl in payloads[:50]:
        s.sendto(pl, ('127.0.0.1', link.port))
    s.close()
    time.sleep(0.2)               # (all of it at once would overflow the socket's receive buffer)
    # ... and from the vehicle's own address (parsed: bad data counted)
    vehicle_sock = link.vt.vehicle._conn.port
    for pl in payloads:
        vehicle_sock.sendto(pl, ('127.0.0.1', link.port))
    wait_for(lambda: b.counters['rx_bad_data'] > 0, what='bad data counted')
    wait_for(lambda: b.counters['rx_foreign_address'] > 0, what='foreign datagrams counted')
    beats = b.status.last_heartbeat
    wait_for(lambda: b.status.last_heartbeat != beats, what='heartbeats still parsed')
    time.sleep(0.6)
    ok, msg = b.arm()
    assert ok, msg
    assert b.counters['loop_errors'] == 0
    assert b.snapshot()['link'] == 'up'


def test_reboot_only_while_disarmed_and_the_vehicle_starts_over(link):
    b, v = link.bridge, link.vt.vehicle
    assert b.wait_heartbeat(5.0)
    wait_for(lambda: v.ekf_ready, what='EKF ready')
    assert b.arm()[0]
    assert b.reboot() == (False, 'reboot: refused, the vehicle is armed')
    assert v.counters.get(f'ack_{mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN}_0', 0) == 0    # nothing was sent
    assert b.disarm()[0]
    wait_for(lambda: not b.snapshot()['armed'], what='disarmed heartbeat')
    ok, msg = b.reboot()
    assert ok, msg
    assert v.counters.get(f'ack_{mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN}_0', 0) == 1
    assert not v.ekf_ready and v.mode == 'STABILIZE'                # booting again: not armable yet
    ok, msg = b.arm()
    assert not ok, msg


def test_force_disarm_only_when_allowed(link):
    b, v = link.bridge, link.vt.vehicle
    assert b.wait_heartbeat(5.0)
    wait_for(lambda: v.ekf_ready, what='EKF ready')
    assert b.arm()[0] and b.takeoff(1.0)[0]
    wait_for(lambda: not b.snapshot()['taking_off'], what='takeoff climb')
    ok, msg = b.force_disarm()
    assert not ok and 'allow_force_disarm is false' in msg
    assert b.disarm()[0] is False                    # a normal disarm is refused in flight
    b.cfg.allow_force_disarm = True
    ok, msg = b.force_disarm()
    assert ok, msg
    wait_for(lambda: not b.snapshot()['armed'], what='disarmed heartbeat')
