"""Frames and rotations (assist_common.frames): FLU<->FRD, ENU<->NED, yaw conventions, quaternions, Euler angles."""
import math

import numpy as np
import pytest

from assist_common import frames as F


def test_body_flu_frd_fixed_vectors():
    np.testing.assert_allclose(F.flu_to_frd([1.0, 2.0, 3.0]), [1.0, -2.0, -3.0])
    np.testing.assert_allclose(F.frd_to_flu([1.0, -2.0, -3.0]), [1.0, 2.0, 3.0])


def test_world_enu_ned_fixed_vectors():
    np.testing.assert_allclose(F.enu_to_ned([1.0, 2.0, 3.0]), [2.0, 1.0, -3.0])
    np.testing.assert_allclose(F.ned_to_enu([2.0, 1.0, -3.0]), [1.0, 2.0, 3.0])


@pytest.mark.parametrize('yaw_enu, yaw_ned', [
    (0.0, math.pi / 2),          # facing East
    (math.pi / 2, 0.0),          # facing North
    (math.pi, -math.pi / 2),     # facing West
    (-math.pi / 2, -math.pi),    # facing South (wrapped to -pi)
])
def test_yaw_conventions(yaw_enu, yaw_ned):
    assert F.yaw_enu_to_ned(yaw_enu) == pytest.approx(yaw_ned)
    assert F.wrap_pi(F.yaw_ned_to_enu(yaw_ned) - yaw_enu) == pytest.approx(0.0, abs=1e-12)


