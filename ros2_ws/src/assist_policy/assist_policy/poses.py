"""Recent odometry poses by sensor stamp: the pose a depth frame was taken from (pad recall's map).

Why: the camera and the odometry arrive on their own topics with their own latencies (a RealSense
frame is typically 30-100 ms old when it arrives, odometry a few ms), so pairing a depth frame with the
latest odometry puts what it shows off by the distance flown since it was taken (at 1.5 m/s, 0.15 m for
100 ms). ``PoseHistory`` keeps the last ``span_s`` of odometry poses by their header stamps and gives
the pose at a frame's header stamp: the position interpolated between the two samples around it, the
attitude of the nearer one. A stamp farther than ``match_s`` outside the samples (another clock, a
stalled source, stamps never set) gets none: the caller falls back to the latest pose and counts it.
Stamps that go backwards (a bag looped, a simulation reset) start the history afresh.

Pure numpy; no rclpy.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np


def header_seconds(msg) -> float | None:
    """A ROS message's header stamp in seconds; None when it was never set (0), as policy_node treats it."""
    st = msg.header.stamp
    return None if int(st.sec) == 0 and int(st.nanosec) == 0 else int(st.sec) + int(st.nanosec) * 1e-9


class PoseHistory:
    """Odometry poses (stamp s, position, quaternion or None) over the last `span_s`; `at(stamp)` looks one up."""

    def __init__(self, span_s: float = 1.0, match_s: float = 0.1):
        for name, v in (('span_s', span_s), ('match_s', match_s)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f'PoseHistory.{name} must be a finite number >= 0, got {v!r}')
        self.span_s, self.match_s = float(span_s), float(match_s)
        self._poses: deque[tuple[float, np.ndarray, np.ndarray | None]] = deque()

    def clear(self) -> None:
        """Forget every pose."""
        self._poses.clear()

    def add(self, stamp: float, position: np.ndarray, quaternion: np.ndarray | None) -> None:
        """Record a pose at `stamp` (s); an earlier stamp than the last restarts the history."""
        if self._poses and stamp < self._poses[-1][0]:
            self._poses.clear()
        self._poses.append((float(stamp), np.asarray(position, dtype=float).copy(),
                            None if quaternion is None else np.asarray(quaternion, dtype=float).copy()))
        while self._poses[0][0] < stamp - self.span_s:
            self._poses.popleft()

    def at(self, stamp: float) -> tuple[np.ndarray, np.ndarray | None] | None:
        """(position, quaternion) at `stamp`, or None when no sample lies within match_s of it."""
        if not self._poses or not math.isfinite(stamp):
            return None
        first, last = self._poses[0], self._poses[-1]
        if stamp >= last[0]:
            return (last[1].copy(), last[2]) if stamp - last[0] <= self.match_s else None
        if stamp <= first[0]:
            return (first[1].copy(), first[2]) if first[0] - stamp <= self.match_s else None
        for (s0, p0, q0), (s1, p1, q1) in zip(self._poses, list(self._poses)[1:]):
            if s0 <= stamp <= s1:
                if min(stamp - s0, s1 - stamp) > self.match_s:
                    return None          # a gap in the odometry longer than twice match_s
                w = 0.0 if s1 == s0 else (stamp - s0) / (s1 - s0)
                return p0 + w * (p1 - p0), (q0 if w < 0.5 else q1)
        return None
