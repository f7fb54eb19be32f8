"""Dataset labels on a hand-built scene with known pads, determinism and resumable shards."""
import numpy as np
import pytest

from assist_lab.cmvae_dataset import (DatasetConfig, load_frames, make_dataset, pad_label,
                                       render_scene, shard_path, split_by_scene)
from assist_sim.core.scene import PadSpec, SceneSpec
from assist_sim.core.world import LandingWorld

PADS = (
    PadSpec(center=(4.0, 0.5), length=1.2, width=1.0, height=0.8, yaw=0.3, material=3),
    PadSpec(center=(7.6, 0.5), length=1.0, width=1.0, height=1.2, yaw=0.0, material=4),
    PadSpec(center=(12.0, -0.5), length=1.0, width=1.0, height=0.6, yaw=0.0, material=5),
    PadSpec(center=(16.0, 0.0), length=1.0, width=1.0, height=0.6, yaw=0.0, material=6),
    PadSpec(center=(20.0, 0.0), length=1.0, width=1.0, height=0.6, yaw=0.0, material=7),
)
SCENE = SceneSpec(seed=0, pads=PADS, floor_material=10, wall_material=11,
                  start_position=(0.0, 0.0, 3.0), room_min=(-6.0, -6.0), room_max=(26.0, 6.0))
CFG = DatasetConfig()


@pytest.fixture(scope='module')
def world():
    w = LandingWorld(seed=0)
    w.reset(scene=SCENE, goal_index=0)
    yield w
    w.close()


def _label(world, base):
    frame = world.render_from(np.array(base, float), 0.0)
    cam, r_wo = world.camera_pose(np.array(base, float), 0.0)
    return frame, pad_label(frame.depth, frame.K, cam, r_wo, PADS, CFG.min_pad_pixels,
                            CFG.surface_tol_m)


def test_label_of_a_pad_below_matches_hand_computation(world):
    # camera optical centre 5 cm below base_link: (4.4, 0.2, 2.95); pad 0 top centre (4.0, 0.5, 0.8)
    # optical x = -world y, optical y = -world x, optical z = -world z (yaw 0)
    frame, lab = _label(world, (4.4, 0.2, 3.0))
    assert lab.visible and lab.index == 0
    np.testing.assert_allclose(lab.xyz, [-0.3, 0.4, 2.15], atol=1e-5)
    # the renderer agrees: the label projects onto pad-top pixels at depth Z
    x, y, z = lab.xyz
    u = frame.K[0, 0] * x / z + frame.K[0, 2]
    v = frame.K[1, 1] * y / z + frame.K[1, 2]
    assert abs(float(frame.depth[int(round(v)), int(round(u))]) - 2.15) < 0.03
    assert lab.pixels[0] > 100 and lab.pixels[1:].sum() == 0


def test_no_visible_pad_is_flagged_not_dropped(world):
    # 0.95 m above the floor between pad 0 and pad 1: footprint x in about [5.5, 6.5]
    _, lab = _label(world, (6.0, 0.5, 1.0))
    assert not lab.visible and lab.index == -1
    assert np.isnan(lab.xyz).all()
    assert lab.pixels.sum() == 0


def test_closest_visible_pad_is_nearest_in_3d(world):
    # high above the gap: pads 0 and 1 both in view; pad 1 (taller, 3.62 m away) beats pad 0 (4.16 m)
    _, lab = _label(world, (6.0, 0.5, 4.5))
    assert (lab.pixels[:2] >= CFG.min_pad_pixels).all()
    assert lab.visible and lab.index == 1
    np.testing.assert_allclose(lab.xyz, [0.0, -1.6, 4.45 - 1.2], atol=1e-5)


def test_partially_visible_pad_below_pixel_threshold_is_not_visible(world):
    _, lab = _label(world, (4.4, 0.2, 3.0))
    small = DatasetConfig(min_pad_pixels=int(lab.pixels[0]) + 1)
    frame = world.render_from(np.array((4.4, 0.2, 3.0)), 0.0)
    cam, r_wo = world.camera_pose(np.array((4.4, 0.2, 3.0)), 0.0)
    lab2 = pad_label(frame.depth, frame.K, cam, r_wo, PADS, small.min_pad_pixels, small.surface_tol_m)
    assert not lab2.visible


def test_render_scene_is_deterministic(world):
    a = render_scene(world, 3, CFG, 10)
    b = render_scene(world, 3, CFG, 10)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert a['rgb'].shape == (10, 64, 64, 3) and a['depth_mm'].dtype == np.uint16


def test_make_dataset_shards_resume_and_split(tmp_path):
    cfg = DatasetConfig(out_dir=str(tmp_path / 'ds'), frames=120, frames_per_scene=50,
                        scenes_per_shard=1, seed=7)
    s1 = make_dataset(cfg, progress=False)
    assert s1['generated'] == 120
    full = load_frames(cfg.out_dir)
    assert len(full) == 120 and set(np.unique(full.scene)) == {0, 1, 2}
    assert np.isnan(full.xyz[~full.visible]).all() and np.isfinite(full.xyz[full.visible]).all()
    shard_path(tmp_path / 'ds', 1).unlink()
    s2 = make_dataset(cfg, progress=False)
    assert s2['generated'] == 50 and s2['reused'] == 70
    again = load_frames(cfg.out_dir)
    np.testing.assert_array_equal(again.depth, full.depth)
    np.testing.assert_array_equal(again.rgb, full.rgb)
    tr, va = split_by_scene(full, 0.34, seed=0)
    assert len(np.intersect1d(full.scene[tr], full.scene[va])) == 0 and len(tr) + len(va) == 120
    with pytest.raises(ValueError, match='different dataset'):
        make_dataset(DatasetConfig(out_dir=cfg.out_dir, frames=120, seed=8), progress=False)
