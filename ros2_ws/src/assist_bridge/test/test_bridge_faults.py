"""Bridge core against values that do not fit MAVLink and against the vehicle's landed state: a message that
cannot be packed is counted, never raised; every configured value that reaches MAVLink is range-checked on
creation; EXTENDED_SYS_STATE's landed state is handed on at every report, and a value
outside MAV_LANDED_STATE is refused and counted."""
import dataclasses
import functools
import math
import os
import time

import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil

from assist_bridge.bridge_core import LANDED_STATES, BridgeConfig, EkfOrigin, MavlinkBridge
from assist_bridge.mavlink_bridge_node import PARAMS, VISION_PARAMS
from assist_bridge.vision import VisionConfig, VisionEstimate
from assist_common.settings import RULE_KEY, SettingsError
from assist_sim.testing import VehicleThread as _VehicleThread, free_udp_port

mavlink = mavutil.mavlink
ON_GROUND, IN_AIR, TAKEOFF, LANDING = (mavlink.MAV_LANDED_STATE_ON_GROUND, mavlink.MAV_LANDED_STATE_IN_AIR,
                                       mavlink.MAV_LANDED_STATE_TAKEOFF, mavlink.MAV_LANDED_STATE_LANDING)


def wait_for(pred, timeout=10.0, what='condition'):
    """Poll pred() until true; the timeout only bounds a hang, it is not the assertion."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.01)
    raise AssertionError(f'timed out waiting for {what}')


@pytest.fixture
def linked_bridge():
    """A bridge whose status says the link is up (nothing listens on the other end of its socket)."""
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpout:127.0.0.1:{free_udp_port()}'))
    bridge.status.link_up = True
    yield bridge
    bridge.close()


def estimate(**changes) -> VisionEstimate:
    fields = dict(usec=1_000_000, x=1.0, y=2.0, z=-0.5, roll=0.0, pitch=0.0, yaw=0.0, covariance=(0.0,) * 21,
                  reset_counter=0)
    fields.update(changes)
    return VisionEstimate(**fields)


# ---------------------------------------------------------------------- nothing sent can raise
@pytest.mark.parametrize('changes', [dict(x=1e39), dict(z=3.5e38), dict(usec=-1),
                                     dict(reset_counter=300)])
def test_a_vision_estimate_that_does_not_fit_mavlink_is_counted_not_raised(linked_bridge, changes):
    assert linked_bridge.send_vision(estimate(**changes)) is False
    assert linked_bridge.counters['tx_errors'] == 1
    assert linked_bridge.send_vision(estimate()) is True            # the link goes on
    assert linked_bridge.counters['tx_errors'] == 1


def test_a_command_that_cannot_be_sent_is_not_waited_for(linked_bridge):
    t0 = time.monotonic()
    assert linked_bridge.command_long(mavlink.MAV_CMD_NAV_TAKEOFF, [0, 0, 0, 0, 0, 0, 1e39], timeout=5.0) is None
    assert time.monotonic() - t0 < 4.0 and linked_bridge.counters['tx_errors'] == 1


@pytest.mark.parametrize('origin, words', [
    ((47.4, 8.5, 1e10), 'altitude_m must be <= 10000'),
    ((47.4, 8.5, -1e6), 'altitude_m must be >= -500'),
    ((95.0, 8.5, 400.0), 'latitude_deg must be <= 90'),
    ((47.4, -181.0, 400.0), 'longitude_deg must be >= -180'),
    ((47.4, math.nan, 400.0), 'longitude_deg must be a finite number'),
])
def test_ekf_origin_out_of_range_is_refused_before_anything_is_sent(linked_bridge, origin, words):
    with pytest.raises(ValueError, match=words):
        linked_bridge.set_ekf_origin(*origin)
    with pytest.raises(ValueError, match=words):
        EkfOrigin.from_list(list(origin))
    assert linked_bridge.counters['tx_errors'] == 0
    assert linked_bridge.set_ekf_origin(47.4, 8.5, 488.0) is True


def test_ekf_origin_list_forms():
    assert EkfOrigin.from_list([0.0]) is None
    assert EkfOrigin.from_list([47.4, 8.5, 488.0]) == EkfOrigin(47.4, 8.5, 488.0)
    with pytest.raises(ValueError, match=r'\[latitude deg, longitude deg, altitude m\]'):
        EkfOrigin.from_list([47.4, 8.5])


# ---------------------------------------------------------------------- ranges: one source, checked
@pytest.mark.parametrize('kwargs, words', [
    (dict(link_timeout_s=1e6), 'link_timeout_s must be <= 30'),
    (dict(odom_rate_hz=1e6), 'odom_rate_hz must be <= 200'),
    (dict(status_rate_hz=0.0), 'status_rate_hz must be >= 0.1'),
    (dict(takeoff_altitude_m=1e39), 'takeoff_altitude_m must be <= 100'),
    (dict(target_system=256), 'target_system must be <= 255'),
    (dict(source_system=0), 'source_system must be >= 1'),
    (dict(baud=True), 'baud must be an integer'),
    (dict(max_speed_mps=math.inf), 'max_speed_mps must be a finite number'),
    (dict(velocity_scale=0.0), 'velocity_scale must be > 0'),
])
def test_bridge_config_out_of_range_is_one_line(kwargs, words):
    with pytest.raises(SettingsError) as err:
        BridgeConfig(**kwargs)
    assert words in str(err.value) and '\n' not in str(err.value)


def _ranged_fields(cls):
    return {f.name: (f.default, f.metadata[RULE_KEY]) for f in dataclasses.fields(cls) if RULE_KEY in f.metadata}


@pytest.mark.parametrize('cls, names', [(BridgeConfig, None), (VisionConfig, VISION_PARAMS)])
def test_node_parameters_take_default_and_range_from_the_config(cls, names):
    """Every ranged config field that is a node parameter is declared with the config's default and bounds."""
    checked = 0
    for field_name, (default, rule) in _ranged_fields(cls).items():
        param = PARAMS.get(names[field_name] if names else field_name)
        if param is None:
            continue
        assert param.default == default, field_name
        low = rule.gt if rule.gt is not None else rule.ge
        assert (param.min, param.max, param.min_exclusive) == (low, rule.le, rule.gt is not None), field_name
        checked += 1
    assert checked == (len(names) if names else 21)


