"""Pilot station core: browser messages -> held keys -> body-FLU velocity; landing, scene, camera, assist."""
import json
import math

import numpy as np
import pytest

from assist_station.station_core import (AssistMonitor, CommandGate, InputError, KeyState, MessageError,
                                         OncePerReason, StationConfig, camera_frame_bytes, camera_payload,
                                         command_from_keys, landing_feedback, parse_client_message, parse_landing,
                                         scene_from_boxes)


def keys(down, seq=None):
    msg = {'type': 'keys', 'down': down}
    if seq is not None:
        msg['seq'] = seq
    return json.dumps(msg)


@pytest.mark.parametrize('code, expected', [
    ('KeyW', [1.0, 0, 0]), ('KeyS', [-1.0, 0, 0]), ('KeyA', [0, 1.0, 0]), ('KeyD', [0, -1.0, 0]),
    ('ArrowUp', [0, 0, 0.5]), ('ArrowDown', [0, 0, -0.5]), ('Space', [0, 0, 0])])
def test_each_key_maps_to_the_teleop_bindings(code, expected):
    np.testing.assert_allclose(command_from_keys([code], 1.0, 0.5), expected)


def test_keys_combine_across_axes_and_the_last_key_on_an_axis_wins():
    np.testing.assert_allclose(command_from_keys(['KeyW', 'KeyA', 'ArrowUp'], 2.0, 0.5), [2.0, 2.0, 0.5])
    np.testing.assert_allclose(command_from_keys(['KeyW', 'KeyS'], 1.0, 0.5), [-1.0, 0, 0])
    np.testing.assert_allclose(command_from_keys(['KeyS', 'KeyW'], 1.0, 0.5), [1.0, 0, 0])


def test_space_held_stops_everything():
    np.testing.assert_allclose(command_from_keys(['KeyW', 'Space', 'ArrowUp'], 1.0, 0.5), [0, 0, 0])


def test_parse_keys_message_splits_known_and_unknown_keys():
    m = parse_client_message(keys(['KeyW', 'KeyQ', 'KeyW', 'ArrowDown', 'Escape'], seq=7), 1024)
    assert m.down == ('KeyW', 'ArrowDown') and m.unknown == ('KeyQ', 'Escape') and m.seq == 7


@pytest.mark.parametrize('raw, reason', [
    ('not json', 'not JSON'), ('[1, 2]', 'JSON object'), ('{"type": "fly"}', 'unknown message type'),
    ('{"type": "keys"}', "'down'"), ('{"type": "keys", "down": "KeyW"}', "'down'"),
    ('{"type": "keys", "down": [1, 2]}', "'down'"), ('{"type": "keys", "down": [], "seq": "x"}', "'seq'"),
    ('{"type": "keys", "down": [], "seq": true}', "'seq'"),
    (json.dumps({'type': 'keys', 'down': ['KeyW'] * 17}), 'at most 16'),
    ('[' * 5000 + ']' * 5000, 'not JSON'),
])
def test_malformed_messages_are_rejected_with_a_reason(raw, reason):
    with pytest.raises(MessageError) as err:
        parse_client_message(raw, 1_000_000)
    assert err.value.kind == 'malformed' and reason in str(err.value)


def test_oversized_and_binary_messages_are_rejected():
    with pytest.raises(MessageError) as err:
        parse_client_message(keys(['KeyW']) + ' ' * 2000, 1024)
    assert err.value.kind == 'oversized' and '1024' in str(err.value)
    with pytest.raises(MessageError) as err:
        parse_client_message(b'\x00\x01', 1024)
    assert err.value.kind == 'malformed'


def test_key_state_expires_without_refresh_and_releases_on_demand():
    ks = KeyState(StationConfig(speed=1.5, speed_z=0.5, key_timeout_s=1.0))
    np.testing.assert_allclose(ks.set(['KeyW', 'ArrowUp', 'Bogus'], now=10.0), [1.5, 0, 0.5])
    assert ks.held(10.5) == ('KeyW', 'ArrowUp')
    np.testing.assert_allclose(ks.command(10.9), [1.5, 0, 0.5])
    np.testing.assert_allclose(ks.command(11.1), [0, 0, 0])     # page silent > 1 s: released
    assert ks.held(11.2) == ()
    ks.set(['KeyD'], now=20.0)
    ks.release_all()
    np.testing.assert_allclose(ks.command(20.0), [0, 0, 0])


