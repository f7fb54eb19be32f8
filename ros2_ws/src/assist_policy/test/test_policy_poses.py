"""PoseHistory: the odometry pose at a sensor stamp (interpolated), a match window, restarts and pruning."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from assist_policy.poses import PoseHistory, header_seconds

Q0, Q1 = np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 0.0, math.sin(0.1), math.cos(0.1)])


def test_position_interpolated_between_the_samples_around_the_stamp_attitude_of_the_nearer():
    h = PoseHistory(span_s=1.0, match_s=0.1)
    h.add(10.00, [0.0, 0.0, 2.0], Q0)
    h.add(10.02, [0.03, 0.0, 2.0], Q1)
    p, q = h.at(10.005)
    np.testing.assert_allclose(p, [0.0075, 0.0, 2.0])
    np.testing.assert_allclose(q, Q0)
    np.testing.assert_allclose(h.at(10.016)[1], Q1)
    np.testing.assert_allclose(h.at(10.02)[0], [0.03, 0.0, 2.0])


def test_a_stamp_outside_the_samples_by_more_than_the_window_has_no_pose():
    h = PoseHistory(span_s=1.0, match_s=0.1)
    assert h.at(10.0) is None                                  # nothing yet
    h.add(10.0, [1.0, 0.0, 2.0], None)
    h.add(10.5, [2.0, 0.0, 2.0], None)
    np.testing.assert_allclose(h.at(10.58)[0], [2.0, 0.0, 2.0])   # just after the latest: the latest
    np.testing.assert_allclose(h.at(9.95)[0], [1.0, 0.0, 2.0])    # just before the first: the first
    assert h.at(10.7) is None and h.at(9.8) is None            # another clock, a stalled source
    assert h.at(10.25) is None                                 # inside a 0.5 s gap in the odometry
    assert h.at(float('nan')) is None


def test_old_poses_are_dropped_and_a_stamp_going_back_restarts_the_history():
    h = PoseHistory(span_s=0.5, match_s=0.05)
    for k in range(20):
        h.add(k * 0.1, [k, 0.0, 0.0], None)
    assert h.at(1.0) is None and h.at(1.45)[0][0] == pytest.approx(14.5)   # 1.0 s is older than 0.5 s
    h.add(0.2, [-1.0, 0.0, 0.0], None)                                       # a bag looped
    assert h.at(1.9) is None
    np.testing.assert_allclose(h.at(0.2)[0], [-1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match='match_s'):
        PoseHistory(match_s=-0.1)


def test_header_seconds_unset_is_none():
    msg = SimpleNamespace(header=SimpleNamespace(stamp=SimpleNamespace(sec=12, nanosec=500_000_000)))
    assert header_seconds(msg) == pytest.approx(12.5)
    msg.header.stamp.sec, msg.header.stamp.nanosec = 0, 0
    assert header_seconds(msg) is None