# ---------------------------------------------------------------------- landed state
def test_landed_state_is_handed_on_at_every_report_and_bad_values_are_counted():
    port = free_udp_port()
    seen = []
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}'), on_landed_state=seen.append)
    ap = mavutil.mavlink_connection(f'udpout:127.0.0.1:{port}', source_system=1, source_component=1,
                                    dialect='ardupilotmega')
    try:
        assert bridge.snapshot()['landed_state'] == 'UNKNOWN'
        ap.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 4, 3)
        for state in (ON_GROUND, ON_GROUND, TAKEOFF, IN_AIR, 9, 255, IN_AIR, LANDING, ON_GROUND):
            ap.mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, state)
        wait_for(lambda: bridge.poll() == 0 and len(seen) >= 7, what='landed states')
        assert seen == [ON_GROUND, ON_GROUND, TAKEOFF, IN_AIR, IN_AIR, LANDING, ON_GROUND]     # every valid report
        assert bridge.counters['rx_bad_landed_state'] == 2 and bridge.counters['rx_rejected'] == 2
        assert bridge.status.landed_state == ON_GROUND and bridge.snapshot()['landed_state'] == 'ON_GROUND'
        assert set(LANDED_STATES) == {0, 1, 2, 3, 4}
    finally:
        ap.close()
        bridge.close()


VehicleThread = functools.partial(_VehicleThread, ekf_ready_delay_s=0.3, heartbeat_interval_s=0.25)


def test_landed_state_follows_the_stand_in_through_a_flight():
    """The sim's ArduCopter stand-in: on the ground, taking off / in the air, landing, on the ground again."""
    port = free_udp_port()
    seen = []
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}', link_timeout_s=2.5,
                                        takeoff_altitude_m=1.0, status_rate_hz=20.0), on_landed_state=seen.append)
    bridge.start()
    vt = VehicleThread(port)
    try:
        assert bridge.wait_heartbeat(5.0)
        wait_for(lambda: seen[:1] == [ON_GROUND], what='first landed state')
        wait_for(lambda: bridge.arm()[0], what='armed')
        ok, msg = bridge.takeoff(1.0)
        assert ok, msg
        wait_for(lambda: not bridge.snapshot()['taking_off'], what='takeoff climb')
        wait_for(lambda: seen[-1] == IN_AIR, what='in the air')
        ok, msg = bridge.land()
        assert ok, msg
        wait_for(lambda: not vt.world.armed, timeout=20.0, what='disarm on touchdown')
        wait_for(lambda: seen[-1] == ON_GROUND, what='on the ground again')
        reports = list(seen)                                            # handed on at every report
        seen = [s for k, s in enumerate(reports) if k == 0 or s != reports[k - 1]]
        assert len(reports) > len(seen)
        airborne = seen.index(IN_AIR)
        assert seen[0] == ON_GROUND and set(seen[1:airborne]) <= {TAKEOFF}
        assert LANDING in seen[airborne:], seen
    finally:
        vt.stop()
        bridge.close()
