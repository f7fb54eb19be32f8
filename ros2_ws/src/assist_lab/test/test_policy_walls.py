"""Wall guard (assist_policy.walls): walls found in rendered depth frames, commands kept off them."""
import math

import numpy as np
import pytest

from assist_lab.evaluate import make_policy, run_landing
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_policy.safety import SafetyConfig
from assist_policy.walls import WallGuard
from assist_sim.core.scene import PadSpec, SceneSpec

from assist_policy.testing import LATENT, constant_actor

# the room's end wall stands at x = 30 (SceneSpec's default room), 6 m tall; a 1.2 m pad at x = 5
PAD = PadSpec(center=(5.0, 0.0), length=1.0, width=1.0, height=1.2, yaw=0.0, material=3)
SCENE = SceneSpec(seed=0, pads=(PAD,), floor_material=1, wall_material=2, start_position=(0.0, 0.0, 3.0))
WALL_X = SCENE.room_max[0]


def _yaw_quat(yaw):
    return np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


def test_a_wall_at_the_edge_of_the_view_is_marked_a_pad_or_the_floor_never(depth_at):
    g = WallGuard()
    assert g.observe(depth_at(WALL_X - 1.2, 0.0, 4.5), [WALL_X - 1.2, 0.0, 4.5]) >= 4
    xs = [(i + 0.5) * g.cfg.wall_cell_m for i, _ in g.cells]
    assert min(xs) > WALL_X - 0.3 and max(xs) < WALL_X + 0.3          # the cells lie on the wall
    dist, unit = g.near([WALL_X - 1.2, 0.0])
    assert dist[0] == pytest.approx(1.2, abs=0.2) and unit[0, 0] > 0.95 and np.all(np.diff(dist) >= 0)
    g.reset()
    assert g.observe(depth_at(5.0, 0.0, 2.5), [5.0, 0.0, 2.5]) == 0     # a 1.2 m pad below: not a wall
    assert g.observe(depth_at(15.0, 0.0, 4.5), [15.0, 0.0, 4.5]) == 0   # bare floor
    assert g.observe(depth_at(WALL_X - 3.5, 0.0, 4.5), [WALL_X - 3.5, 0.0, 4.5]) == 0   # wall out of view
    assert not g.cells and len(g.near([WALL_X - 0.5, 0.0])[0]) == 0


def test_the_approach_to_a_remembered_wall_is_removed_from_v_and_nothing_else(depth_at):
    g = WallGuard()
    g.observe(depth_at(WALL_X - 1.2, 0.0, 4.5), [WALL_X - 1.2, 0.0, 4.5])
    p = [WALL_X - 1.0, 0.0, 1.5]          # lower now: the wall is out of view, its cells remembered
    u = np.array([1.0, 0.0, -0.5])
    _, units = g.near(p[:2])
    assert len(units) >= 3                                             # a stretch of wall within reach
    for v in ([0.8, 0.5, -0.3], [1.0, 0.0, 0.2], [0.3, -1.0, 0.0]):
        r = g.apply(u, None, np.array(v), p, None)
        assert r.engaged and r.velocity[2] == v[2]                    # vertical untouched
        assert np.all(units @ r.velocity[:2] <= 1e-6)                 # toward no wall cell within reach
        assert np.linalg.norm(r.velocity[:2]) <= np.linalg.norm(v[:2]) + 1e-9
        np.testing.assert_allclose(r.agent, 2 * r.velocity - u)        # shown as the assistant's action
    assert not g.apply(u, None, np.array([-0.8, 0.5, -0.3]), p, None).engaged      # away from it
    r = g.apply(u, None, np.array([0.0, 1.0, 0.0]), p, None)          # along it: slowed, never toward it
    assert r.engaged and r.velocity[0] <= 1e-9 and 0.2 < r.velocity[1] < 1.0
    assert not g.apply(u, None, np.array([1.0, 0.0, 0.0]), [WALL_X - 2.0, 0.0, 1.5], None).engaged   # > 1.5 m
    # heading 90 degrees: the wall (odom +x) is on the vehicle's right, base_link -y
    r = g.apply(u, None, np.array([0.3, -0.8, 0.0]), p, _yaw_quat(math.pi / 2))
    assert r.engaged and r.velocity[1] > -0.05                          # no longer toward the wall (base_link -y)
    assert not g.apply(u, None, np.array([0.0, 0.8, 0.0]), p, _yaw_quat(math.pi / 2)).engaged   # away: left
    g.cfg.wall_radius_m = 0.0                                          # off
    assert not g.apply(u, None, np.array([1.0, 0.0, 0.0]), p, None).engaged
    assert g.observe(depth_at(WALL_X - 1.2, 0.0, 4.5), [WALL_X - 1.2, 0.0, 4.5]) == 0
    g.cfg.wall_radius_m, g.cfg.enabled = 1.5, False                    # the floor guard's switch turns it off too
    assert not g.apply(u, None, np.array([1.0, 0.0, 0.0]), p, None).engaged


def test_policy_core_stops_the_actor_flying_into_a_wall(tmp_path, depth_at):
    path = constant_actor(tmp_path / 'east.pt', [0.9, 0.0, 0.0])         # actor pushes +x at 0.9 m/s
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    x, z = WALL_X - 1.2, 4.5
    core.set_odom(1.0, [x, 0, z], [0, 0, 0])
    core.set_pilot(1.0, [0.0, 0.0, 0.0])
    core.set_latent(1.0, np.zeros(LATENT))
    core.set_depth(1.0, depth_at(x, 0.0, z))
    out = core.step(1.0)
    assert out.key == 'wall_guard' and core.engaged['wall_guard'] == 1
    assert out.velocity[0] == pytest.approx(0.0, abs=0.05) and out.agent[0] < 0.1
    core.guard.cfg.wall_radius_m = 0.0                                   # policy_node's parameter
    core.set_odom(1.05, [x, 0, z], [0, 0, 0])
    out = core.step(1.05)
    assert out.key == 'assisting' and out.velocity[0] > 0.3


def test_the_cautious_novice_who_flew_into_the_end_wall_now_stops_short_of_it():
    """Traced landing (cautious, beta 0, seed 11): the pilot's aim lies beyond the last pad and the actor pushed
    the same way at 4.8 m; it hit the end wall and fell. With the wall rule it hovers short of it."""
    env, policy = make_policy('latent', '', '', 60.0, 0.5, 'cautious', rules={'safety': SafetyConfig()})
    try:
        row = run_landing(env, policy, 11, 0.0)
        assert not row['crash'] and row['wall_fraction'] > 0.02, row
        env.cfg.safety.wall_radius_m = 0.0
        row = run_landing(env, policy, 11, 0.0)
        assert row['crash'] and row['wall_fraction'] == 0.0, row
    finally:
        env.close()
