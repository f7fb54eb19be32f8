"""The ArduCopter stand-in, driven over UDP loopback by a pymavlink 'GCS' with a manual clock."""
import math
import os
import socket

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil

from assist_common.mavlink_io import COPTER_MODES
from assist_sim.mavlink_vehicle import MavlinkVehicle, MavlinkVehicleConfig
from assist_sim.testing import KinematicWorld, free_udp_port

mavlink = mavutil.mavlink
DT = 0.05


class Clock:
    """Manual clock the vehicle reads instead of time.monotonic."""

    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Rig:
    """Vehicle + GCS endpoint + clock, with helpers to step and collect what the GCS hears."""

    def __init__(self, world=None, **cfg):
        self.port = free_udp_port()
        self.gcs = mavutil.mavlink_connection(f'udpin:127.0.0.1:{self.port}', source_system=255,
                                              source_component=190, dialect='ardupilotmega')
        self.clock = Clock()
        self.world = world or KinematicWorld(start_xy=(1.0, 2.0), fall_when_disarmed=True)
        config = MavlinkVehicleConfig(**{'ekf_ready_delay_s': 2.0, **cfg})
        self.vehicle = MavlinkVehicle(self.world, f'udpout:127.0.0.1:{self.port}', config, self.clock)
        self.heard: list = []
        self.step(1)   # first HEARTBEAT: the udpin GCS learns the vehicle's address

    def step(self, n: int = 1, dt: float = DT) -> list:
        out = []
        for _ in range(n):
            self.clock.t += dt
            self.vehicle.step(dt)
            out += self.drain()
        return out

    def drain(self) -> list:
        out = []
        while True:
            m = self.gcs.recv_msg()
            if m is None:
                break
            if m.get_type() != 'BAD_DATA':
                out.append(m)
        self.heard += out
        return out

    def command(self, cmd, *params) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        self.gcs.mav.command_long_send(1, 1, cmd, 0, *p)
        for m in self.step(1):
            if m.get_type() == 'COMMAND_ACK' and m.command == cmd:
                return m.result
        raise AssertionError(f'no COMMAND_ACK for {cmd}')

    def set_mode(self, name: str) -> int:
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                            COPTER_MODES[name])

    def velocity(self, vn, ve, vd, frame=mavlink.MAV_FRAME_LOCAL_NED, yaw=None, yaw_rate=None):
        mask = 0b0000_1111_1100_0111
        if yaw is not None:
            mask &= ~0b0100_0000_0000
        if yaw_rate is not None:
            mask &= ~0b1000_0000_0000
        self.gcs.mav.set_position_target_local_ned_send(0, 1, 1, frame, mask, 0, 0, 0, vn, ve, vd,
                                                        0, 0, 0, yaw or 0.0, yaw_rate or 0.0)

    def airborne(self, alt=2.0):
        """Wait out the EKF, GUIDED, arm, take off to `alt` and return."""
        self.step(int(2.5 / DT))
        assert self.set_mode('GUIDED') == mavlink.MAV_RESULT_ACCEPTED
        assert self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
        assert self.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt) == mavlink.MAV_RESULT_ACCEPTED
        for _ in range(400):
            self.step(1)
            if self.vehicle.guided_submode == 'hold':
                return
        raise AssertionError('takeoff did not complete')

    def close(self):
        self.vehicle.close()
        self.gcs.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def of_type(msgs, t):
    return [m for m in msgs if m.get_type() == t]


def test_heartbeat_identifies_an_arducopter_and_nothing_else_is_streamed_unasked(rig):
    msgs = rig.step(int(2.2 / DT))
    hb = of_type(msgs, 'HEARTBEAT')
    assert 2 <= len(hb) <= 3          # 1 Hz
    assert hb[0].type == mavlink.MAV_TYPE_QUADROTOR
    assert hb[0].autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb[0].custom_mode == COPTER_MODES['STABILIZE']
    assert not hb[0].base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb[0].get_srcSystem() == 1
    assert {m.get_type() for m in msgs} == {'HEARTBEAT'}
    assert rig.world.pos[2] == 0.0 and not rig.world.armed   # starts landed and disarmed


