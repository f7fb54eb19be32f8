"""ArduPilot SITL JSON physics backend against a SITL stand-in written from the protocol.

The stand-in (assist_sim.testing_sitl) sends servo packets and parses the replies with SITL's own
rules (SIM_JSON.cpp: newline framing, strstr + sscanf parsing, frame_count and clock rules).
"""
from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from assist_sim.core.config import TurbulenceConfig, WorldConfig
from assist_sim.core.quad_json import QuadJsonModel, rotation_ned_frd
from assist_sim.core.world import LandingWorld
from assist_sim.json_backend import JsonBackendConfig, JsonPhysicsServer, JsonRunnerConfig
from assist_sim.testing_sitl import SitlStandIn, sitl_parse

G = 9.81
T_NED_ENU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


class Rig:
    """World + quad model + backend on an ephemeral port + stand-in, all in one thread."""

    def __init__(self, turbulence: bool = False):
        cfg = WorldConfig(turbulence=TurbulenceConfig(enabled=turbulence))
        self.world = LandingWorld(cfg, seed=0)
        self.world.reset(3, start_position=(0.0, 0.0, 0.0), airborne=False)
        self.model = QuadJsonModel(self.world)
        self.server = JsonPhysicsServer(self.model, JsonBackendConfig(port=0))
        self.sitl = SitlStandIn(port=self.server.address[1])
        self.events: list[str | None] = []

    def pump(self):
        self.events.append(self.server.poll(1.0))

    def frame(self, pwm):
        reply = self.sitl.exchange(pwm, pump=self.pump)
        assert reply is not None, 'no parsable reply'
        return reply

    def airborne(self, z=2.0):
        """Teleport to z metres, motors spinning at hover."""
        self.world.reset(3, start_position=(0.0, 0.0, z), airborne=True)
        self.model.reset()
        self.model.command[:] = self.model.cfg.command_for_thrust(self.world.cfg.vehicle.mass_kg * G / 4)

    @property
    def hover_pwm(self):
        c = self.model.cfg
        return c.pwm_for_command(c.command_for_thrust(self.world.cfg.vehicle.mass_kg * G / 4))

    def close(self):
        self.sitl.close()
        self.server.close()
        self.world.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_reply_wire_format_and_vehicle_at_rest(rig):
    for _ in range(200):
        reply = rig.frame([1000] * 4)
    raw = rig.sitl.raw
    assert raw.startswith(b'\n') and raw.endswith(b'\n') and raw.count(b'\n') == 2
    assert b': ' not in raw and b', ' not in raw              # SITL's strstr/sscanf parser needs compact JSON
    assert sitl_parse(raw.decode().strip()) is not None
    j = reply['json']
    assert set(j) == {'timestamp', 'imu', 'position', 'velocity', 'attitude', 'quaternion', 'rng_1'}
    assert set(j['imu']) == {'gyro', 'accel_body'}
    # resting on its legs at the start spot, facing East (ENU +x): NED yaw +90 deg
    np.testing.assert_allclose(reply['accel_body'], [0.0, 0.0, -G], atol=0.05)
    np.testing.assert_allclose(reply['gyro'], [0.0, 0.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(reply['velocity'], [0.0, 0.0, 0.0], atol=1e-3)
    leg = rig.world.cfg.vehicle.leg_length_m
    np.testing.assert_allclose(reply['position'], [0.0, 0.0, -leg], atol=5e-3)
    np.testing.assert_allclose(reply['attitude'], [0.0, 0.0, math.pi / 2], atol=2e-3)
    np.testing.assert_allclose(reply['quaternion'], [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], atol=2e-3)
    assert reply['rng_1'] == pytest.approx(leg, abs=5e-3)
    assert rig.server.counters['replies'] == 200


def test_hover_pwm_keeps_it_hovering_and_more_climbs(rig):
    rig.airborne(2.0)
    hover = rig.hover_pwm
    assert 1500 < hover < 1700                                  # hover throttle 0.42 -> mid-range PWM
    first = rig.frame([hover] * 4)
    for _ in range(400):                                        # 1 s
        reply = rig.frame([hover] * 4)
    assert abs(reply['position'][2] - first['position'][2]) < 0.02
    assert abs(reply['velocity'][2]) < 0.02
    np.testing.assert_allclose(reply['accel_body'], [0.0, 0.0, -G], atol=0.05)
    np.testing.assert_allclose(reply['gyro'], [0, 0, 0], atol=1e-3)
    for _ in range(200):
        reply = rig.frame([hover + 60] * 4)
    assert reply['velocity'][2] < -0.3                          # NED down negative: climbing
    assert reply['accel_body'][2] < -G - 0.5                    # more thrust than weight


def _attitude_pulse(rig, deltas, frames=40):
    """From hover, offset servo 1..4 by `deltas` (us) for `frames`, then hover PWM again."""
    rig.airborne(3.0)
    hover = rig.hover_pwm
    for _ in range(frames):
        reply = rig.frame([hover + d for d in deltas])
    return reply


def test_roll_command_gyro_accel_and_velocity_signs(rig):
    # roll right (FRD +x): left motors (servo 2 back-left, 3 front-left) up, right motors down
    reply = _attitude_pulse(rig, [-40, +40, +40, -40])
    gx, gy, gz = reply['gyro']
    assert gx > 0.5 and abs(gy) < 0.1 * gx and abs(gz) < 0.1 * gx
    assert reply['attitude'][0] > 0.01
    thrust = float(rig.model.thrust.sum())
    ax, ay, az = reply['accel_body']
    assert az == pytest.approx(-thrust / rig.world.cfg.vehicle.mass_kg, abs=0.15)   # thrust along body -z
    assert abs(ax) < 0.3 and abs(ay) < 0.3
    # level the motors again: tilted right, the vehicle slides to its right = South (facing East)
    for _ in range(200):
        reply = rig.frame([rig.hover_pwm] * 4)
    truth = rig.world.state.velocity
    assert truth[1] < -0.05                                     # ENU -y = South
    assert reply['velocity'][0] == pytest.approx(truth[1], abs=1e-9)   # NED north = ENU y


def test_pitch_and_yaw_command_signs(rig):
    reply = _attitude_pulse(rig, [+40, -40, +40, -40])          # front up, back down: nose up
    assert reply['gyro'][1] > 0.5 and reply['attitude'][1] > 0.01
    reply = _attitude_pulse(rig, [+60, +60, -60, -60], frames=80)   # CCW motors faster: yaw right (CW from above)
    assert reply['gyro'][2] > 0.05
    assert rig.world.state.angular_velocity[2] < -0.05        # FLU z up: clockwise is negative
    assert abs(reply['gyro'][0]) < 0.2 * reply['gyro'][2] and abs(reply['gyro'][1]) < 0.2 * reply['gyro'][2]


def test_ned_position_velocity_attitude_match_pybullet_enu_truth(rig):
    rig.airborne(2.5)
    hover = rig.hover_pwm
    rng = np.random.default_rng(1)
    for _ in range(300):
        pwm = [hover + d for d in rng.normal(0, 25, 4)]
        reply = rig.frame(pwm)
        st = rig.world.state
        np.testing.assert_allclose(reply['position'], T_NED_ENU @ st.position, atol=1e-9)
        np.testing.assert_allclose(reply['velocity'], T_NED_ENU @ st.velocity, atol=1e-9)
        r_enu_flu = np.array(rig.world._bc.getMatrixFromQuaternion(st.quaternion)).reshape(3, 3)
        r_ned_frd = rotation_ned_frd(r_enu_flu)
        w, x, y, z = reply['quaternion']
        q_mat = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                          [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                          [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(q_mat, r_ned_frd, atol=1e-6)
        roll, pitch, yaw = reply['attitude']
        cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                                  math.cos(yaw), math.sin(yaw))
        e_mat = np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                          [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                          [-sp, sr * cp, cr * cp]])
        np.testing.assert_allclose(e_mat, r_ned_frd, atol=1e-6)
        gyro_flu = st.angular_velocity
        np.testing.assert_allclose(reply['gyro'], [gyro_flu[0], -gyro_flu[1], -gyro_flu[2]], atol=1e-9)


def test_lock_step_advance_by_one_over_frame_rate(rig):
    t0 = rig.world.time
    for n in range(1, 41):
        reply = rig.frame([1000] * 4)
        assert reply['timestamp'] == pytest.approx(n / 400, abs=1e-12)
    assert rig.world.time - t0 == pytest.approx(40 / 400, abs=1e-12)
    assert rig.sitl.time_s == pytest.approx(0.1, abs=1e-12)        # SITL's clock follows exactly
    rig.sitl.frame_rate = 200                                       # SIM_RATE_HZ changed
    for n in range(1, 11):
        reply = rig.frame([1000] * 4)
        assert reply['timestamp'] == pytest.approx(0.1 + n / 200, abs=1e-12)
    # SITL did not get (parse) the last reply: it re-sends that frame; same reply, physics not stepped
    t, raw = rig.world.time, rig.sitl.raw
    rig.sitl.frame_count -= 1
    rig.sitl.send([1000] * 4)
    rig.pump()
    assert rig.events[-1] == 'duplicate'
    assert rig.sitl.receive(1.0) is not None and rig.sitl.raw == raw
    assert rig.world.time == t
    assert rig.server.counters['duplicate_frames'] == 1
    rig.sitl.frame_count += 3                                       # three frames lost on the way
    rig.frame([1000] * 4)
    assert rig.server.counters['missed_frames'] == 3
    assert rig.world.time == pytest.approx(t + 1 / 200, abs=1e-12)


def test_frame_count_reset_means_sitl_restart(rig):
    resets = []
    rig.server.on_restart = lambda: resets.append(rig.world.time)
    rig.airborne(2.0)
    for _ in range(100):
        rig.frame([rig.hover_pwm] * 4)
    rig.sitl.restart()
    reply = rig.frame([1000] * 4)
    assert rig.events[-1] == 'restart' and len(resets) == 1
    assert reply['timestamp'] == pytest.approx(1 / 400)             # new SITL session starts at t = 0
    assert rig.server.counters['sitl_restarts'] == 1
    reply = rig.frame([1000] * 4)
    assert reply['timestamp'] == pytest.approx(2 / 400)


@pytest.mark.parametrize('data, reason', [
    (struct.pack('<HHI16H', 12345, 400, 0, *[1000] * 16), 'bad_magic'),
    (struct.pack('<HHI16H', 18458, 400, 0, *[1000] * 16)[:30], 'bad_length'),
    (struct.pack('<HHI16H', 18458, 400, 0, *[1000] * 16) + b'\0', 'bad_length'),
    (struct.pack('<HHI16H', 29569, 400, 0, *[1000] * 16), 'bad_length'),       # 32-channel magic, 16 channels
    (struct.pack('<HHI16H', 18458, 0, 0, *[1000] * 16), 'bad_frame_rate'),
    (b'', 'bad_length'),
    (b'\xff' * 40, 'bad_magic'),
])
def test_malformed_packets_are_dropped_and_counted(rig, data, reason):
    rig.sitl.send_raw(data)
    assert rig.server.poll(1.0) == 'dropped'
    assert rig.server.counters[reason] == 1
    assert rig.sitl.receive(0.05) is None                            # no reply to garbage
    assert rig.server.counters['replies'] == 0 and rig.world.time == 0.0   # physics not stepped
    reply = rig.frame([1000] * 4)                                    # and the link still works
    assert reply['timestamp'] == pytest.approx(1 / 400)


def test_32_channel_packets_are_served(rig):
    rig.sitl.send_raw(struct.pack('<HHI32H', 29569, 400, 0, *[1000] * 32))
    assert rig.server.poll(1.0) == 'step'
    assert rig.sitl.receive(1.0) is not None


def test_shipped_parm_file_matches_the_motor_model():
    from pathlib import Path

    from assist_sim.core.config import VehicleConfig
    from assist_sim.core.quad_json import QuadJsonConfig
    parm = Path(__file__).resolve().parents[1] / 'ros2_ws/src/assist_sim/config/ardupilot_json_quad.parm'
    params = {}
    for line in parm.read_text().splitlines():
        assert len(line) < 100, line                     # AP_Param's defaults-file line buffer
        if line and not line.startswith('#'):
            name, value = line.split()
            params[name] = float(value)
    c, veh = QuadJsonConfig(), VehicleConfig()
    assert (params['FRAME_CLASS'], params['FRAME_TYPE']) == (1, 1)           # quad, X
    assert params['MOT_THST_HOVER'] == pytest.approx(c.hover_throttle(veh.mass_kg), abs=0.005)
    assert params['MOT_THST_EXPO'] == c.thrust_expo
    assert (params['MOT_SPIN_MIN'], params['MOT_SPIN_MAX']) == (c.spin_min, c.spin_max)
    assert (params['MOT_PWM_MIN'], params['MOT_PWM_MAX']) == (c.pwm_min, c.pwm_max)
    # spinning-when-armed PWM is above the runner's disarmed threshold, MOT_PWM_MIN below it
    armed_idle = params['MOT_PWM_MIN'] + params['MOT_SPIN_ARM'] * (params['MOT_PWM_MAX'] - params['MOT_PWM_MIN'])
    assert params['MOT_PWM_MIN'] <= JsonRunnerConfig().disarmed_pwm_max < armed_idle
    assert params['SIM_RATE_HZ'] == 800 and params['RNGFND1_TYPE'] == 100 and params['RNGFND1_ORIENT'] == 25
    assert params['RNGFND1_GNDCLR'] == pytest.approx(veh.leg_length_m, abs=0.01)
    assert params['GUID_TIMEOUT'] > 0


def test_camera_is_rigidly_mounted_and_tilts_with_the_airframe(rig):
    """Rendered depth on the optical axis over the flat floor: H / cos(tilt) once the airframe rolls."""
    w = rig.world
    off = w.cfg.camera.offset_below_base_m
    for roll_deg in (0.0, 20.0):
        roll = math.radians(roll_deg)
        w._bc.resetBasePositionAndOrientation(w._vehicle, [0.0, 0.0, 3.0], w._bc.getQuaternionFromEuler([roll, 0, 0]))
        frame = w.render()
        h, wd = frame.depth.shape
        centre = float(frame.depth[h // 2 - 1:h // 2 + 1, wd // 2 - 1:wd // 2 + 1].mean())
        cam_z = 3.0 - off * math.cos(roll)
        assert centre == pytest.approx(cam_z / math.cos(roll), abs=0.02), roll_deg


def test_reset_while_motors_spin_is_deferred_until_disarmed():
    from assist_sim.core.runner import RunnerConfig
    from assist_sim.json_backend import JsonSimRunner
    world = LandingWorld(WorldConfig(turbulence=TurbulenceConfig(enabled=False)), seed=0)
    runner = JsonSimRunner(world, RunnerConfig(airborne_start=False, camera_rate_hz=0.0), JsonBackendConfig(port=0),
                           JsonRunnerConfig(poll_timeout_s=0.02))
    sitl = SitlStandIn(port=runner.server.address[1])
    try:
        runner.reset(7)
        episode = world.episode
        outs = []
        for _ in range(5):                                  # armed, idling on the ground (below hover)
            sitl.send([1200] * 4)
            outs.append(runner.step())
            assert sitl.receive(1.0) is not None
        runner.reset()
        assert runner.reset_pending and world.episode == episode          # not while the motors spin
        sitl.send([1000] * 4)                                             # disarmed: MOT_PWM_MIN
        out = runner.step()
        assert sitl.receive(1.0) is not None
        assert out.new_episode and not runner.reset_pending and world.episode == episode + 1
        assert not any(o.new_episode for o in outs)
    finally:
        sitl.close()
        runner.close()
        world.close()


def test_non_finite_state_is_never_sent(rig, monkeypatch):
    good = rig.model.sensors
    monkeypatch.setattr(rig.model, 'sensors', lambda *a, **k: {**good(*a, **k), 'position': [float('nan'), 0.0, 0.0]})
    rig.sitl.send([1000] * 4)
    assert rig.server.poll(1.0) == 'step'
    assert rig.sitl.receive(0.1) is None and rig.server.counters['reply_errors'] == 1
    monkeypatch.setattr(rig.model, 'sensors', good)
    rig.sitl.send([1000] * 4)                      # SITL re-sends the frame it got no reply for
    assert rig.server.poll(1.0) == 'step'          # no reply was stored, so it is served afresh
    assert rig.sitl.receive(1.0) is not None
