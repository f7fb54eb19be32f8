"""Camera levelling (assist_perception.level): geometry against the renderer, and the CM-VAE gain."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from assist_lab.cmvae_dataset import pad_label
from assist_perception.encoder_core import LatentEncoder
from assist_perception.level import AttitudeBuffer, level_frame, level_rotation, tilt_deg
from assist_sim.core.config import WorldConfig
from assist_common.frames import unit_quat_to_matrix as quaternion_matrix
from assist_sim.core.world import LandingWorld


def quat(roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0):
    """(x, y, z, w) of an odom <- base_link attitude given as ZYX Euler angles."""
    return Rotation.from_euler('ZYX', [yaw_deg, pitch_deg, roll_deg], degrees=True).as_quat()


@pytest.fixture(scope='module')
def world():
    w = LandingWorld(WorldConfig(), seed=0)
    yield w
    w.close()


def test_yaw_alone_is_level_and_tilt_is_measured():
    assert np.allclose(level_rotation(quat(yaw_deg=73.0)), np.eye(3), atol=1e-12)
    assert tilt_deg(level_rotation(quat(roll_deg=10.0, yaw_deg=-40.0))) == pytest.approx(10.0, abs=1e-9)
    assert tilt_deg(level_rotation(quat(pitch_deg=-7.0))) == pytest.approx(7.0, abs=1e-9)
    with pytest.raises(ValueError):
        quaternion_matrix((0.0, 0.0, 0.0, 0.0))
    with pytest.raises(ValueError):
        quaternion_matrix((float('nan'), 0.0, 0.0, 1.0))


def test_identity_rotation_changes_nothing(world):
    world.reset(5, airborne=True)
    f = world.render()
    rgb, depth = level_frame(f.rgb, f.depth, f.K, np.eye(3))
    assert np.array_equal(rgb, f.rgb)
    assert np.allclose(depth, f.depth, rtol=1e-6)


@pytest.mark.parametrize('roll,pitch,yaw', [(10.0, 0.0, 0.0), (0.0, -12.0, 30.0), (6.0, 8.0, -120.0)])
def test_levelled_frame_matches_a_level_render_from_the_same_centre(world, roll, pitch, yaw):
    """Pitch forward/back and roll are undone: the warp reproduces what a level camera renders."""
    world.reset(11, airborne=True)
    pad = world.scene.pads[2].top_center
    base = pad + np.array([0.3, -0.2, 1.8])
    q = quat(roll, pitch, yaw)
    r_wb = quaternion_matrix(q)
    cam, r_wo = world.camera_pose()                     # only for its conventions
    r_wo_tilted = r_wb @ (np.linalg.inv(quaternion_matrix(quat(yaw_deg=0.0))) @ r_wo)
    cam_pos = base + np.array([0.0, 0.0, -0.05])
    tilted = world.render_pose(cam_pos, r_wo_tilted)
    r_level = level_rotation(q)
    r_wo_level = r_wo_tilted @ r_level.T
    assert tilt_deg(r_wo_level.T @ r_wo_tilted) == pytest.approx(math.degrees(math.acos(r_wb[2, 2])), abs=1e-6)
    assert abs(r_wo_level[2, 2] + 1.0) < 1e-9            # the levelled optical axis points straight down
    level = world.render_pose(cam_pos, r_wo_level)
    rgb, depth = level_frame(tilted.rgb, tilted.depth, tilted.K, r_level)
    # compare where the tilted camera saw the scene (border strips it did not see are replicated)
    h, w = depth.shape
    inner = (slice(h // 6, h - h // 6), slice(w // 6, w - w // 6))
    d_err = np.abs(depth[inner] - level.depth[inner]) / level.depth[inner]
    assert np.mean(d_err < 0.02) > 0.93, np.mean(d_err < 0.02)
    # colour: textures are fine-grained, so a one-pixel resampling shift changes single pixels a lot;
    # compare the mean difference with the unlevelled frame's
    c_err = np.abs(rgb[inner].astype(int) - level.rgb[inner].astype(int)).mean()
    c_raw = np.abs(tilted.rgb[inner].astype(int) - level.rgb[inner].astype(int)).mean()
    assert c_err < 0.5 * c_raw, (c_err, c_raw)
    # without levelling the depth comparison fails clearly
    d_raw = np.abs(tilted.depth[inner] - level.depth[inner]) / level.depth[inner]
    assert np.mean(d_raw < 0.02) < 0.6, np.mean(d_raw < 0.02)


def test_invalid_depth_stays_invalid():
    K = np.array([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]])
    depth = np.full((64, 64), 2.0, np.float32)
    depth[20:40, 20:40] = 0.0
    rgb = np.zeros((64, 64, 3), np.uint8)
    _, out = level_frame(rgb, depth, K, level_rotation(quat(roll_deg=5.0)))
    assert np.sum(out == 0.0) > 300                      # the hole moved, it was not filled
    assert np.all(out[out > 0] > 1.9)
    with pytest.raises(ValueError):
        level_frame(np.zeros((32, 64, 3), np.uint8), depth, K, np.eye(3))


def test_cmvae_pad_estimate_recovers_with_levelling(world):
    """At 10 deg the estimate read as level is off by ~0.45 m; levelled it is close to the level case."""
    enc = LatentEncoder(threads=1)
    rng = np.random.default_rng(3)
    raw, lev, flat = [], [], []
    for s in range(10):
        world.reset(2000 + s, airborne=True)
        pad = world.scene.pads[int(rng.integers(len(world.scene.pads)))]
        base = pad.top_center + np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(1.3, 2.3)])
        az, yaw = rng.uniform(-math.pi, math.pi, 2)
        q = quat(10.0 * math.cos(az), 10.0 * math.sin(az), math.degrees(yaw))
        world._bc.resetBasePositionAndOrientation(world._vehicle, base.tolist(), q.tolist())
        frame = world.render()
        cam, r_wo = world.camera_pose()
        lab = pad_label(frame.depth, frame.K, cam, r_wo, world.scene.pads, 12, 0.02)
        if not lab.visible:
            continue
        target = world.scene.pads[lab.index].top_center[:2]
        r = level_rotation(q)
        r_wo_level = r_wo @ r.T
        raw.append(np.linalg.norm((cam + r_wo_level @ enc.encode(frame.rgb, frame.depth).pad_xyz)[:2] - target))
        c2, d2 = level_frame(frame.rgb, frame.depth, frame.K, r)
        lev.append(np.linalg.norm((cam + r_wo_level @ enc.encode(c2, d2).pad_xyz)[:2] - target))
        world._bc.resetBasePositionAndOrientation(world._vehicle, base.tolist(),
                                                  quat(yaw_deg=math.degrees(yaw)).tolist())
        f0 = world.render()
        c0, r0 = world.camera_pose()
        flat.append(np.linalg.norm((c0 + r0 @ enc.encode(f0.rgb, f0.depth).pad_xyz)[:2] - target))
    assert len(raw) >= 7
    assert np.median(raw) > 0.3, raw
    assert np.median(lev) < 0.5 * np.median(raw), (lev, raw)
    assert np.median(lev) < np.median(flat) + 0.08, (lev, flat)


def test_attitude_buffer_nearest_and_reset():
    b = AttitudeBuffer(horizon_s=1.5)
    assert b.nearest(1.0, 0.1) is None
    for i in range(20):
        b.add(10.0 + 0.1 * i, (0.0, 0.0, 0.0, 1.0 + i))
    assert b.nearest(10.52, 0.05)[3] == pytest.approx(6.0)   # 10.5 is nearest
    assert b.nearest(12.5, 0.1) is None                      # too far after the last sample
    assert b.nearest(10.0, 0.05) is None                     # pruned: older than the horizon
    b.add(3.0, (0.0, 0.0, 0.0, 1.0))                         # time went back (sim reset): starts over
    assert b.nearest(3.0, 0.01) == (0.0, 0.0, 0.0, 1.0) and b.nearest(11.8, 0.5) is None
    with pytest.raises(ValueError):
        b.add(4.0, (0.0, float('inf'), 0.0, 1.0))