def test_arming_refused_with_reason_until_ekf_ready(rig):
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_FAILED
    texts = [m.text for m in of_type(rig.heard, 'STATUSTEXT')]
    assert any(t.startswith('PreArm: ') for t in texts)
    assert rig.set_mode('GUIDED') == mavlink.MAV_RESULT_FAILED      # needs a position estimate
    assert not rig.vehicle.armed
    rig.step(int(2.1 / DT))
    assert rig.set_mode('GUIDED') == mavlink.MAV_RESULT_ACCEPTED
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    hb = of_type(rig.step(int(1.1 / DT)), 'HEARTBEAT')[-1]
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED and hb.custom_mode == COPTER_MODES['GUIDED']
    assert rig.world.armed


def test_set_mode_message_and_unknown_mode(rig):
    rig.step(int(2.1 / DT))
    rig.gcs.mav.set_mode_send(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES['LOITER'])
    acks = of_type(rig.step(1), 'COMMAND_ACK')
    assert acks[0].command == mavlink.MAVLINK_MSG_ID_SET_MODE and acks[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert rig.vehicle.mode == 'LOITER'
    assert rig.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 99) == mavlink.MAV_RESULT_FAILED
    assert rig.vehicle.mode == 'LOITER'
    assert rig.command(mavlink.MAV_CMD_DO_SET_MODE, 1, COPTER_MODES['AUTO']) == mavlink.MAV_RESULT_FAILED
    assert rig.command(12345) == mavlink.MAV_RESULT_UNSUPPORTED


def test_takeoff_refused_while_disarmed_then_climbs_to_altitude(rig):
    rig.step(int(2.1 / DT))
    assert rig.set_mode('GUIDED') == mavlink.MAV_RESULT_ACCEPTED
    assert rig.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == mavlink.MAV_RESULT_FAILED
    assert rig.world.pos[2] == 0.0
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert rig.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 2.0) == mavlink.MAV_RESULT_ACCEPTED
    rig.step(int(4.0 / DT))
    assert rig.world.pos[2] == pytest.approx(2.0, abs=0.15)
    assert rig.vehicle.guided_submode == 'hold'
    # already flying: a second takeoff is refused
    assert rig.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0) == mavlink.MAV_RESULT_FAILED


def test_velocity_local_ned_with_yaw_held_moves_north(rig):
    rig.airborne()
    start = rig.world.pos.copy()
    for _ in range(20):   # 1 s of 1 m/s North at 20 Hz, heading held at 90 deg (East, the sim's yaw 0)
        rig.velocity(1.0, 0.0, 0.0, yaw=math.pi / 2)
        rig.step(1)
    d = rig.world.pos - start
    assert d[1] == pytest.approx(1.0, abs=0.1)      # ENU +y is North
    assert abs(d[0]) < 0.05 and abs(d[2]) < 0.05
    assert rig.world.yaw_target == pytest.approx(0.0, abs=1e-6)


def test_body_offset_ned_forward_follows_the_heading(rig):
    rig.airborne()
    start = rig.world.pos.copy()
    for _ in range(20):   # forward 1 m/s, right 0.5 m/s in FRD; the vehicle faces East
        rig.velocity(1.0, 0.5, -0.2, frame=mavlink.MAV_FRAME_BODY_OFFSET_NED, yaw=0.0)
        rig.step(1)
    d = rig.world.pos - start
    assert d[0] == pytest.approx(1.0, abs=0.1)      # forward = East = ENU +x
    assert d[1] == pytest.approx(-0.5, abs=0.1)     # right of East-facing = South
    assert d[2] == pytest.approx(0.2, abs=0.05)     # NED up
    assert rig.world.yaw_target == pytest.approx(0.0, abs=1e-6)   # relative yaw 0 = keep heading


