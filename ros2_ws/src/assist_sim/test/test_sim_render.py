"""The analytic renderer against pybullet's TinyRenderer (the baseline), pixel for pixel."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from assist_sim.core.config import WorldConfig
from assist_sim.core.render import FACE_UV, SceneRenderer
from assist_sim.core.world import R_BODY_FROM_OPTICAL, LandingWorld


@pytest.fixture(scope='module')
def world():
    cfg = WorldConfig()
    cfg.camera.renderer = 'analytic'
    w = LandingWorld(cfg, seed=0)
    yield w
    w.close()


def _poses(world, rng):
    """Camera poses over this scene: above pad edges (level and yawed), tilted, next to walls."""
    cam_cfg = world.cfg.camera
    (x0, y0), (x1, y1) = world.scene.room_min, world.scene.room_max
    out = []
    for k in range(8):
        pad = world.scene.pads[int(rng.integers(len(world.scene.pads)))]
        kind = ('edge', 'yaw', 'tilt', 'wall')[k % 4]
        if kind == 'wall':
            base = np.array([rng.choice([x0 + 0.6, x1 - 0.6, rng.uniform(x0, x1)]),
                             rng.choice([y0 + 0.5, y1 - 0.5]), rng.uniform(2.0, 5.0)])
        else:
            # the camera's footprint straddles the pad's outline
            half = max(pad.length, pad.width) / 2
            base = np.array([pad.center[0] + rng.choice([-1, 1]) * half + rng.uniform(-0.3, 0.3),
                             pad.center[1] + rng.uniform(-half, half), rng.uniform(pad.height + 0.5, 4.5)])
        yaw = float(rng.uniform(-math.pi, math.pi)) if kind in ('yaw', 'tilt') else 0.0
        if kind == 'tilt':
            r_wb = Rotation.from_euler('xyz', [rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), yaw]).as_matrix()
            cam = base + r_wb @ np.array([0.0, 0.0, -cam_cfg.offset_below_base_m])
            out.append((kind, cam, r_wb @ R_BODY_FROM_OPTICAL))
        else:
            out.append((kind,) + world.camera_pose(base, yaw))
    return out


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_analytic_frames_match_tinyrenderer(world, seed):
    world.reset(seed)
    rng = np.random.default_rng(seed)
    edges = 0
    for kind, cam, r_wo in _poses(world, rng):
        fast = world.render_pose(cam, r_wo)
        slow = world._render_pybullet(cam, r_wo)
        assert fast.rgb.dtype == slow.rgb.dtype == np.uint8 and fast.depth.dtype == slow.depth.dtype == np.float32
        assert fast.rgb.shape == slow.rgb.shape and fast.depth.shape == slow.depth.shape
        dd = np.abs(fast.depth - slow.depth)
        # same surfaces at the same depth: only rasteriser ties on a few edge pixels may differ
        assert np.median(dd) < 1e-5, kind
        assert (dd > 1e-3).mean() < 0.005, (kind, (dd > 1e-3).sum())
        diff = np.abs(fast.rgb.astype(int) - slow.rgb.astype(int))
        assert diff.mean() < 0.25, (kind, diff.mean())
        assert (diff.max(axis=-1) > 0).mean() < 0.005, (kind, (diff.max(axis=-1) > 0).sum())
        edges += int((np.abs(np.diff(slow.depth, axis=1)) > 0.2).sum())
    assert edges > 50          # the poses did look at pad outlines (depth steps), not just floor


def test_every_box_face_is_textured_affinely_from_a_quarter_of_the_texture():
    for (axis, sign), m in FACE_UV.items():
        corners = np.array([[1, a, b] for a in (-1, 1) for b in (-1, 1)], float) @ m
        span = corners.max(axis=0) - corners.min(axis=0)
        assert np.allclose(span, 0.25), (axis, sign)
        assert corners.min() >= 0 and corners.max() <= 1


def test_renderer_selection_and_bad_value():
    cfg = WorldConfig()
    cfg.camera.renderer = 'pybullet'
    w = LandingWorld(cfg, seed=0)
    try:
        w.reset(4)
        assert w._analytic is False
        frame = w.render_from(tuple(w.goal_position[:2]) + (3.0,))
        assert frame.depth.min() < 3.0                 # the goal pad under the camera
    finally:
        w.close()
    cfg.camera.renderer = 'raytraced'
    with pytest.raises(ValueError, match='renderer'):
        LandingWorld(cfg, seed=0)


def test_scene_renderer_without_world_depth_of_a_pad_top(world):
    world.reset(5)
    c = world.cfg.camera
    r = SceneRenderer(world.scene, width=c.width, height=c.height, vertical_fov_deg=c.vertical_fov_deg,
                      near_m=c.near_m, far_m=c.far_m, floor_tile_m=c.floor_tile_m, floor_shading=c.floor_shading)
    pad = world.scene.pads[2]
    cam = np.array([pad.center[0], pad.center[1], pad.height + 1.0])
    rgb, depth = r.render(cam, R_BODY_FROM_OPTICAL)      # level, heading +x
    assert depth[30:34, 30:34] == pytest.approx(1.0, abs=1e-6)
    assert rgb.shape == (c.height, c.width, 3) and rgb.dtype == np.uint8


def test_pads_hiding_each_other_and_walls_from_a_grazing_view(world):
    """Looking along the row of pads from low and far back: pads overlap in the image (nearest
    wins) and the far walls show; still the same picture as TinyRenderer."""
    world.reset(6)
    first = world.scene.pads[0]
    for pitch in (0.9, 1.2):                          # camera pitched up from straight down (rad)
        r_wb = Rotation.from_euler('xyz', [0.0, -pitch, 0.0]).as_matrix()
        cam = np.array([first.center[0] - 3.0, first.center[1], 1.6])
        r_wo = r_wb @ R_BODY_FROM_OPTICAL
        fast, slow = world.render_pose(cam, r_wo), world._render_pybullet(cam, r_wo)
        near_pads = (slow.depth < 12.0) & (slow.depth > 0.5)
        assert near_pads.mean() > 0.1
        dd = np.abs(fast.depth - slow.depth)
        assert (dd > 1e-3).mean() < 0.01, (pitch, (dd > 1e-3).sum())
        diff = np.abs(fast.rgb.astype(int) - slow.rgb.astype(int)).max(axis=-1)
        assert (diff > 0).mean() < 0.01, (pitch, (diff > 0).sum())
