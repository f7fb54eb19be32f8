"""External pose (motion capture) -> ArduPilot's VISION_POSITION_ESTIMATE (pure Python, no rclpy).

The paper's demonstration flew indoors on OptiTrack poses. A mocap driver publishes the vehicle's pose as
geometry_msgs/PoseStamped in an ENU world frame (x east, y north, z up; body FLU); ArduPilot's EKF3 takes
external navigation as VISION_POSITION_ESTIMATE in NED with FRD body angles. This module converts, checks
and paces them:

* a pose is refused (counted by reason) when a value is not finite, the quaternion is not close to unit
  length, the stamp is more than `max_age_s` old or ahead of the clock by more than `max_ahead_s`, or it is
  older than the last one accepted;
* at most `rate_hz` estimates are sent, each the newest accepted pose, never one sent before, never one older
  than `max_age_s` (a stalled mocap stream stops the estimates, so the EKF falls back instead of fusing an
  old pose as new);
* `usec` is the pose's own capture stamp in microseconds (ArduPilot aligns the sender's clock to its own and
  applies VISO_DELAY_MS), the covariance is the upper triangle of a diagonal (position variance `position_sigma_m`^2,
  angle variance `angle_sigma_rad`^2), and `reset_counter` goes up by one when the pose jumps more than
  `reset_jump_m` between consecutive poses (a re-initialised mocap frame), so the EKF resets its position
  instead of rejecting the innovation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from assist_common.frames import attitude_enu_flu_to_ned_frd, enu_to_ned, unit_quat_to_matrix


@dataclass
class VisionConfig:
    """Pacing and checks of the forwarded poses (node parameters `vision_*`)."""

    rate_hz: float = 30.0               # ArduPilot wants >= 4 Hz; mocap runs at 100-240 Hz
    max_age_s: float = 0.2              # older poses are not sent
    max_ahead_s: float = 0.05           # stamps further in the future than this are refused
    position_sigma_m: float = 0.01      # mocap position noise (1 sigma)
    angle_sigma_rad: float = 0.02       # mocap attitude noise (1 sigma)
    reset_jump_m: float = 0.5           # a jump larger than this between consecutive poses is a reset


@dataclass(frozen=True)
class VisionEstimate:
    """The fields of one VISION_POSITION_ESTIMATE."""

    usec: int
    x: float
    y: float
    z: float
    roll: float
    pitch: float
    yaw: float
    covariance: tuple[float, ...]
    reset_counter: int


def _covariance(cfg: VisionConfig) -> tuple[float, ...]:
    """Upper triangle (row-major, 21 values) of the 6x6 diagonal covariance of x, y, z, roll, pitch, yaw."""
    diag = [cfg.position_sigma_m ** 2] * 3 + [cfg.angle_sigma_rad ** 2] * 3
    return tuple(float(diag[i]) if i == j else 0.0 for i in range(6) for j in range(i, 6))


class VisionForwarder:
    """Accepts ENU poses (`offer`) and hands out the NED estimates to send (`due`)."""

    def __init__(self, cfg: VisionConfig) -> None:
        self.cfg = cfg
        self.cov = _covariance(cfg)
        self.latest: tuple[float, VisionEstimate] | None = None     # (stamp s, estimate)
        self.last_position: np.ndarray | None = None
        self.last_stamp = -math.inf
        self.sent_stamp: float | None = None
        self.next_due = -math.inf
        self.reset_counter = 0

    def offer(self, stamp_s: float, position_enu, quat_xyzw, now_s: float) -> str | None:
        """Take one pose; None when accepted, else the reason it was refused."""
        values = [stamp_s, *position_enu, *quat_xyzw]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            return 'nonfinite'
        if abs(math.sqrt(sum(q * q for q in quat_xyzw)) - 1.0) > 0.01:
            return 'bad_quaternion'
        if stamp_s > now_s + self.cfg.max_ahead_s:
            return 'from_future'
        if now_s - stamp_s > self.cfg.max_age_s:
            return 'stale'
        if stamp_s <= self.last_stamp:
            return 'out_of_order'
        ned = enu_to_ned(position_enu)
        if self.last_position is not None and float(np.linalg.norm(ned - self.last_position)) > self.cfg.reset_jump_m:
            self.reset_counter = (self.reset_counter + 1) % 256
        roll, pitch, yaw = attitude_enu_flu_to_ned_frd(unit_quat_to_matrix(quat_xyzw))
        est = VisionEstimate(int(round(stamp_s * 1e6)), float(ned[0]), float(ned[1]), float(ned[2]),
                             roll, pitch, yaw, self.cov, self.reset_counter)
        self.latest = (stamp_s, est)
        self.last_position = ned
        self.last_stamp = stamp_s
        return None

    def due(self, now_s: float) -> VisionEstimate | None:
        """The estimate to send now: the newest pose, if fresh, not sent yet and the rate allows; else None."""
        if self.latest is None or now_s < self.next_due:
            return None
        stamp, est = self.latest
        if stamp == self.sent_stamp or now_s - stamp > self.cfg.max_age_s:
            return None
        period = 1.0 / self.cfg.rate_hz
        self.next_due = now_s + period if now_s - self.next_due > period else self.next_due + period
        self.sent_stamp = stamp
        return est