def test_a_stop_from_another_page_zeros_the_command_until_the_held_keys_are_pressed_again():
    ks = KeyState(StationConfig(speed=1.0, speed_z=0.5, key_timeout_s=1.0))
    ks.set(['KeyW', 'ArrowUp'], now=0.0)
    viewer = object()
    np.testing.assert_allclose(ks.set_stop(viewer, True, 0.1), [0, 0, 0])
    assert ks.stopped(0.2)
    np.testing.assert_allclose(ks.set(['KeyW', 'ArrowUp', 'KeyA'], 0.3), [0, 0, 0])   # keys while stopped: zero
    np.testing.assert_allclose(ks.set_stop(viewer, False, 0.4), [0, 0, 0])             # held through the stop
    np.testing.assert_allclose(ks.set(['ArrowUp'], 0.5), [0, 0, 0])
    np.testing.assert_allclose(ks.set(['ArrowUp', 'KeyS'], 0.6), [-1.0, 0, 0])          # a new press counts
    np.testing.assert_allclose(ks.set(['KeyS'], 0.7), [-1.0, 0, 0])
    np.testing.assert_allclose(ks.set(['KeyS', 'ArrowUp'], 0.8), [-1.0, 0, 0.5])       # pressed again: counts
    ks.set_stop(viewer, True, 1.0)
    assert ks.stopped(1.9) and not ks.stopped(2.1)              # a stop not refreshed expires like a key
    assert ks.held(2.1) == ()


def test_command_gate_publishes_changes_only_and_bounds_a_flood():
    gate = CommandGate(rate_hz=50.0, burst=10)
    w, zero = np.array([1.0, 0, 0]), np.zeros(3)
    assert gate.immediate(w, 0.0) and not gate.immediate(w, 0.001)          # unchanged: left to the timer
    gate.sent(w)
    assert not gate.immediate(w, 0.5)
    assert gate.immediate(zero, 0.6) and gate.immediate(w, 0.61)
    toggles = sum(gate.immediate(zero if i % 2 else w, 1.0 + i / 900) for i in range(900))   # 900 changes in 1 s
    assert 50 <= toggles <= 61, toggles


def test_once_per_reason():
    once = OncePerReason(max_reasons=2)
    assert once('a') and not once('a') and once('b') and not once('c')


def test_station_config_rejects_bad_values():
    with pytest.raises(ValueError, match='speed'):
        StationConfig(speed=float('nan'))
    with pytest.raises(ValueError, match='key_timeout_s'):
        StationConfig(key_timeout_s=0)


def test_assist_monitor_states():
    m = AssistMonitor(timeout_s=0.5, threshold=0.25)
    assert m.state(0.0) == 'off'
    assert m.note([0.1, 0.0, 0.0], 1.0) and m.state(1.2) == 'standby'
    assert m.note([0.3, 0.1, 0.0], 2.0) and m.state(2.4) == 'acting'
    assert m.state(2.6) == 'off'
    assert not m.note([math.nan, 0, 0], 3.0) and m.state(3.0) == 'off'


LANDING = {'episode': 4, 'goal_index': 2, 'landed_index': 3, 'nearest_index': 3, 'error_m': 3.91,
           'nearest_error_m': 0.2, 'success': False, 'crash': False, 'duration_s': 21.5, 'assisted': True,
           'outcome': 'wrong_pad', 'reason': 'landed'}


def test_landing_feedback_depends_on_the_mode():
    landing = parse_landing(json.dumps(LANDING))
    fb = landing_feedback(landing, 'practice')
    assert fb['show'] and fb['text'] == 'Landed on platform 4, goal was 3 - 3.91 m from the goal centre'
    study = landing_feedback(landing, 'study')
    assert not study['show'] and study['text'] == 'Landing recorded' and 'error_m' not in study
    ok = landing_feedback(dict(landing, success=True, landed_index=2, error_m=0.12), 'free')
    assert ok['success'] and ok['text'].startswith('Landed on the goal platform - 0.12 m')
    crash = landing_feedback(dict(landing, crash=True, landed_index=None), 'practice')
    assert crash['crash'] and crash['text'].startswith('Crashed')


@pytest.mark.parametrize('text', ['nope', '[]', '{"episode": 1}', '[' * 100000 + ']' * 100000,
                                  json.dumps(dict(LANDING, goal_index='two')), json.dumps(dict(LANDING, goal_index=-1)),
                                  json.dumps(dict(LANDING, goal_index=2.5)), json.dumps(dict(LANDING, goal_index=None)),
                                  json.dumps(dict(LANDING, landed_index='3')), json.dumps(dict(LANDING, success='yes')),
                                  json.dumps(dict(LANDING, crash=1)), json.dumps(dict(LANDING, episode=[1])),
                                  json.dumps(dict(LANDING, outcome='x' * 20000))])
