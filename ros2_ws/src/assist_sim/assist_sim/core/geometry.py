"""Frames and rotations shared by the world, the bridge and the encoder (numpy only, no pybullet)."""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

# Optical frame axes expressed in base_link (FLU): x_opt = -y_body, y_opt = -x_body, z_opt = -z_body.
R_BODY_FROM_OPTICAL = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def yaw_rotation(yaw: float) -> np.ndarray:
    """3x3 rotation about +z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quat_to_matrix(q) -> np.ndarray:
    """Quaternion (x, y, z, w) -> 3x3 rotation matrix."""
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
