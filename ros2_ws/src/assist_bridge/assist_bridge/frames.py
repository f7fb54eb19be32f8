"""Frame conventions between ROS (ENU world, FLU body) and ArduPilot MAVLink (NED world, FRD body).

ROS (REP-103/105): world `odom` is East-North-Up, body `base_link` is Forward-Left-Up, yaw is
measured counter-clockwise from East. ArduPilot: LOCAL_NED is North-East-Down, body is
Forward-Right-Down, yaw (heading) is measured clockwise from North. Pure numpy, no rclpy.

Every function takes and returns plain numpy arrays (float64); vectors are shape (3,).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from assist_sim.core.geometry import unit_quat_to_matrix as quaternion_to_matrix  # noqa: F401 (re-exported)

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


def rot_z(yaw: float) -> np.ndarray:
    """Right-handed rotation matrix about +z by `yaw` radians."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def flu_to_enu(v_flu: Sequence[float], yaw_enu: float) -> np.ndarray:
    """Body FLU vector of a level vehicle with ROS yaw `yaw_enu` -> world ENU."""
    return rot_z(yaw_enu) @ _vec3(v_flu)


def enu_to_flu(v_enu: Sequence[float], yaw_enu: float) -> np.ndarray:
    """World ENU vector -> body FLU of a level vehicle with ROS yaw `yaw_enu`."""
    return rot_z(yaw_enu).T @ _vec3(v_enu)


def frd_to_ned(v_frd: Sequence[float], yaw_ned: float) -> np.ndarray:
    """Body FRD vector of a level vehicle with NED heading `yaw_ned` -> world NED.

    This is ArduCopter's rotate_body_frame_to_NE for MAV_FRAME_BODY_(OFFSET_)NED velocities.
    """
    return rot_z(yaw_ned) @ _vec3(v_frd)


def ned_to_frd(v_ned: Sequence[float], yaw_ned: float) -> np.ndarray:
    """World NED vector -> body FRD of a level vehicle with NED heading `yaw_ned`."""
    return rot_z(yaw_ned).T @ _vec3(v_ned)


def flu_velocity_to_ned(v_flu: Sequence[float], yaw_enu: float) -> np.ndarray:
    """Body FLU velocity (vehicle held at ROS yaw `yaw_enu`) -> LOCAL_NED velocity."""
    return enu_to_ned(flu_to_enu(v_flu, yaw_enu))


def euler_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Z-Y-X (yaw, pitch, roll) Euler angles -> rotation matrix world_from_body."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return rot_z(yaw) @ ry @ rx


def matrix_to_euler(r: np.ndarray) -> tuple[float, float, float]:
    """Rotation matrix world_from_body -> Z-Y-X Euler (roll, pitch, yaw)."""
    pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
    roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
    yaw = math.atan2(float(r[1, 0]), float(r[0, 0]))
    return roll, pitch, yaw


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (x, y, z, w) with w >= 0."""
    m = np.asarray(r, dtype=float)
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
    qa = np.array(q, dtype=float)
    qa /= np.linalg.norm(qa)
    return -qa if qa[3] < 0.0 else qa


def attitude_ned_frd_to_enu_flu(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """ArduPilot ATTITUDE (NED/FRD Euler) -> rotation matrix odom(ENU)_from_base_link(FLU)."""
    return _ENU_NED @ euler_to_matrix(roll, pitch, yaw) @ _FLU_FRD


def attitude_enu_flu_to_ned_frd(r_enu_flu: np.ndarray) -> tuple[float, float, float]:
    """Rotation matrix odom(ENU)_from_base_link(FLU) -> ArduPilot (roll, pitch, yaw) NED/FRD."""
    return matrix_to_euler(_ENU_NED @ np.asarray(r_enu_flu, dtype=float) @ _FLU_FRD)
