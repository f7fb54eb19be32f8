"""Unit tests of the pure simulation core (no ROS)."""
import math

import cv2
import numpy as np
import pytest

from assist_sim.core.config import WorldConfig
from assist_sim.core.runner import RunnerConfig, SimRunner, validate_velocity
from assist_sim.core.scene import PadSpec, SceneSpec, generate_scene
from assist_sim.core.textures import make_texture
from assist_sim.core.world import LandingWorld, turbulence_sigma


@pytest.fixture(scope='module')
def world():
    w = LandingWorld(WorldConfig(), seed=0)
    yield w
    w.close()


def _flat_scene(pad_height=0.8) -> SceneSpec:
    """One scene with five known 1 m pads at x = 0, 4, 8, 12, 16 (pad 2 at x=8, y=0)."""
    pads = tuple(PadSpec(center=(4.0 * i, 0.0), length=1.0, width=1.0, height=pad_height, yaw=0.0,
                         material=i) for i in range(5))
    return SceneSpec(seed=0, pads=pads, floor_material=10, wall_material=11, start_position=(-3.0, 0.0, 3.0),
                     room_min=(-8.0, -6.0), room_max=(26.0, 6.0))


def _drop(world, xy, height_above, goal=2, pad_height=0.8, max_s=6.0):
    """Place the vehicle above `xy`, cut the motors, and run until the judge decides."""
    scene = _flat_scene(pad_height)
    ground = pad_height if any(pd.contains_xy(np.array(xy)) for pd in scene.pads) else 0.0
    start = (xy[0], xy[1], ground + world.cfg.vehicle.leg_length_m + height_above)
    world.reset(0, scene=scene, goal_index=goal, start_position=start)
    world.set_armed(False)
    # the judge arms once the vehicle has been high enough; start it explicitly for drops
    world._judge_active = True
    t_end = world.time + max_s
    while not world.done and world.time < t_end:
        world.step(np.zeros(3))
    return world.result


def test_scene_is_deterministic_and_matches_the_paper_layout():
    a, b, c = generate_scene(7), generate_scene(7), generate_scene(8)
    assert a == b
    assert a != c
    xs = np.array([p.center[0] for p in a.pads])
    assert len(a.pads) == 5 and np.all(np.diff(xs) > 0)
    gaps = np.concatenate([np.diff([p.center[0] for p in generate_scene(s).pads]) for s in range(200)])
    assert 3.7 < gaps.mean() < 4.3                      # paper: mean gap near 4 m
    mats = {p.material for p in a.pads} | {a.floor_material, a.wall_material}
    assert len(mats) == 7                                # distinct textures in one scene


def test_textures_are_files_in_the_user_cache_and_still_made_with_the_cache_off(monkeypatch, tmp_path):
    from assist_sim.core import textures
    monkeypatch.setenv('ASSIST_CACHE_DIR', str(tmp_path))
    png = textures.texture_path(3, 16)
    assert png.parent == tmp_path / f'textures_v{textures.TEXTURE_VERSION}' and png.is_file()
    assert cv2.imread(str(png)).shape == (16, 16, 3)
    monkeypatch.setenv('ASSIST_CACHE_DIR', 'off')             # pybullet reads files: a scratch folder then
    scratch = textures.texture_path(3, 16)
    assert scratch.is_file() and not scratch.is_relative_to(tmp_path)


def test_52_distinct_deterministic_materials():
    imgs = [make_texture(i) for i in range(52)]
    assert all(img.shape == (64, 64, 3) and img.dtype == np.uint8 for img in imgs)
    assert np.array_equal(make_texture(5), imgs[5])
    flat = {img.tobytes() for img in imgs}
    assert len(flat) == 52
    means = np.array([img.reshape(-1, 3).mean(0) for img in imgs])
    assert np.ptp(means, axis=0).min() > 60            # they really look different


def test_same_seed_same_episode():
    def run(seed):
        w = LandingWorld(seed=seed)
        w.reset()
        traj = [w.step(np.array([0.8, 0.1, -0.2])).position for _ in range(40)]
        goal = w.goal_index
        w.close()
        return np.array(traj), goal
    a, ga = run(3)
    b, gb = run(3)
    c, _ = run(4)
    assert ga == gb and np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_drop_on_goal_centre_is_success(world):
    r = _drop(world, (8.0, 0.0), 0.3)
    assert r is not None and r.outcome == 'success' and r.success and not r.crash
    assert r.landed_index == 2 and r.error_m < 0.05


def test_drop_on_other_pad_is_wrong_pad(world):
    r = _drop(world, (12.0, 0.0), 0.3, goal=2)
    assert r.outcome == 'wrong_pad' and not r.success and r.landed_index == 3
    assert r.error_m == pytest.approx(4.0, abs=0.05) and r.nearest_index == 3


def test_drop_on_floor_is_crash(world):
    r = _drop(world, (6.0, 0.0), 0.3)
    assert r.crash and not r.success and r.outcome == 'crash'


def test_drop_half_over_an_edge_is_not_success(world):
    # pad 2 spans x in [7.5, 8.5]; put the body centre on the edge line: two legs over the pad
    r = _drop(world, (8.5, 0.0), 0.2)
    assert r is not None and not r.success


