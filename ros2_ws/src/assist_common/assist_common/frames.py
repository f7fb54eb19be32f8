"""Frames and rotations shared by every package (numpy only: no rclpy, no pybullet, no scipy).

ROS (REP-103/105): world `odom` is East-North-Up, body `base_link` is Forward-Left-Up, yaw is
measured counter-clockwise from East. ArduPilot: LOCAL_NED is North-East-Down, body is
Forward-Right-Down, yaw (heading) is measured clockwise from North. The downward camera's optical
frame (ARCHITECTURE.md): optical x = body -y, optical y = body -x, optical z = body -z.

Quaternions are (x, y, z, w) as in ROS messages unless a name says otherwise. Every function takes
and returns plain numpy arrays (float64); vectors are shape (3,). `quat_to_matrix` and
`yaw_rotation` are closed forms (they run per frame in the renderer, the pad map and the policy, and
the renderer's pixels depend on their exact values); so are Euler angles to a matrix and a matrix to a
quaternion (they agree with scipy's Rotation to 1e-15: tested), which keeps scipy's ~0.5 s import out of
every node's start-up.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

# Optical frame axes expressed in base_link (FLU): x_opt = -y_body, y_opt = -x_body, z_opt = -z_body.
R_BODY_FROM_OPTICAL = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

# Axis permutation world ENU <-> NED (its own inverse): x_ned = y_enu, y_ned = x_enu, z_ned = -z_enu.
_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# Body FLU <-> FRD (its own inverse): x same, y and z flipped.
_FLU_FRD = np.diag([1.0, -1.0, -1.0])


def _vec3(v: Sequence[float]) -> np.ndarray:
    """Validate and convert a 3-vector."""
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f'expected a 3-vector, got shape {a.shape}')
    return a


def wrap_pi(angle: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (float(angle) + math.pi) % (2.0 * math.pi) - math.pi


def enu_to_ned(v: Sequence[float]) -> np.ndarray:
    """World vector ENU -> NED."""
    return _ENU_NED @ _vec3(v)


def ned_to_enu(v: Sequence[float]) -> np.ndarray:
    """World vector NED -> ENU."""
    return _ENU_NED @ _vec3(v)


def flu_to_frd(v: Sequence[float]) -> np.ndarray:
    """Body vector FLU -> FRD (also body angular rates)."""
    return _FLU_FRD @ _vec3(v)


def frd_to_flu(v: Sequence[float]) -> np.ndarray:
    """Body vector FRD -> FLU (also body angular rates)."""
    return _FLU_FRD @ _vec3(v)


def yaw_enu_to_ned(yaw_enu: float) -> float:
    """ROS yaw (CCW from East) -> NED heading (CW from North), wrapped to [-pi, pi)."""
    return wrap_pi(math.pi / 2.0 - float(yaw_enu))


def yaw_ned_to_enu(yaw_ned: float) -> float:
    """NED heading (CW from North) -> ROS yaw (CCW from East), wrapped to [-pi, pi)."""
    return wrap_pi(math.pi / 2.0 - float(yaw_ned))


def yaw_rotation(yaw: float) -> np.ndarray:
    """Right-handed 3x3 rotation matrix about +z by `yaw` radians."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Unit quaternion (x, y, z, w) -> 3x3 rotation matrix (not normalised: see unit_quat_to_matrix)."""
    x, y, z, w = (float(v) for v in q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def unit_quat_to_matrix(q_xyzw: Sequence[float]) -> np.ndarray:
    """Quaternion (x, y, z, w) from outside (a message), normalised -> rotation matrix.

    ValueError when it is not finite or zero."""
    x, y, z, w = (float(c) for c in q_xyzw)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if n == 0.0 or not math.isfinite(n):
        raise ValueError('quaternion must be finite and non-zero')
    return quat_to_matrix((x / n, y / n, z / n, w / n))


def heading(q: Sequence[float]) -> float:
    """Heading (rad, CCW about +z) of quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in q)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def rotate_xy(xy: Sequence[float], yaw: float) -> np.ndarray:
    """Horizontal vector `xy` rotated by `yaw` (rad): base_link -> odom for the vehicle's heading, -yaw back."""
    return yaw_rotation(yaw)[:2, :2] @ np.asarray(xy, dtype=float)[:2]


def flu_to_enu(v_flu: Sequence[float], yaw_enu: float) -> np.ndarray:
    """Body FLU vector of a level vehicle with ROS yaw `yaw_enu` -> world ENU."""
    return yaw_rotation(yaw_enu) @ _vec3(v_flu)


def enu_to_flu(v_enu: Sequence[float], yaw_enu: float) -> np.ndarray:
    """World ENU vector -> body FLU of a level vehicle with ROS yaw `yaw_enu`."""
    return yaw_rotation(yaw_enu).T @ _vec3(v_enu)


def frd_to_ned(v_frd: Sequence[float], yaw_ned: float) -> np.ndarray:
    """Body FRD vector of a level vehicle with NED heading `yaw_ned` -> world NED.

    This is ArduCopter's rotate_body_frame_to_NE for MAV_FRAME_BODY_(OFFSET_)NED velocities.
    """
    return yaw_rotation(yaw_ned) @ _vec3(v_frd)


def ned_to_frd(v_ned: Sequence[float], yaw_ned: float) -> np.ndarray:
    """World NED vector -> body FRD of a level vehicle with NED heading `yaw_ned`."""
    return yaw_rotation(yaw_ned).T @ _vec3(v_ned)


def flu_velocity_to_ned(v_flu: Sequence[float], yaw_enu: float) -> np.ndarray:
    """Body FLU velocity (vehicle held at ROS yaw `yaw_enu`) -> LOCAL_NED velocity."""
    return enu_to_ned(flu_to_enu(v_flu, yaw_enu))


def euler_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Z-Y-X (yaw, pitch, roll) Euler angles -> rotation matrix world_from_body."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def matrix_to_euler(r: np.ndarray) -> tuple[float, float, float]:
    """Rotation matrix world_from_body -> Z-Y-X Euler (roll, pitch, yaw)."""
    pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
    roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
    yaw = math.atan2(float(r[1, 0]), float(r[0, 0]))
    return roll, pitch, yaw


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (x, y, z, w) with w >= 0."""
    m = np.asarray(r, dtype=float).reshape(3, 3)
    # Shepperd's method: start from the largest of 4w^2, 4x^2, 4y^2, 4z^2 (no division by a small number)
    diag = (m[0, 0] + m[1, 1] + m[2, 2], m[0, 0], m[1, 1], m[2, 2])
    k = int(np.argmax(diag))
    if k == 0:
        w = 0.5 * math.sqrt(max(0.0, 1.0 + diag[0]))
        q = np.array([(m[2, 1] - m[1, 2]) / (4 * w), (m[0, 2] - m[2, 0]) / (4 * w), (m[1, 0] - m[0, 1]) / (4 * w), w])
    elif k == 1:
        x = 0.5 * math.sqrt(max(0.0, 1.0 + m[0, 0] - m[1, 1] - m[2, 2]))
        q = np.array([x, (m[0, 1] + m[1, 0]) / (4 * x), (m[0, 2] + m[2, 0]) / (4 * x), (m[2, 1] - m[1, 2]) / (4 * x)])
    elif k == 2:
        y = 0.5 * math.sqrt(max(0.0, 1.0 - m[0, 0] + m[1, 1] - m[2, 2]))
        q = np.array([(m[0, 1] + m[1, 0]) / (4 * y), y, (m[1, 2] + m[2, 1]) / (4 * y), (m[0, 2] - m[2, 0]) / (4 * y)])
    else:
        z = 0.5 * math.sqrt(max(0.0, 1.0 - m[0, 0] - m[1, 1] + m[2, 2]))
        q = np.array([(m[0, 2] + m[2, 0]) / (4 * z), (m[1, 2] + m[2, 1]) / (4 * z), z, (m[1, 0] - m[0, 1]) / (4 * z)])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0.0 else q


def attitude_ned_frd_to_enu_flu(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ArduPilot ATTITUDE (NED/FRD Euler) -> rotation matrix odom(ENU)_from_base_link(FLU)."""
    return _ENU_NED @ euler_to_matrix(roll, pitch, yaw) @ _FLU_FRD


def attitude_enu_flu_to_ned_frd(r_enu_flu: np.ndarray) -> tuple[float, float, float]:
    """Rotation matrix odom(ENU)_from_base_link(FLU) -> ArduPilot (roll, pitch, yaw) NED/FRD."""
    return matrix_to_euler(_ENU_NED @ np.asarray(r_enu_flu, dtype=float) @ _FLU_FRD)


def nearest_xy(points: np.ndarray, xy: Sequence[float]) -> int:
    """Index of the point (rows of x, y[, z]) horizontally nearest to `xy` (its first two values)."""
    pts = np.asarray(points, dtype=float)
    return int(np.argmin(np.linalg.norm(pts[:, :2] - np.asarray(xy, dtype=float)[:2], axis=1)))
