"""Bridge core: every velocity setpoint passes through the touchdown envelope at the vehicle's downward range
(DISTANCE_SENSOR); an unknown range (none, stale, outside the sensor's limits, a sensor not facing down) lets
the command through; engagements, state and range are on the diagnostics; the envelope resets on disarm and
on a take-off after ON_GROUND; the node declares the TouchdownConfig fields as touchdown_* parameters."""
import dataclasses
import math
import os
import time

import numpy as np
import pytest

os.environ['MAVLINK20'] = '1'
from pymavlink import mavutil

from assist_bridge.bridge_core import RANGE_DOWN, BridgeConfig, MavlinkBridge, downward_range_m
from assist_bridge.mavlink_bridge_node import PARAMS, TOUCHDOWN_PARAMS
from assist_common.settings import RULE_KEY
from assist_common.touchdown import TouchdownConfig
from assist_sim.testing import RecordingWorld, VehicleThread, free_udp_port

mavlink = mavutil.mavlink
GUIDED = 4                                  # ArduCopter custom_mode
ARMED = mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
DISARMED = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
ON_GROUND, IN_AIR, TAKEOFF = (mavlink.MAV_LANDED_STATE_ON_GROUND, mavlink.MAV_LANDED_STATE_IN_AIR,
                              mavlink.MAV_LANDED_STATE_TAKEOFF)
FORWARD = mavlink.MAV_SENSOR_ROTATION_NONE
SIDEWAYS_DESCENT = [0.5, 0.3, -0.4]         # body FLU: forward, left, down (what slides on a pad top)


def final_descent(cmd, td) -> list[float]:
    """The final-descent setpoint for `cmd`: its sideways part limited to lateral_max_mps, the steady descent."""
    k = min(1.0, td.lateral_max_mps / float(np.hypot(cmd[0], cmd[1])))
    return [cmd[0] * k, cmd[1] * k, -td.descent_mps]


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class Rig:
    """A bridge on a fake clock, locked onto a scripted autopilot (GUIDED, armed, heading North) over loopback."""

    def __init__(self, touchdown: TouchdownConfig | None = None, **cfg):
        self.clock = FakeClock()
        port = free_udp_port()
        cfg.setdefault('link_timeout_s', 30.0)
        self.bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}', **cfg), clock=self.clock,
                                    touchdown=touchdown)
        self.ap = mavutil.mavlink_connection(f'udpout:127.0.0.1:{port}', source_system=1, source_component=1,
                                             dialect='ardupilotmega')
        self.heartbeat(armed=True)
        self.ap.mav.attitude_send(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)      # level, heading North
        self.deliver(2)

    def deliver(self, n: int) -> None:
        """Let the bridge handle the next `n` messages sent to it (the timeout only bounds a hang)."""
        handled, deadline = 0, time.monotonic() + 10.0
        while handled < n:
            assert time.monotonic() < deadline, f'only {handled} of {n} messages reached the bridge'
            handled += self.bridge.poll()
            time.sleep(0.002)

    def heartbeat(self, armed: bool) -> None:
        self.ap.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   ARMED if armed else DISARMED, GUIDED, mavlink.MAV_STATE_ACTIVE)

    def range_cm(self, cm: int, orientation: int = RANGE_DOWN, min_cm: int = 5, max_cm: int = 1500) -> None:
        """One DISTANCE_SENSOR reading, handled (received at the fake clock's now)."""
        self.ap.mav.distance_sensor_send(0, min_cm, max_cm, cm, mavlink.MAV_DISTANCE_SENSOR_LASER, 0, orientation, 0)
        self.deliver(1)

    def landed_state(self, state: int) -> None:
        self.ap.mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, state)
        self.deliver(1)

    def sent_flu(self) -> np.ndarray:
        """The last setpoint as body FLU (heading North: NED x = forward, NED y = right, NED z = down)."""
        sp = self.bridge.last_setpoint
        return np.array([sp['vx'], -sp['vy'], -sp['vz']])

    def next_scheduled(self) -> np.ndarray:
        """Advance one setpoint period and tick: the scheduled send; returns it (body FLU)."""
        n = self.bridge.counters['setpoints_sent']
        self.clock.t += 1.0 / self.bridge.cfg.setpoint_rate_hz
        self.bridge.tick()
        assert self.bridge.counters['setpoints_sent'] == n + 1
        return self.sent_flu()

    def close(self) -> None:
        self.ap.close()
        self.bridge.close()


