"""Mocap poses (ENU) -> VISION_POSITION_ESTIMATE fields (NED): conversion, refusals, plausibility bounds, one source
at a time, pacing, reset counter."""
import math

import pytest
from scipy.spatial.transform import Rotation

from assist_bridge.vision import VisionConfig, VisionForwarder
from assist_common.settings import SettingsError


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


def test_a_jump_counts_as_a_reset_once_the_poses_continue_from_it():
    f = VisionForwarder(VisionConfig(reset_jump_m=0.5, reset_confirm_poses=3))
    f.offer(1.00, (0.0, 0.0, 1.0), quat(0), now_s=1.0)
    f.offer(1.01, (0.1, 0.0, 1.0), quat(0), now_s=1.01)
    assert f.due(1.01).reset_counter == 0
    # the mocap frame was re-initialised: held until three poses continue from the new place
    assert f.offer(1.02, (3.0, 0.0, 1.0), quat(0), now_s=1.02) == 'jump_unconfirmed'
    assert f.offer(1.03, (3.01, 0.0, 1.0), quat(0), now_s=1.03) == 'jump_unconfirmed'
    assert f.due(1.05) is None                                  # nothing held goes out
    assert f.offer(1.04, (3.02, 0.0, 1.0), quat(0), now_s=1.04) is None
    est = f.due(1.05)
    assert est.reset_counter == 1 and est.y == pytest.approx(3.02)    # ENU x = NED y
    f.offer(1.06, (3.1, 0.0, 1.0), quat(0), now_s=1.06)        # and stays at 1 while the poses are continuous
    assert f.due(1.1).reset_counter == 1 and f.events['reset'] == 1


@pytest.mark.parametrize('position', [(1e39, 0.0, 0.0), (0.0, -1e30, 0.0), (0.0, 0.0, 3.4e38), (80.0, 80.0, 0.0)])
def test_positions_beyond_max_position_are_refused(position):
    """1e39 does not fit MAVLink's float32 (packing it raised and ended the bridge); 1e30 fits but is no pose."""
    f = VisionForwarder(VisionConfig(max_position_m=100.0))
    assert f.offer(5.0, position, quat(0), now_s=5.0) == 'out_of_range'
    assert f.due(5.0) is None
    assert f.offer(5.01, (60.0, 79.0, 1.0), quat(0), now_s=5.01) is None     # 99.2 m from the origin: inside
    assert f.due(5.01).x == pytest.approx(79.0)


def test_a_jump_beyond_max_jump_is_refused_until_the_stream_starts_over():
    f = VisionForwarder(VisionConfig(max_jump_m=5.0, reset_jump_m=0.5, max_age_s=0.2))
    assert f.offer(1.00, (0.0, 0.0, 1.0), quat(0), now_s=1.0) is None
    assert f.offer(1.01, (40.0, 0.0, 1.0), quat(0), now_s=1.01) == 'jump'
    assert f.offer(1.02, (0.01, 0.0, 1.0), quat(0), now_s=1.02) is None      # the track goes on
    assert f.reset_counter == 0
    # the far place persists: refused while the last accepted pose is fresh, then a fresh start (a reset)
    assert f.offer(1.10, (40.0, 0.0, 1.0), quat(0), now_s=1.10) == 'jump'
    assert f.offer(1.25, (40.0, 0.0, 1.0), quat(0), now_s=1.25) is None
    assert f.due(1.25).reset_counter == 1


def test_poses_faster_than_max_pose_rate_are_refused():
    f = VisionForwarder(VisionConfig(max_pose_rate_hz=1000.0))
    assert f.offer(2.0, (0.0, 0.0, 1.0), quat(0), now_s=2.0) is None
    assert f.offer(2.0004, (0.0, 0.0, 1.0), quat(0), now_s=2.001) == 'too_fast'
    assert f.offer(2.0011, (0.0, 0.0, 1.0), quat(0), now_s=2.002) is None


def test_two_interleaved_publishers_never_bump_the_reset_counter():
    """Two mocap drivers 2 m apart on one topic, alternating at 100 Hz each: the first track is forwarded, the
    other held and dropped each time the first comes back; the reset counter stays where it was."""
    f = VisionForwarder(VisionConfig(reset_jump_m=0.5, reset_confirm_poses=3, rate_hz=100.0))
    verdicts, sent = [], []
    for k in range(200):
        t = 10.0 + k * 0.005
        x = 0.0 if k % 2 == 0 else 2.0
        verdicts.append(f.offer(t, (x + 0.001 * k, 0.0, 1.0), quat(0), now_s=t))
        est = f.due(t)
        if est is not None:
            sent.append(est)
    assert verdicts[0::2] == [None] * 100
    assert verdicts[1::2] == ['jump_unconfirmed'] * 100
    assert f.reset_counter == 0 and {e.reset_counter for e in sent} == {0}
    assert all(abs(e.y - 0.001 * round((e.usec / 1e6 - 10.0) / 0.005)) < 1e-6 for e in sent)   # track A only
    assert f.events['track_returned'] == 99 and f.events['reset'] == 0


def test_a_single_outlier_is_dropped_without_a_reset():
    f = VisionForwarder(VisionConfig(reset_jump_m=0.5, reset_confirm_poses=3))
    for k, x in enumerate((0.0, 0.01, 3.0, 0.02, 0.03)):
        f.offer(1.0 + 0.01 * k, (x, 0.0, 1.0), quat(0), now_s=1.0 + 0.01 * k)
    assert f.reset_counter == 0 and f.last_position[1] == pytest.approx(0.03)
    assert f.events['track_returned'] == 1


def test_another_frame_id_is_refused_while_the_first_source_is_live():
    f = VisionForwarder(VisionConfig(max_age_s=0.2))
    assert f.offer(1.00, (0.0, 0.0, 1.0), quat(0), now_s=1.00, source='optitrack') is None
    assert f.offer(1.01, (0.0, 0.0, 1.0), quat(0), now_s=1.01, source='vicon') == 'other_source'
    assert f.offer(1.02, (0.01, 0.0, 1.0), quat(0), now_s=1.02, source='optitrack') is None
    # the first source goes quiet for longer than max_age_s: the other takes over as a fresh start
    assert f.offer(1.30, (0.0, 0.0, 1.0), quat(0), now_s=1.30, source='vicon') is None
    assert f.source == 'vicon' and f.events['source_switched'] == 1
    assert f.offer(1.31, (0.0, 0.0, 1.0), quat(0), now_s=1.31, source='optitrack') == 'other_source'


@pytest.mark.parametrize('kwargs, words', [
    (dict(max_position_m=1e39), 'max_position_m must be <='),
    (dict(rate_hz=0.0), 'rate_hz must be >='),
    (dict(reset_confirm_poses=0), 'reset_confirm_poses must be >='),
    (dict(position_sigma_m=math.inf), 'position_sigma_m must be a finite number'),
    (dict(reset_jump_m=2.0, max_jump_m=1.0), 'max_jump_m (1) must be >= reset_jump_m (2)'),
])
def test_bad_vision_config_is_refused_in_one_line(kwargs, words):
    with pytest.raises(SettingsError) as err:
        VisionConfig(**kwargs)
    assert words in str(err.value) and '\n' not in str(err.value)