def test_fast_impact_is_crash(world):
    scene = _flat_scene()
    world.reset(0, scene=scene, goal_index=2, start_position=(8.0, 0.0, 4.0))
    world.set_armed(False)              # free fall from ~3 m: ~7 m/s at impact
    while not world.done and world.time < 1000:
        world.step(np.zeros(3))
    assert world.result.crash and 'impact' in world.result.reason


def test_velocity_step_response_respects_limits(world):
    cfg = world.cfg.controller
    world.reset(1, scene=_flat_scene(), goal_index=0, start_position=(-3.0, 0.0, 3.0))
    world.cfg.turbulence.enabled = False
    try:
        dt = 1.0 / world.cfg.control_hz
        vs = []
        for _ in range(60):                              # 3 s
            vs.append(world.step(np.array([2.0, 0.0, 0.0])).velocity.copy())
        vs = np.array(vs)
        acc = np.diff(vs[:, 0]) / dt
        assert acc.max() <= cfg.max_accel_xy_mps2 * 1.1
        assert vs[-1, 0] == pytest.approx(2.0, abs=0.05)  # tracks the command
        assert vs[:, 0].max() < 2.0 * 1.05                # no large overshoot
        assert np.abs(vs[:, 2]).max() < 0.1               # altitude held
        # commands beyond the speed limits are clamped
        for _ in range(80):
            st = world.step(np.array([10.0, 0.0, 10.0]))
        assert math.hypot(*st.velocity[:2]) <= cfg.max_speed_xy_mps * 1.02
        assert st.velocity[2] <= cfg.max_climb_mps * 1.02
        assert abs(st.yaw) < 0.01                         # constant yaw
    finally:
        world.cfg.turbulence.enabled = True


def test_non_finite_command_raises(world):
    world.reset(2)
    with pytest.raises(ValueError):
        world.step(np.array([np.nan, 0.0, 0.0]))


def test_depth_over_flat_floor_matches_height(world):
    world.reset(0, scene=_flat_scene(), goal_index=0)
    h = 2.5
    frame = world.render_from((-4.0, 0.0, h))            # nothing but floor below
    cam_h = h - world.cfg.camera.offset_below_base_m
    assert frame.depth.dtype == np.float32 and frame.rgb.dtype == np.uint8
    assert frame.depth.shape == (64, 64) and frame.rgb.shape == (64, 64, 3)
    # z-depth of a plane parallel to the image is the height everywhere
    assert np.abs(frame.depth / cam_h - 1).max() < 0.01
    # intrinsics: the principal point projects straight down
    assert frame.K[0, 2] == pytest.approx(31.5) and frame.K[0, 0] == pytest.approx(32 / math.tan(math.radians(29)))


def test_camera_orientation_top_of_image_is_forward(world):
    world.reset(0, scene=_flat_scene(pad_height=1.0), goal_index=0)
    # camera 1 m behind pad 0 (x=0): the pad appears in the top half of the image
    frame = world.render_from((-1.0, 0.0, 3.0))
    top, bottom = frame.depth[:20].min(), frame.depth[-20:].min()
    assert top < bottom - 0.5
    # pad to the left (+y) appears on the image's left side (optical x = body -y)
    frame = world.render_from((0.0, -1.0, 3.0))
    assert frame.depth[:, :20].min() < frame.depth[:, -20:].min() - 0.5


def test_turbulence_grows_near_the_surface():
    cfg = WorldConfig()
    t = cfg.turbulence
    assert turbulence_sigma(0.0, t) == pytest.approx(t.sigma_far_mps + t.sigma_ground_mps)
    assert turbulence_sigma(0.2, t) > turbulence_sigma(1.0, t) > turbulence_sigma(3.0, t) > t.sigma_far_mps
    w = LandingWorld(cfg, seed=0)

    def noise_std(height):
        samples = []
        for k in range(8):
            w.reset(5 + k, scene=_flat_scene(), goal_index=0, start_position=(-3.0, 0.0, height))
            samples += [w.step(np.zeros(3)) is not None and w.turbulence_velocity for _ in range(30)]
        return float(np.std(np.array(samples)[:, :2]))
    far, near = noise_std(4.0), noise_std(0.7)
    w.close()
    expected_near = turbulence_sigma(0.7 - cfg.vehicle.leg_length_m, t)
    expected_far = turbulence_sigma(4.0 - cfg.vehicle.leg_length_m, t)
    assert near > 2.5 * far
    assert near == pytest.approx(expected_near, rel=0.35)
    assert far == pytest.approx(expected_far, rel=0.35)


def test_validate_velocity():
    assert validate_velocity([1, 2, 3], 5.0)[1] is None
    assert 'non-finite' in validate_velocity([np.inf, 0, 0], 5.0)[1]
    assert 'limit' in validate_velocity([9, 0, 0], 5.0)[1]
    assert 'components' in validate_velocity([1, 2], 5.0)[1]


