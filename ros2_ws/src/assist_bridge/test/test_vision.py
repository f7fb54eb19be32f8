"""Mocap poses (ENU) -> VISION_POSITION_ESTIMATE fields (NED): conversion, refusals, pacing, reset counter."""
import math

import pytest
from scipy.spatial.transform import Rotation

from assist_bridge.vision import VisionConfig, VisionForwarder


def quat(yaw_enu: float, roll: float = 0.0, pitch: float = 0.0) -> tuple:
    return tuple(Rotation.from_euler('ZYX', [yaw_enu, pitch, roll]).as_quat())


def test_enu_pose_becomes_ned_with_frd_angles():
    f = VisionForwarder(VisionConfig())
    # 1 m east, 2 m north, 3 m up, facing north (ENU yaw 90 deg), nose 0.1 rad up (ENU/FLU pitch -0.1)
    assert f.offer(100.0, (1.0, 2.0, 3.0), quat(math.pi / 2, pitch=-0.1), now_s=100.01) is None
    est = f.due(100.01)
    assert (est.x, est.y, est.z) == pytest.approx((2.0, 1.0, -3.0))
    assert est.yaw == pytest.approx(0.0, abs=1e-9)            # north in NED
    assert est.pitch == pytest.approx(0.1, abs=1e-9)          # nose up is positive pitch in FRD
    assert est.roll == pytest.approx(0.0, abs=1e-9)
    assert est.usec == 100_000_000
    assert len(est.covariance) == 21 and est.covariance[0] == pytest.approx(1e-4)
    assert est.covariance[15] == pytest.approx(4e-4) and est.covariance[1] == 0.0   # roll variance; off-diagonal
    f.offer(100.02, (1.0, 2.0, 3.0), quat(0.0), now_s=100.02)                     # facing east
    assert f.due(100.1).yaw == pytest.approx(math.pi / 2)


@pytest.mark.parametrize('stamp, pos, q, why', [
    (99.0, (0, 0, 0), quat(0), 'stale'),
    (100.5, (0, 0, 0), quat(0), 'from_future'),
    (100.0, (0, math.nan, 0), quat(0), 'nonfinite'),
    (100.0, (0, 0, 0), (0.0, 0.0, 0.0, 2.0), 'bad_quaternion'),
    (100.0, (0, 0, 0), (0.0, 0.0, 0.0, 0.0), 'bad_quaternion'),
])
def test_bad_poses_are_refused_with_a_reason(stamp, pos, q, why):
    f = VisionForwarder(VisionConfig())
    assert f.offer(stamp, pos, q, now_s=100.0) == why
    assert f.due(100.0) is None


def test_paced_newest_only_and_stops_when_the_stream_stalls():
    f = VisionForwarder(VisionConfig(rate_hz=10.0, max_age_s=0.2))
    sent = []
    t = 0.0
    for k in range(100):                      # a 100 Hz mocap for 1 s
        t = 10.0 + k * 0.01
        assert f.offer(t, (0.001 * k, 0, 1), quat(0), now_s=t) is None
        est = f.due(t)
        if est is not None:
            sent.append(est)
    assert 9 <= len(sent) <= 11 and len({e.usec for e in sent}) == len(sent)
    assert f.offer(t - 0.005, (0, 0, 1), quat(0), now_s=t) == 'out_of_order'
    # no new pose: the newest goes out once (if the pacing held it back), then nothing; a pose older than
    # max_age_s never goes out
    late = [f.due(t + dt) for dt in (0.1, 0.15, 0.3, 1.0)]
    assert late[0] is None or late[0].usec == round(t * 1e6)
    assert late[1:] == [None, None, None]
    g = VisionForwarder(VisionConfig(rate_hz=10.0, max_age_s=0.2))
    g.offer(5.0, (0, 0, 1), quat(0), now_s=5.0)
    assert g.due(5.25) is None


def test_a_jump_counts_as_a_reset():
    f = VisionForwarder(VisionConfig(reset_jump_m=0.5))
    f.offer(1.00, (0.0, 0.0, 1.0), quat(0), now_s=1.0)
    f.offer(1.01, (0.1, 0.0, 1.0), quat(0), now_s=1.01)
    assert f.due(1.01).reset_counter == 0
    f.offer(1.02, (3.0, 0.0, 1.0), quat(0), now_s=1.02)        # the mocap frame was re-initialised
    assert f.due(1.05).reset_counter == 1
    f.offer(1.06, (3.1, 0.0, 1.0), quat(0), now_s=1.06)        # and stays at 1 while the poses are continuous
    assert f.due(1.1).reset_counter == 1
