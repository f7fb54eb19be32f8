"""External pose (motion capture) -> ArduPilot's VISION_POSITION_ESTIMATE (pure Python, no rclpy).

The paper's demonstration flew indoors on OptiTrack poses. A mocap driver publishes the vehicle's pose as
geometry_msgs/PoseStamped in an ENU world frame (x east, y north, z up; body FLU); ArduPilot's EKF3 takes
external navigation as VISION_POSITION_ESTIMATE in NED with FRD body angles. This module converts, checks
and paces them:

* a pose is refused (counted by reason) when a value is not finite (`nonfinite`), the quaternion is not
  close to unit length (`bad_quaternion`), the stamp is negative (`bad_stamp`), more than `max_age_s` old
  (`stale`) or ahead of the clock by more than `max_ahead_s` (`from_future`), older than the last one
  accepted (`out_of_order`), closer to it than 1/`max_pose_rate_hz` (`too_fast`), or the position is
  farther than `max_position_m` from the origin (`out_of_range`: nothing the EKF could use, and beyond
  1e38 m nothing MAVLink's float32 can carry);
* one source at a time: the first pose's `source` (the node passes the header's frame_id) is the one
  forwarded; poses from another source are refused (`other_source`) while it is live, i.e. while its last
  accepted pose is younger than `max_age_s`; after that the next source takes over as a fresh start;
* the track: a pose within `reset_jump_m` of the last accepted one continues it. A jump larger than
  `max_jump_m` is refused (`jump`). A jump between the two is held (`jump_unconfirmed`) until
  `reset_confirm_poses` consecutive poses continue from the new place: then it is a re-initialised mocap
  frame, `reset_counter` goes up by one (the EKF resets its position instead of rejecting the innovation)
  and the confirming pose is forwarded. When the old track comes back first, the held poses were an outlier
  or a second publisher on the topic: they are dropped (`track_returned` in `events`) and the reset counter
  stays. Two interleaved publishers therefore never bump the reset counter pose after pose: the track that
  was there first keeps being forwarded (unless the other runs `reset_confirm_poses` poses in a row without
  it);
* after the stream stalls (no pose accepted for `max_age_s`) the next pose starts over wherever it is
  (within `max_position_m`), a reset when it moved more than `reset_jump_m`;
* at most `rate_hz` estimates are sent, each the newest accepted pose, never one sent before, never one older
  than `max_age_s` (a stalled mocap stream stops the estimates, so the EKF falls back instead of fusing an
  old pose as new);
* `usec` is the pose's own capture stamp in microseconds (ArduPilot aligns the sender's clock to its own and
  applies VISO_DELAY_MS), the covariance is the upper triangle of a diagonal (position variance
  `position_sigma_m`^2, angle variance `angle_sigma_rad`^2).
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

from assist_common.frames import attitude_enu_flu_to_ned_frd, enu_to_ned, unit_quat_to_matrix
from assist_common.settings import SettingsError, check_named, setting



@dataclass
class VisionConfig:
    """Pacing and checks of the forwarded poses (node parameters `vision_*`); ranges checked on creation."""

    rate_hz: float = setting(30.0, ge=4.0, le=100.0)          # ArduPilot wants >= 4 Hz; mocap runs 100-240 Hz
    max_age_s: float = setting(0.2, ge=0.01, le=2.0)          # older poses are not sent
    max_ahead_s: float = setting(0.05, ge=0.0, le=1.0)        # stamps further in the future than this are refused
    position_sigma_m: float = setting(0.01, gt=0.0, le=10.0)  # mocap position noise (1 sigma)
    angle_sigma_rad: float = setting(0.02, gt=0.0, le=1.0)    # mocap attitude noise (1 sigma)
    reset_jump_m: float = setting(0.5, ge=0.01, le=100.0)     # a confirmed jump larger than this is a reset
    max_jump_m: float = setting(5.0, ge=0.01, le=1000.0)      # a larger jump between two poses is refused
    reset_confirm_poses: int = setting(3, ge=1, le=100)       # poses continuing a jump before it is a reset
    max_position_m: float = setting(100.0, ge=1.0, le=10000.0)   # farther from the mocap origin: refused
    max_pose_rate_hz: float = setting(1000.0, ge=10.0, le=10000.0)  # stamps closer than 1/this: refused

    def __post_init__(self) -> None:
        check_named(self)

    def check_relations(self) -> None:
        """Rules between fields (check_settings calls it)."""
        if self.max_jump_m < self.reset_jump_m:
            raise SettingsError(f'max_jump_m ({self.max_jump_m:g}) must be >= reset_jump_m ({self.reset_jump_m:g})')


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
    """Accepts ENU poses (`offer`) and hands out the NED estimates to send (`due`).

    `events` counts what happened beyond each pose's verdict: `reset` (the counter went up),
    `track_returned` (held poses dropped because the old track came back: an outlier or a second
    publisher), `source_switched` (a new source took over after the old one went quiet).
    """

    def __init__(self, cfg: VisionConfig) -> None:
        self.cfg = cfg
        self.cov = _covariance(cfg)
        self.latest: tuple[float, VisionEstimate] | None = None     # (stamp s, estimate)
        self.last_position: np.ndarray | None = None                # NED of the last accepted pose
        self.last_stamp = -math.inf                                 # its stamp
        self.source: str | None = None                              # the source being forwarded
        self.pending: list[tuple[float, np.ndarray]] = []           # poses held after a jump (stamp, NED)
        self.sent_stamp: float | None = None
        self.next_due = -math.inf
        self.reset_counter = 0
        self.events: collections.Counter[str] = collections.Counter()

    def offer(self, stamp_s: float, position_enu, quat_xyzw, now_s: float, source: str = '') -> str | None:
        """Take one pose from `source` (e.g. its frame_id); None when accepted, else why it was refused or held."""
        c = self.cfg
        values = [stamp_s, *position_enu, *quat_xyzw]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            return 'nonfinite'
        if abs(math.sqrt(sum(q * q for q in quat_xyzw)) - 1.0) > 0.01:
            return 'bad_quaternion'
        if stamp_s < 0.0:
            return 'bad_stamp'
        if stamp_s > now_s + c.max_ahead_s:
            return 'from_future'
        if now_s - stamp_s > c.max_age_s:
            return 'stale'
        ned = enu_to_ned(position_enu)
        if float(np.linalg.norm(ned)) > c.max_position_m:
            return 'out_of_range'
        live = self.last_position is not None and now_s - self.last_stamp <= c.max_age_s
        if live and source != self.source:
            return 'other_source'
        if live and stamp_s <= self.last_stamp:
            return 'out_of_order'
        if live and stamp_s - self.last_stamp < 1.0 / c.max_pose_rate_hz:
            return 'too_fast'
        reset = False
        if not live:                        # first pose, or a fresh start after the stream stalled
            if self.last_position is not None:
                reset = float(np.linalg.norm(ned - self.last_position)) > c.reset_jump_m
                if source != self.source:
                    self.events['source_switched'] += 1
            self.pending.clear()
        else:
            jump = float(np.linalg.norm(ned - self.last_position))
            if jump > c.max_jump_m:
                return 'jump'
            if jump <= c.reset_jump_m:      # continues the track; anything held was not a new frame
                if self.pending:
                    self.events['track_returned'] += 1
                    self.pending.clear()
            else:
                if self.pending and (stamp_s <= self.pending[-1][0] or float(
                        np.linalg.norm(ned - self.pending[-1][1])) > c.reset_jump_m):
                    self.pending.clear()    # not continuous with what was held: start holding again
                self.pending.append((stamp_s, ned))
                if len(self.pending) < c.reset_confirm_poses:
                    return 'jump_unconfirmed'
                self.pending.clear()
                reset = True
        if reset:
            self.reset_counter = (self.reset_counter + 1) % 256
            self.events['reset'] += 1
        roll, pitch, yaw = attitude_enu_flu_to_ned_frd(unit_quat_to_matrix(quat_xyzw))
        est = VisionEstimate(int(round(stamp_s * 1e6)), float(ned[0]), float(ned[1]), float(ned[2]),
                             roll, pitch, yaw, self.cov, self.reset_counter)
        self.latest = (stamp_s, est)
        self.last_position = ned
        self.last_stamp = stamp_s
        self.source = source
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