@pytest.fixture
def rig():
    made = []

    def _make(touchdown=None, **cfg) -> Rig:
        made.append(Rig(touchdown, **cfg))
        return made[-1]
    yield _make
    for r in made:
        r.close()


def test_a_descent_below_the_engage_range_goes_out_vertical_and_a_climb_releases_it(rig):
    r = rig()
    td = r.bridge.touchdown.cfg
    assert r.bridge.snapshot()['touchdown'] == 'idle' and r.bridge.counters['touchdown_engaged'] == 0
    r.range_cm(80)                                  # above the engage range: the command as given
    r.bridge.set_command(SIDEWAYS_DESCENT)
    np.testing.assert_allclose(r.sent_flu(), SIDEWAYS_DESCENT, atol=1e-12)
    r.range_cm(30)                                  # 0.30 m < engage_range_m: the final descent
    np.testing.assert_allclose(r.next_scheduled(), final_descent(SIDEWAYS_DESCENT, td), atol=1e-12)
    snap = r.bridge.snapshot()
    assert snap['touchdown'] == 'engaged' and snap['range_m'] == pytest.approx(0.30)
    assert r.bridge.counters['touchdown_engaged'] == 1
    r.range_cm(20)
    np.testing.assert_allclose(r.next_scheduled(), final_descent(SIDEWAYS_DESCENT, td), atol=1e-12)
    assert r.bridge.counters['touchdown_engaged'] == 1       # one descent, one engagement
    r.bridge.set_command([0.2, 0.0, 0.5])          # the pilot climbs away: released, sent as commanded
    np.testing.assert_allclose(r.sent_flu(), [0.2, 0.0, 0.5], atol=1e-12)
    assert r.bridge.snapshot()['touchdown'] == 'idle'
    r.bridge.set_command(SIDEWAYS_DESCENT)         # descends again: a second engagement
    np.testing.assert_allclose(r.next_scheduled(), final_descent(SIDEWAYS_DESCENT, td), atol=1e-12)
    assert r.bridge.counters['touchdown_engaged'] == 2
    r.range_cm(14)                                  # the legs are down: nothing sideways, the touchdown held
    np.testing.assert_allclose(r.next_scheduled(), [0.0, 0.0, -td.descent_mps], atol=1e-12)
    r.bridge.set_command([0.2, 0.0, 0.5])          # a hop after the legs touched does not undo the landing
    np.testing.assert_allclose(r.next_scheduled(), [0.0, 0.0, -td.descent_mps], atol=1e-12)
    assert r.bridge.touchdown.committed


def test_the_vertical_descent_keeps_to_max_descent_mps(rig):
    r = rig(max_descent_mps=0.3)
    assert r.bridge.touchdown.cfg.descent_mps > 0.3
    r.range_cm(30)
    r.bridge.set_command([0.5, 0.0, -1.0])
    np.testing.assert_allclose(r.sent_flu(), [r.bridge.touchdown.cfg.lateral_max_mps, 0.0, -0.3], atol=1e-12)


@pytest.mark.parametrize('reading, counter', [
    (None, None),                                             # no rangefinder heard
    (dict(cm=30, orientation=FORWARD), 'range_not_down'),     # a sensor that does not face down
    (dict(cm=3), 'range_out_of_limits'),                      # below the sensor's own minimum (5 cm)
    (dict(cm=30, max_cm=25), 'range_out_of_limits'),          # above its maximum
])
def test_an_unknown_range_lets_the_command_through(rig, reading, counter):
    r = rig()
    if reading is not None:
        r.range_cm(**reading)
    r.bridge.set_command(SIDEWAYS_DESCENT)
    np.testing.assert_allclose(r.sent_flu(), SIDEWAYS_DESCENT, atol=1e-12)
    np.testing.assert_allclose(r.next_scheduled(), SIDEWAYS_DESCENT, atol=1e-12)
    assert r.bridge.snapshot()['range_m'] == 'unknown' and r.bridge.snapshot()['touchdown'] == 'idle'
    assert r.bridge.counters['touchdown_engaged'] == 0
    if counter is not None:
        assert r.bridge.counters[counter] == 1


