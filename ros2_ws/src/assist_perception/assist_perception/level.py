"""Camera levelling: re-render a frame from a tilted, rigidly mounted camera as a level camera would see it.

On a real airframe (and in sim_node's ardupilot_json mode) the downward camera tilts with the
vehicle, but the CM-VAE and the assistants were trained on level images (velocity mode keeps the
camera level). Read as if level, a pad estimate from a frame tilted by 5 / 10 / 20 deg is off by
0.25 / 0.46 / 0.72 m horizontally (median, `python -m bench json`). Levelling removes most of that.

The level camera shares the optical centre and heading of the real one; only roll and pitch are
undone. A pure rotation about the optical centre maps pixels by the homography K R K^-1, whatever
the depth, so every output pixel is looked up in the input (no holes, nearest-neighbour so depth
edges are never blended); the depth along the new optical axis is the input depth divided by the
z component of the output pixel's ray expressed in the input camera. Pixels the tilted camera did
not see (strips at the image border) repeat the nearest border pixel, which is what the encoder
handled best when measured. Invalid depth (0 or NaN) stays invalid. The camera's small offset from
base_link is neglected: 10 cm below base_link at 10 deg tilt moves the optical centre 1.7 cm.
"""
from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque

import cv2
import numpy as np

from assist_common.frames import R_BODY_FROM_OPTICAL, unit_quat_to_matrix, yaw_rotation


DEFAULT_MIN_TILT_DEG = 0.5      # frames tilted less than this pass unchanged (encoder_node, the env)


def level_rotation(q_world_from_base) -> np.ndarray:
    """R (level optical <- tilted optical) for a base_link attitude quaternion (x, y, z, w) in odom."""
    r_wb = unit_quat_to_matrix(q_world_from_base)
    r_level_from_body = yaw_rotation(math.atan2(r_wb[1, 0], r_wb[0, 0])).T @ r_wb   # heading removed
    return R_BODY_FROM_OPTICAL.T @ r_level_from_body @ R_BODY_FROM_OPTICAL


def tilt_deg(r: np.ndarray) -> float:
    """Angle between the optical axes of the two cameras related by rotation `r`, in degrees."""
    return math.degrees(math.acos(max(-1.0, min(1.0, float(r[2, 2])))))


def level_frame(rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, r_level_from_cam: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The (rgb HxWx3, depth HxW metres along the optical axis) a level camera would see."""
    h, w = depth.shape
    if rgb.shape[:2] != (h, w):
        raise ValueError(f'colour {rgb.shape[:2]} and depth {(h, w)} differ in size')
    K = np.asarray(K, dtype=np.float64)
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones((h, w))], -1)
    src = rays @ np.asarray(r_level_from_cam, dtype=np.float64)    # = (R^T ray) per pixel: rays in the input camera
    sz = src[..., 2]
    ahead = sz > 1e-6
    sz_safe = np.where(ahead, sz, 1.0)
    map_x = np.where(ahead, K[0, 0] * src[..., 0] / sz_safe + K[0, 2] - 0.5, -1e4).astype(np.float32)
    map_y = np.where(ahead, K[1, 1] * src[..., 1] / sz_safe + K[1, 2] - 0.5, -1e4).astype(np.float32)
    out_rgb = cv2.remap(np.ascontiguousarray(rgb), map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    d = cv2.remap(np.ascontiguousarray(depth, dtype=np.float32), map_x, map_y, cv2.INTER_NEAREST,
                  borderMode=cv2.BORDER_REPLICATE)
    out_depth = (d / sz_safe).astype(np.float32)
    out_depth[~ahead] = np.nan
    return out_rgb, out_depth


class AttitudeBuffer:
    """Recent (stamp, quaternion) samples; the one nearest a frame's stamp within a tolerance.

    Filled by the /odom callback and read by the inference thread: samples are kept as
    (stamp, quaternion) pairs in one deque and `nearest` works on one snapshot of it, so a sample
    added or pruned meanwhile cannot pair a stamp with another sample's attitude.
    """

    def __init__(self, horizon_s: float = 2.0, maxlen: int = 1000):
        self.horizon_s = float(horizon_s)
        self._samples: deque[tuple[float, tuple[float, float, float, float]]] = deque(maxlen=maxlen)

    def add(self, stamp: float, q_xyzw) -> None:
        """Add a sample (stamps must not go backwards; a jump back clears the buffer: sim reset)."""
        q = tuple(float(v) for v in q_xyzw)
        if not (math.isfinite(stamp) and all(math.isfinite(v) for v in q)):
            raise ValueError('non-finite attitude sample')
        if self._samples and stamp < self._samples[-1][0]:
            self._samples.clear()
        self._samples.append((stamp, q))
        while self._samples[0][0] < stamp - self.horizon_s:
            self._samples.popleft()

    def nearest(self, stamp: float, max_offset_s: float) -> tuple[float, float, float, float] | None:
        """The sample closest to `stamp`, or None when none is within `max_offset_s`."""
        samples = list(self._samples)
        if not samples:
            return None
        i = bisect_left(samples, stamp, key=lambda sample: sample[0])
        t, q = min(samples[max(i - 1, 0):i + 1], key=lambda sample: abs(sample[0] - stamp))
        return q if abs(t - stamp) <= max_offset_s else None