def test_runner_stale_commands_and_auto_reset(world):
    runner = SimRunner(world, RunnerConfig(camera_rate_hz=10.0, auto_reset=True, reset_delay_s=0.2,
                                           cmd_timeout_s=0.5))
    runner.reset(11)
    assert runner.set_command([1.0, 0.0, 0.0]) is None
    assert runner.command[0] == 1.0
    frames = 0
    for _ in range(20):                                  # 1 s without a new command
        frames += runner.step().frame is not None
    assert runner.command_stale and np.all(runner.command == 0)
    assert frames == 10                                  # 10 Hz camera over 1 s
    assert runner.set_command([np.nan, 0, 0]) is not None and runner.commands_rejected == 1
    # force an ending: drop onto the floor
    ep = world.episode
    world.set_armed(False)
    landing, new_ep = None, False
    for _ in range(200):
        out = runner.step()
        landing = landing or out.landing
        new_ep = new_ep or out.new_episode
        if new_ep:
            break
    assert landing is not None and landing.crash
    assert new_ep and world.episode == ep + 1 and not world.done and world.armed


def test_runner_publishes_no_frame_of_the_last_episode_at_a_reset(world):
    """A frame rendered in the reset step showed the landed pose and old scene, stamped with the new start's time."""
    runner = SimRunner(world, RunnerConfig(camera_rate_hz=world.cfg.control_hz, auto_reset=True, reset_delay_s=0.2))
    runner.reset(11)
    world.set_armed(False)                               # drop onto the floor: the episode ends
    frames_before_reset = 0
    for _ in range(200):
        out = runner.step()
        if out.new_episode:
            break
        frames_before_reset += out.frame is not None
    assert out.new_episode and frames_before_reset > 0   # a frame every step until then
    assert out.frame is None
    assert runner.step().frame is not None               # the new episode's frames follow


def test_runner_episode_seeds_give_each_episode_its_scene(world):
    """RunnerConfig.episode_seeds: episode i gets scene seed i of the list, then the world's own sequence."""
    runner = SimRunner(world, RunnerConfig(episode_seeds=(7, 123)))
    runner.reset()
    first = (world.scene, world.goal_index)
    runner.reset()
    second = (world.scene, world.goal_index)
    ref = LandingWorld(WorldConfig(), seed=99)
    try:
        for seed, (scene, goal) in zip((7, 123), (first, second)):
            ref.reset(seed=seed)
            assert scene == ref.scene and goal == ref.goal_index
    finally:
        ref.close()
    runner.reset()                                   # past the list: the world's sequence, not an error
    assert runner.episodes_started == 3 and world.scene not in (first[0], second[0])


def test_world_config_yaml_roundtrip(tmp_path):
    path = tmp_path / 'w.yaml'
    path.write_text('control_hz: 40\ncamera:\n  width: 32\nturbulence:\n  enabled: false\n')
    cfg = WorldConfig.from_yaml(path)
    assert cfg.control_hz == 40 and cfg.camera.width == 32 and cfg.camera.height == 64
    assert cfg.turbulence.enabled is False
    path.write_text('no_such_field: 1\n')
    with pytest.raises(ValueError, match='no_such_field'):
        WorldConfig.from_yaml(path)


def test_analytic_floor_matches_the_rasterised_floor():
    cfg = WorldConfig()
    cfg.camera.renderer = 'pybullet'                    # TinyRenderer, floor rasterised too
    cfg.camera.analytic_floor = False
    fast_cfg = WorldConfig()
    fast_cfg.camera.renderer = 'pybullet'               # TinyRenderer pads + analytic floor
    fast, slow = LandingWorld(fast_cfg, seed=1), LandingWorld(cfg, seed=1)
    fast.reset(3)
    slow.reset(3)
    try:
        for pos in [(-3.0, 0.0, 3.0), (-4.0, 2.0, 2.0), (1.0, -3.0, 4.0), (tuple(fast.goal_position[:2]) + (2.5,))]:
            a, b = fast.render_from(pos), slow.render_from(pos)
            assert np.abs(a.depth - b.depth).max() < 1e-3
            diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int))
            assert diff.mean() < 8 and (diff.max(-1) > 40).mean() < 0.05
    finally:
        fast.close()
        slow.close()


def test_runner_flies_one_scene_and_the_goal_pads_it_is_given():
    """scene_seed / goal_index (a user study's fixed scene and landing sequence) apply at every reset."""
    world = LandingWorld(seed=1)
    try:
        runner = SimRunner(world, RunnerConfig(camera_rate_hz=0.0, scene_seed=7, goal_index=3))
        runner.reset()
        pads, start = world.pad_top_centers.copy(), np.array(world.state.position)
        assert world.goal_index == 3
        runner.cfg.goal_index = 0
        runner.reset()
        assert world.goal_index == 0
        np.testing.assert_allclose(world.pad_top_centers, pads)          # the same scene, another goal
        np.testing.assert_allclose(world.state.position, start, atol=1e-6)
        runner.cfg.scene_seed, runner.cfg.goal_index = -1, -1
        runner.reset()
        assert not np.allclose(world.pad_top_centers, pads)              # back to the seed's sequence
    finally:
        world.close()