def test_a_stale_or_invalid_reading_releases_an_engaged_envelope(rig):
    r = rig(range_timeout_s=0.5)
    r.range_cm(30)
    r.bridge.set_command(SIDEWAYS_DESCENT)
    assert r.bridge.snapshot()['touchdown'] == 'engaged'
    r.clock.t += 0.5                                # exactly range_timeout_s old: still current
    r.bridge.set_command(SIDEWAYS_DESCENT)
    r.bridge.tick()
    assert r.bridge.snapshot()['touchdown'] == 'engaged' and r.bridge.downward_range() == pytest.approx(0.30)
    r.clock.t += 0.05                               # older than range_timeout_s: unknown
    assert r.bridge.downward_range() is None
    np.testing.assert_allclose(r.next_scheduled(), SIDEWAYS_DESCENT, atol=1e-12)
    assert r.bridge.snapshot()['touchdown'] == 'idle'
    r.range_cm(30)                                  # a fresh reading engages it again ...
    np.testing.assert_allclose(r.next_scheduled(), final_descent(SIDEWAYS_DESCENT, r.bridge.touchdown.cfg),
                               atol=1e-12)
    r.range_cm(2)                                   # ... an invalid one (below the sensor's minimum) releases it
    np.testing.assert_allclose(r.next_scheduled(), SIDEWAYS_DESCENT, atol=1e-12)
    assert r.bridge.counters['touchdown_engaged'] == 2


@pytest.mark.parametrize('args', [(math.nan, 0.05, 15.0, RANGE_DOWN), (math.inf, 0.05, 15.0, RANGE_DOWN),
                                  (0.3, math.nan, 15.0, RANGE_DOWN), (0.3, 0.05, math.inf, RANGE_DOWN),
                                  (0.04, 0.05, 15.0, RANGE_DOWN), (15.5, 0.05, 15.0, RANGE_DOWN),
                                  (0.3, 0.05, 15.0, FORWARD)])
def test_non_finite_out_of_limits_or_sideways_readings_are_unknown(args):
    assert downward_range_m(*args) is None


def test_readings_within_limits_facing_down_are_the_range():
    assert downward_range_m(0.3, 0.05, 15.0, RANGE_DOWN) == 0.3
    assert downward_range_m(0.05, 0.05, 15.0, RANGE_DOWN) == 0.05       # limits inclusive
    assert downward_range_m(15.0, 0.05, 15.0, RANGE_DOWN) == 15.0


def test_touchdown_disabled_sends_commands_as_given(rig):
    r = rig(TouchdownConfig(enabled=False))
    r.range_cm(30)
    r.bridge.set_command(SIDEWAYS_DESCENT)
    np.testing.assert_allclose(r.sent_flu(), SIDEWAYS_DESCENT, atol=1e-12)
    assert r.bridge.snapshot()['touchdown'] == 'off' and r.bridge.counters['touchdown_engaged'] == 0


def test_the_envelope_resets_on_disarm_and_on_a_take_off_after_landing(rig):
    r = rig()
    r.range_cm(30)
    r.bridge.set_command(SIDEWAYS_DESCENT)
    assert r.bridge.touchdown.engaged
    r.heartbeat(armed=False)                        # disarmed: the next flight starts afresh
    r.deliver(1)
    assert not r.bridge.touchdown.engaged
    r.heartbeat(armed=True)
    r.deliver(1)
    r.landed_state(IN_AIR)
    r.bridge.set_command(SIDEWAYS_DESCENT)
    r.next_scheduled()
    assert r.bridge.touchdown.engaged
    r.landed_state(IN_AIR)                          # still flying: kept
    assert r.bridge.touchdown.engaged
    r.landed_state(ON_GROUND)                       # landed: kept (ArduCopter's verdict, not a new flight) ...
    assert r.bridge.touchdown.engaged
    r.landed_state(TAKEOFF)                         # ... until it takes off again
    assert not r.bridge.touchdown.engaged
    assert r.bridge.counters['touchdown_engaged'] == 2


def test_distance_sensor_is_requested_at_range_rate_hz(rig):
    r = rig(range_rate_hz=25.0)
    r.bridge.request_streams()
    seen = {}
    deadline = time.monotonic() + 10.0
    while mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR not in seen:
        assert time.monotonic() < deadline, f'no SET_MESSAGE_INTERVAL for DISTANCE_SENSOR: {seen}'
        msg = r.ap.recv_match(type='COMMAND_LONG', blocking=True, timeout=0.2)
        if msg is not None and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            seen[int(msg.param1)] = msg.param2
    assert seen[mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR] == pytest.approx(1e6 / 25.0)