def test_free_yaw_turns_to_face_travel_like_wp_yaw_behavior(rig):
    rig.airborne()
    for _ in range(60):   # North, yaw and yaw rate both ignored
        rig.velocity(1.0, 0.0, 0.0)
        rig.step(1)
    assert rig.world.yaw_target == pytest.approx(math.pi / 2, abs=1e-6)   # ENU yaw of North
    assert rig.world.yaw == pytest.approx(math.pi / 2, abs=0.05)
    # slow travel (below 5 % of WPNAV_SPEED) does not turn the vehicle
    for _ in range(40):
        rig.velocity(0.0, -0.3, 0.0)
        rig.step(1)
    assert rig.world.yaw_target == pytest.approx(math.pi / 2, abs=1e-6)


def test_yaw_rate_setpoint_turns_counter_clockwise_in_enu_for_negative_ned_rate(rig):
    rig.airborne()
    y0 = rig.world.yaw_target
    for _ in range(10):
        rig.velocity(0.0, 0.0, 0.0, yaw_rate=-0.5)
        rig.step(1)
    assert rig.world.yaw_target - y0 == pytest.approx(0.25, abs=0.03)


def test_velocity_target_expires_after_guid_timeout(rig):
    rig.airborne()
    rig.velocity(0.0, 1.0, 0.0, yaw=math.pi / 2)
    rig.step(int(2.0 / DT))
    assert rig.vehicle.guided_submode == 'velocity'
    assert rig.world.vel[0] == pytest.approx(1.0)
    rig.step(int(1.2 / DT))
    assert rig.vehicle.guided_submode == 'hold'
    p = rig.world.pos.copy()
    rig.step(int(2.0 / DT))
    assert np.linalg.norm(rig.world.pos - p) < 0.05
    assert rig.vehicle.counters['guid_timeouts'] == 1


def test_setpoints_ignored_outside_guided_and_while_landed_or_disarmed(rig):
    rig.step(int(2.1 / DT))
    assert rig.set_mode('GUIDED') == mavlink.MAV_RESULT_ACCEPTED
    rig.velocity(0.0, 0.0, -1.0)        # disarmed: nothing
    rig.step(5)
    assert rig.world.pos[2] == 0.0
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    rig.velocity(1.0, 0.0, -1.0)        # armed but landed: nothing
    rig.step(5)
    assert rig.world.pos[2] == 0.0 and rig.world.pos[1] == 2.0
    assert rig.vehicle.counters['setpoints_ignored_landed_or_disarmed'] == 2
    assert rig.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 1.0) == mavlink.MAV_RESULT_ACCEPTED
    rig.step(int(2.0 / DT))
    assert rig.set_mode('LOITER') == mavlink.MAV_RESULT_ACCEPTED
    p = rig.world.pos.copy()
    rig.velocity(1.0, 0.0, 0.0)
    rig.step(10)
    assert np.linalg.norm(rig.world.pos - p) < 0.02
    assert rig.vehicle.counters['setpoints_ignored_not_guided'] == 1


def test_land_mode_descends_and_disarms_on_touchdown_and_disarm_in_flight_refused(rig):
    rig.airborne(1.0)
    assert rig.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mavlink.MAV_RESULT_FAILED
    assert rig.vehicle.armed
    assert rig.set_mode('LAND') == mavlink.MAV_RESULT_ACCEPTED
    rig.step(int(1.0 / DT))
    assert rig.world.vel[2] == pytest.approx(-0.5)
    rig.step(int(2.5 / DT))
    assert rig.world.pos[2] == 0.0
    assert not rig.vehicle.armed and not rig.world.armed