def test_sim_vehicle_facing_east_forward_is_ned_east_and_up_is_negative_down():
    np.testing.assert_allclose(F.flu_velocity_to_ned([1.0, 0.0, 0.0], 0.0), [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(F.flu_velocity_to_ned([0.0, 1.0, 0.0], 0.0), [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(F.flu_velocity_to_ned([0.0, 0.0, 1.0], 0.0), [0.0, 0.0, -1.0], atol=1e-12)


def test_yawed_vehicle_facing_north():
    yaw = math.pi / 2
    np.testing.assert_allclose(F.flu_velocity_to_ned([1.0, 0.0, 0.0], yaw), [1.0, 0.0, 0.0], atol=1e-12)
    # left of a north-facing vehicle is west = NED -y
    np.testing.assert_allclose(F.flu_velocity_to_ned([0.0, 1.0, 0.0], yaw), [0.0, -1.0, 0.0], atol=1e-12)


def test_yawed_vehicle_30_degrees_fixed_vector():
    yaw = math.radians(30.0)  # ROS yaw: 30 deg CCW from East
    v = F.flu_to_enu([2.0, 0.0, 0.0], yaw)
    np.testing.assert_allclose(v, [2.0 * math.cos(yaw), 2.0 * math.sin(yaw), 0.0], atol=1e-12)
    np.testing.assert_allclose(F.enu_to_flu(v, yaw), [2.0, 0.0, 0.0], atol=1e-12)
    # NED heading of that vehicle is 60 deg; ArduCopter's body->NE rotation gives the same vector
    assert math.degrees(F.yaw_enu_to_ned(yaw)) == pytest.approx(60.0)
    np.testing.assert_allclose(F.frd_to_ned([2.0, 0.0, 0.0], F.yaw_enu_to_ned(yaw)), F.enu_to_ned(v), atol=1e-12)


def test_flu_route_equals_frd_route_for_random_vectors():
    rng = np.random.default_rng(3)
    for _ in range(50):
        v = rng.normal(size=3)
        yaw = rng.uniform(-math.pi, math.pi)
        a = F.flu_velocity_to_ned(v, yaw)
        b = F.frd_to_ned(F.flu_to_frd(v), F.yaw_enu_to_ned(yaw))
        np.testing.assert_allclose(a, b, atol=1e-12)
        np.testing.assert_allclose(F.ned_to_frd(b, F.yaw_enu_to_ned(yaw)), F.flu_to_frd(v), atol=1e-12)


def test_attitude_level_east_is_identity_in_ros():
    r = F.attitude_ned_frd_to_enu_flu(0.0, 0.0, math.pi / 2)
    np.testing.assert_allclose(r, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(F.matrix_to_quaternion(r), [0.0, 0.0, 0.0, 1.0], atol=1e-12)


def test_attitude_nose_up_and_right_wing_down():
    nose_up = F.attitude_ned_frd_to_enu_flu(0.0, 0.2, math.pi / 2)
    assert (nose_up @ [1.0, 0.0, 0.0])[2] == pytest.approx(math.sin(0.2))
    right_down = F.attitude_ned_frd_to_enu_flu(0.3, 0.0, math.pi / 2)
    assert (right_down @ [0.0, -1.0, 0.0])[2] == pytest.approx(-math.sin(0.3))


def test_attitude_round_trip_and_quaternion_round_trip():
    rng = np.random.default_rng(7)
    for _ in range(50):
        roll, pitch, yaw = rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), rng.uniform(-3.1, 3.1)
        r = F.attitude_ned_frd_to_enu_flu(roll, pitch, yaw)
        np.testing.assert_allclose(F.attitude_enu_flu_to_ned_frd(r), [roll, pitch, yaw], atol=1e-9)
        np.testing.assert_allclose(F.unit_quat_to_matrix(F.matrix_to_quaternion(r)), r, atol=1e-9)
        # ROS yaw of the body x axis matches the converted heading
        fwd = r @ [1.0, 0.0, 0.0]
        assert F.wrap_pi(math.atan2(fwd[1], fwd[0]) - F.yaw_ned_to_enu(yaw)) == pytest.approx(0.0, abs=1e-9)


def test_bad_shapes_rejected():
    with pytest.raises(ValueError):
        F.enu_to_ned([1.0, 2.0])
    with pytest.raises(ValueError):
        F.unit_quat_to_matrix([0.0, 0.0, 0.0, 0.0])


# Closed forms the module had before scipy's Rotation took over Euler angles and matrix -> quaternion:
# the results must stay the same (to rounding).
def _euler_to_matrix_closed_form(roll, pitch, yaw):
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return F.yaw_rotation(yaw) @ ry @ rx


def _matrix_to_quaternion_closed_form(m):
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    qa = np.array(q) / np.linalg.norm(q)
    return -qa if qa[3] < 0.0 else qa


def test_euler_and_quaternion_conversions_agree_with_scipy_and_the_textbook_forms():
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(11)
    angles = [(rng.uniform(-3.1, 3.1), rng.uniform(-1.5, 1.5), rng.uniform(-3.1, 3.1)) for _ in range(200)]
    angles += [(0.0, 0.0, math.pi), (math.pi, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, math.pi / 2 - 1e-9, 0.3),
               (math.pi, 0.0, math.pi), (0.0, math.pi, 0.0), (math.pi / 2, 0.0, math.pi)]   # w ~ 0: x, y or z leads
    for roll, pitch, yaw in angles:
        r = F.euler_to_matrix(roll, pitch, yaw)
        np.testing.assert_allclose(r, Rotation.from_euler('ZYX', [yaw, pitch, roll]).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(r, _euler_to_matrix_closed_form(roll, pitch, yaw), atol=1e-12)
        q = F.matrix_to_quaternion(r)
        assert q[3] >= 0.0 and abs(np.linalg.norm(q) - 1.0) < 1e-12
        ref = Rotation.from_matrix(r).as_quat()
        np.testing.assert_allclose(q, -ref if ref[3] < 0 else ref, atol=1e-9)
        np.testing.assert_allclose(q, _matrix_to_quaternion_closed_form(r), atol=1e-9)
        np.testing.assert_allclose(F.quat_to_matrix(q), r, atol=1e-12)


def test_quaternion_helpers_agree_with_scipy():
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(3)
    for q in Rotation.random(100, random_state=5).as_quat():
        np.testing.assert_allclose(F.quat_to_matrix(q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
        np.testing.assert_allclose(F.unit_quat_to_matrix(3.0 * q), Rotation.from_quat(q).as_matrix(), atol=1e-12)
        assert F.heading(q) == pytest.approx(Rotation.from_quat(q).as_euler('ZYX')[0], abs=1e-9)
        yaw = rng.uniform(-3.1, 3.1)
        xy = rng.normal(size=2)
        np.testing.assert_allclose(F.rotate_xy(xy, yaw), (Rotation.from_euler('z', yaw).as_matrix() @ [*xy, 0.0])[:2],
                                   atol=1e-12)
        np.testing.assert_allclose(F.rotate_xy(F.rotate_xy(xy, yaw), -yaw), xy, atol=1e-12)


def test_optical_frame_axes():
    # optical x = body -y (right), optical y = body -x (image top = forward), optical z = body -z (down)
    np.testing.assert_array_equal(F.R_BODY_FROM_OPTICAL @ [1.0, 0.0, 0.0], [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(F.R_BODY_FROM_OPTICAL @ [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0])
    np.testing.assert_array_equal(F.R_BODY_FROM_OPTICAL @ [0.0, 0.0, 1.0], [0.0, 0.0, -1.0])
    assert np.linalg.det(F.R_BODY_FROM_OPTICAL) == pytest.approx(1.0)