# ---------------------------------------------------------------------- configuration
def test_touchdown_parameters_take_default_and_range_from_touchdown_config():
    fields = dataclasses.fields(TouchdownConfig)
    assert set(TOUCHDOWN_PARAMS) == {f.name for f in fields}
    for f in fields:
        param = PARAMS[TOUCHDOWN_PARAMS[f.name]]
        assert param.default == f.default, f.name
        rule = f.metadata[RULE_KEY]
        low = rule.gt if rule.gt is not None else rule.ge
        assert (param.min, param.max, param.min_exclusive) == (low, rule.le, rule.gt is not None), f.name
    assert PARAMS['touchdown_enabled'].default is True
    for name in ('range_timeout_s', 'range_rate_hz'):
        assert PARAMS[name].default == getattr(BridgeConfig(), name)


def test_a_release_range_below_the_engage_range_is_refused():
    with pytest.raises(ValueError, match='release_range_m'):
        MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{free_udp_port()}'),
                      touchdown=TouchdownConfig(engage_range_m=0.5, release_range_m=0.4))
    with pytest.raises(ValueError, match='descent_mps'):
        MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{free_udp_port()}'),
                      touchdown=TouchdownConfig(descent_mps=-1.0))


# ---------------------------------------------------------------------- against the sim's ArduCopter stand-in
def wait_for(pred, timeout=20.0, what='condition'):
    """Poll pred() until true; the timeout only bounds a hang, it is not the assertion."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.01)
    raise AssertionError(f'timed out waiting for {what}')


def test_a_sideways_descent_onto_the_stand_in_ends_vertical():
    """The stand-in's DISTANCE_SENSOR reaches the envelope: below the engage range the vehicle is flown straight
    down at descent_mps although the pilot still asks for sideways speed (it slid on before)."""
    port = free_udp_port()
    bridge = MavlinkBridge(BridgeConfig(connection=f'udpin:127.0.0.1:{port}', link_timeout_s=3.0,
                                        takeoff_altitude_m=1.0))
    bridge.start()
    world = RecordingWorld()
    vt = VehicleThread(port, world=world, ekf_ready_delay_s=0.3)
    td = bridge.touchdown.cfg
    try:
        assert bridge.wait_heartbeat(10.0)
        wait_for(lambda: bridge.arm()[0], what='armed')
        ok, msg = bridge.takeoff()
        assert ok, msg
        wait_for(lambda: not bridge.snapshot()['taking_off'], what='takeoff climb')
        wait_for(lambda: bridge.downward_range() is not None, what='a downward range')
        assert bridge.downward_range() > td.release_range_m
        command = [0.3, 0.2, -0.2]                  # sideways while descending slowly
        deadline = time.monotonic() + 60.0          # bounds a hang only
        while world.pos[2] > 0.02:
            assert time.monotonic() < deadline, f'never came down: {world.pos}'
            bridge.set_command(command)
            time.sleep(0.02)
        steps = world.flown()
        high = [cmd for z, cmd in steps if z > td.release_range_m + 0.1]
        vertical = [k for k, (z, cmd) in enumerate(steps)
                    if np.allclose(cmd, [0.0, 0.0, -td.descent_mps], atol=1e-9)]
        assert high and vertical
        # above the envelope the vehicle flew the command (sideways); from the commit on, straight down to the
        # floor. The bridge commits on the range it last received, so the first vertical step may come a sensor
        # period or two below commit_range_m; never above it (DISTANCE_SENSOR reports whole centimetres)
        assert np.allclose(high[-1], command, atol=1e-9), high[-1]
        assert steps[vertical[0]][0] <= td.commit_range_m + 0.005, steps[vertical[0]]
        for z, cmd in steps[vertical[0]:]:
            if z > 0.02:
                np.testing.assert_allclose(cmd, [0.0, 0.0, -td.descent_mps], atol=1e-9)
        assert bridge.counters['touchdown_engaged'] == 1 and bridge.counters['range_received'] > 10
    finally:
        vt.stop()
        bridge.close()


# ---------------------------------------------------------------------- the node
@pytest.fixture
def make_node():
    """Factory: make_node(param=value, ...) -> MavlinkBridgeNode in process on its own context."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from assist_bridge.mavlink_bridge_node import MavlinkBridgeNode
    from assist_common.ros_io import release_logging
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get('ROS_DOMAIN_ID') or 0))
    made = []

    def _make(**params):
        params.setdefault('connection', f'udpin:127.0.0.1:{free_udp_port()}')
        node = MavlinkBridgeNode(context=ctx, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        made.append(node)
        return node
    yield _make
    for node in made:
        node.close()
        node.destroy_node()
    release_logging()
    rclpy.shutdown(context=ctx)


def test_the_node_builds_the_envelope_from_its_parameters_and_shows_it_on_diagnostics(make_node):
    node = make_node(touchdown_engage_range_m=0.3, touchdown_release_range_m=0.5, touchdown_descent_mps=0.4,
                     range_timeout_s=0.25)
    assert node.bridge.touchdown.cfg == TouchdownConfig(engage_range_m=0.3, release_range_m=0.5, descent_mps=0.4)
    assert node.bridge.cfg.range_timeout_s == 0.25
    node._update_diagnostics()
    values = node.diag._values
    assert (values['touchdown_engaged'], values['touchdown'], values['range_m']) == ('0', 'idle', 'unknown')
    node.bridge.counters['touchdown_engaged'] += 1           # as an engagement counts it
    node._update_diagnostics()
    assert node.diag._values['touchdown_engaged'] == '1'
    assert make_node(touchdown_enabled=False).bridge.touchdown.cfg.enabled is False


def test_the_node_refuses_a_release_range_below_the_engage_range_in_one_line(make_node):
    from assist_common.ros_params import StartupError
    with pytest.raises(StartupError) as err:
        make_node(touchdown_engage_range_m=0.5, touchdown_release_range_m=0.4)
    assert 'touchdown_release_range_m' in str(err.value) and '\n' not in str(err.value)


def test_the_takeoff_climb_ends_when_the_vehicle_reports_in_air_even_below_the_altitude_threshold(rig):
    # an EKF still converging at the takeoff command (a vehicle moved on the ground) puts the ground 0.5 m
    # up: the altitude threshold is then out of reach, and ArduCopter's TAKEOFF -> IN_AIR ends the climb
    import threading
    r = rig()
    r.ap.mav.local_position_ned_send(0, 0.0, 0.0, -0.5, 0.0, 0.0, 0.0)
    r.deliver(1)
    r.landed_state(ON_GROUND)
    result = []
    t = threading.Thread(target=lambda: result.append(r.bridge.takeoff(2.0)))
    t.start()
    try:
        deadline = time.monotonic() + 10.0
        while not r.bridge.snapshot()['taking_off']:
            assert time.monotonic() < deadline, 'takeoff never started'
            time.sleep(0.002)
        r.ap.mav.command_ack_send(mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_RESULT_ACCEPTED)
        r.deliver(1)
    finally:
        t.join(10.0)
    assert result and result[0][0], result
    r.bridge.set_command([0.5, 0.0, 0.0])
    r.landed_state(TAKEOFF)
    r.ap.mav.local_position_ned_send(0, 0.0, 0.0, -1.9, 0.0, 0.0, 0.0)   # 1.9 m < 0.5 + 2.0 - margin
    r.deliver(1)
    sent = r.bridge.counters['setpoints_sent']
    r.clock.t += 1.0
    r.bridge.tick()
    assert r.bridge.snapshot()['taking_off'] and r.bridge.counters['setpoints_sent'] == sent   # still climbing
    r.landed_state(IN_AIR)                       # ArduCopter: the takeoff reached its target
    assert not r.bridge.snapshot()['taking_off']
    r.bridge.set_command([0.5, 0.0, 0.0])        # the pilot's next command goes out
    np.testing.assert_allclose(r.sent_flu(), [0.5, 0.0, 0.0], atol=1e-12)
    assert r.bridge.counters['setpoints_sent'] == sent + 1
    r.landed_state(TAKEOFF)                      # a TAKEOFF report after the climb ended changes nothing
    r.landed_state(IN_AIR)
    assert not r.bridge.snapshot()['taking_off']