def test_unusable_landing_messages_raise(text):
    with pytest.raises(InputError) as err:
        parse_landing(text)
    assert len(str(err.value)) < 200 and '\n' not in str(err.value)


def test_a_valid_landing_always_gives_feedback():
    for mode in ('practice', 'study', 'free'):
        for landed in (None, 0, 4):
            landing = parse_landing(json.dumps(dict(LANDING, landed_index=landed, outcome={'x': 1})))
            assert 'outcome' not in landing and landing_feedback(landing, mode)['text']


def test_non_finite_landing_error_is_dropped():
    assert parse_landing(json.dumps(dict(LANDING, error_m=float('nan'))))['error_m'] is None


def box(ns, i, size=(1.0, 1.2, 0.8)):
    return {'ns': ns, 'id': i, 'p': (4.0 * i, 0.0, 0.4), 'q': (0, 0, 0, 1), 's': size, 'c': (0.5, 0.4, 0.3)}


def test_scene_from_boxes_lists_platforms_and_goal():
    scene = scene_from_boxes([box('platforms', i) for i in (2, 0, 1)] + [box('goal', 1)])
    assert [p['id'] for p in scene['platforms']] == [0, 1, 2] and scene['goal'] == 1
    assert scene['platforms'][2]['p'] == [8.0, 0.0, 0.4]
    assert scene_from_boxes([box('platforms', 0), box('goal', 7)])['goal'] is None   # goal not a platform


def test_scene_with_bad_boxes_is_rejected():
    with pytest.raises(ValueError):
        scene_from_boxes([box('platforms', 0, size=(1.0, 0.0, 1.0))])
    with pytest.raises(ValueError):
        scene_from_boxes([dict(box('platforms', 0), p=(math.inf, 0, 0))])


def test_camera_payload_converts_and_subsamples():
    img = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    padded = np.zeros((4, 20), np.uint8)
    padded[:, :18] = img.reshape(4, 18)                        # row step larger than width * 3
    w, h, data = camera_payload(6, 4, 'rgb8', 20, padded.tobytes(), max_width=160)
    assert (w, h) == (6, 4) and data == img.tobytes()
    w, h, data = camera_payload(6, 4, 'bgr8', 18, img.tobytes(), max_width=160)
    assert data == img[:, :, ::-1].tobytes()
    w, h, data = camera_payload(6, 4, 'rgb8', 18, img.tobytes(), max_width=3)
    assert (w, h) == (3, 2) and data == img[::2, ::2].tobytes()
    mono = np.array([[7, 9]], np.uint8)
    assert camera_payload(2, 1, 'mono8', 2, mono.tobytes(), 160)[2] == bytes([7, 7, 7, 9, 9, 9])
    frame = camera_frame_bytes(3, 2, b'x' * 18)
    assert frame[:4] == bytes([3, 0, 2, 0]) and len(frame) == 22


def test_a_tall_or_wide_image_is_subsampled_to_fit_the_inset_frame():
    w, h, data = camera_payload(1, 70000, 'mono8', 1, bytes(70000), max_width=160)
    assert (w, h) == (1, 160) and len(camera_frame_bytes(w, h, data)) == 4 + 160 * 3
    w, h, data = camera_payload(70000, 1, 'mono8', 70000, bytes(70000), max_width=160)
    assert (w, h) == (160, 1)
    w, h, _ = camera_payload(640, 480, 'mono8', 640, bytes(640 * 480), max_width=160)
    assert (w, h) == (160, 120)
    with pytest.raises(InputError):
        camera_frame_bytes(1, 70000, bytes(3 * 70000))


@pytest.mark.parametrize('args', [(6, 4, '32FC1', 24, b'\0' * 96), (6, 4, 'rgb8', 18, b'\0' * 10),
                                  (6, 4, 'rgb8', 5, b'\0' * 100), (0, 4, 'rgb8', 0, b'')])
def test_camera_payload_rejects_unusable_images(args):
    with pytest.raises(ValueError):
        camera_payload(*args, max_width=160)


def test_the_station_never_imports_pybullet_or_torch():
    import subprocess
    import sys
    code = ('import sys, assist_station.pilot_station, assist_station.server, assist_station.testing; '
            'print(sorted(m for m in ("pybullet", "torch") if m in sys.modules))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == '[]'