def test_message_interval_and_request_data_stream(rig):
    rig.step(int(2.1 / DT))
    assert rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                       100_000) == mavlink.MAV_RESULT_ACCEPTED
    msgs = rig.step(int(2.0 / DT))
    lp = of_type(msgs, 'LOCAL_POSITION_NED')
    assert 19 <= len(lp) <= 21
    # NED position of the ENU start (1, 2, 0)
    assert (lp[-1].x, lp[-1].y, lp[-1].z) == pytest.approx((2.0, 1.0, 0.0))
    assert rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                       -1) == mavlink.MAV_RESULT_ACCEPTED
    assert not of_type(rig.step(20), 'LOCAL_POSITION_NED')
    assert rig.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 9999, 100_000) == mavlink.MAV_RESULT_FAILED
    rig.gcs.mav.request_data_stream_send(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 4, 1)
    rig.gcs.mav.request_data_stream_send(1, 1, mavlink.MAV_DATA_STREAM_EXTRA3, 2, 1)
    msgs = rig.step(int(2.0 / DT))
    att = of_type(msgs, 'ATTITUDE')
    assert 7 <= len(att) <= 9
    assert att[-1].yaw == pytest.approx(math.pi / 2)     # sim yaw 0 faces East
    ess = of_type(msgs, 'EXTENDED_SYS_STATE')
    assert ess and ess[-1].landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_no_position_telemetry_before_ekf_ready(rig):
    rig.gcs.mav.request_data_stream_send(1, 1, mavlink.MAV_DATA_STREAM_POSITION, 10, 1)
    assert not of_type(rig.step(int(1.5 / DT)), 'LOCAL_POSITION_NED')
    assert of_type(rig.step(int(1.0 / DT)), 'GLOBAL_POSITION_INT')


def test_messages_for_another_system_are_ignored(rig):
    rig.step(int(2.1 / DT))
    rig.gcs.mav.command_long_send(7, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, COPTER_MODES['GUIDED'], 0, 0, 0, 0, 0)
    assert not of_type(rig.step(2), 'COMMAND_ACK')
    assert rig.vehicle.mode == 'STABILIZE'


def test_garbage_does_not_break_the_vehicle(rig):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rng = np.random.default_rng(0)
    vehicle_addr = next(iter(rig.gcs.clients))
    good = rig.gcs.mav.command_long_encode(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0)
    frame = bytearray(good.pack(rig.gcs.mav))
    bad_crc = bytes(frame[:-2]) + bytes([frame[-2] ^ 0xFF, frame[-1]])
    for payload in [rng.bytes(200), bytes(frame[:7]), bad_crc, b'\xfd' * 3000, rng.bytes(60000)]:
        sock.sendto(payload, vehicle_addr)
    rig.step(3)
    sock.close()
    rig.step(int(2.1 / DT))
    # UDP datagrams are whole frames: a truncated one never swallows the next good frame
    assert rig.set_mode('GUIDED') == mavlink.MAV_RESULT_ACCEPTED
    assert rig.vehicle.mode == 'GUIDED'
    assert rig.vehicle.counters.get('rx_bad_data', 0) > 0
    assert rig.vehicle.counters.get('rx_truncated', 0) > 0


def test_external_world_reset_disarms_and_lands_state(rig):
    rig.airborne(1.0)
    rig.world.reset(airborne=False)
    rig.step(1)
    assert not rig.vehicle.armed and rig.vehicle.guided_submode == 'idle'
    assert rig.vehicle.reset() is not None and rig.world.episode == 2


def test_real_landing_world_takeoff_and_fly_north():
    from assist_sim.core.world import LandingWorld
    world = LandingWorld(seed=1)
    r = Rig(world=world)
    try:
        assert world.landed and not world.armed
        r.airborne(2.0)
        assert world.state.position[2] == pytest.approx(2.0, abs=0.2)
        start = world.state.position.copy()
        for _ in range(40):    # 2 s North at 1 m/s, heading held East
            r.velocity(1.0, 0.0, 0.0, yaw=math.pi / 2)
            r.step(1)
        d = world.state.position - start
        assert d[1] > 1.2 and abs(d[0]) < 0.4 and abs(world.state.yaw) < 0.1
        for _ in range(60):    # yaw free: turns North (ENU yaw +pi/2)
            r.velocity(1.0, 0.0, 0.0)
            r.step(1)
        assert world.state.yaw == pytest.approx(math.pi / 2, abs=0.15)
    finally:
        r.close()
        world.close()
