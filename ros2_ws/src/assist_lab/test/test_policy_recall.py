"""Pad recall (assist_policy.recall): the pad map on depth images rendered in the LandingWorld, the rule, PolicyCore."""
import csv
import math

import numpy as np
import pytest

from assist_policy.blending import blend
from assist_lab.env import EnvConfig, LandingAssistEnv
from assist_lab.evaluate import EvalArgs, evaluate
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_policy.flight import FlightConfig
from assist_policy.recall import PadMap, PadRecall, RecallConfig
from assist_common.frames import R_BODY_FROM_OPTICAL, quat_to_matrix
from assist_sim.core.scene import PadSpec, SceneSpec
from assist_sim.core.world import LandingWorld

from assist_policy.testing import LATENT, constant_actor

PADS = (PadSpec(center=(5.0, 0.5), length=1.2, width=1.0, height=0.8, yaw=0.3, material=3),
        PadSpec(center=(9.0, -0.5), length=1.0, width=1.4, height=0.5, yaw=-0.2, material=4))
SCENE = SceneSpec(seed=0, pads=PADS, floor_material=1, wall_material=2, start_position=(0.0, 0.0, 3.5))
TOPS = np.array([[5.0, 0.5, 0.8], [9.0, -0.5, 0.5]])
MAX_SPEED = (1.0, 1.0, 0.6)

# the tests place the vehicle where they need it (odometry jumps): the flight monitor stays out of them
TELEPORTS = FlightConfig(enabled=False)


def _quat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of roll-pitch-yaw (ZYX)."""
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
                     cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy])


@pytest.fixture(scope='module')
def world():
    w = LandingWorld()
    w.reset(scene=SCENE)
    yield w
    w.close()


def _frame(world, position, q=None):
    """Depth image from base_link at `position` with attitude `q` (level, heading 0 when None)."""
    q = _quat(0.0, 0.0, 0.0) if q is None else q
    r_wb = quat_to_matrix(q)
    cam = np.asarray(position, dtype=float) + r_wb @ np.array([0.0, 0.0, -world.cfg.camera.offset_below_base_m])
    return world.render_pose(cam, r_wb @ R_BODY_FROM_OPTICAL).depth.copy()


def test_map_finds_each_pad_centre_and_top_from_a_level_and_a_tilted_camera(world):
    for q in (None, _quat(0.15, -0.12, 0.4)):          # ~9 and 7 degrees of tilt, heading 23 degrees
        m = PadMap()
        for pos in ([5.3, 0.3, 3.5], [9.2, -0.3, 3.4]):
            assert m.update(_frame(world, pos, q), np.array(pos), q) >= 1
        assert len(m.pads) == 2
        for pad, true in zip(sorted(m.pads, key=lambda p: p.xyz[0]), TOPS):
            assert pad.whole
            assert np.hypot(*(pad.xyz[:2] - true[:2])) < 0.08, (q, pad.xyz, true)
            assert abs(pad.xyz[2] - true[2]) < 0.05


def test_floor_and_walls_are_not_pads_and_holes_are_ignored(world):
    m = PadMap()
    assert m.update(_frame(world, [2.0, 0.0, 3.0]), np.array([2.0, 0.0, 3.0])) == 0      # bare floor
    assert m.update(_frame(world, [7.0, 5.0, 3.0]), np.array([7.0, 5.0, 3.0])) == 0      # a wall at y = 6 in view
    assert m.update(np.full((64, 64), np.nan, np.float32), np.array([5.0, 0.5, 3.0])) == 0
    assert m.pads == []
    with pytest.raises(ValueError):
        m.update(np.zeros((4, 4, 3)), np.array([5.0, 0.5, 3.0]))


def test_part_views_are_kept_only_until_a_better_one_and_never_move_a_centre_seen_whole(world):
    m = PadMap()
    edge, nearer = [6.5, 0.5, 3.0], [6.3, 0.5, 3.0]         # the pad cut by the image border
    m.update(_frame(world, edge), np.array(edge))
    assert len(m.pads) == 1 and not m.pads[0].whole
    first = m.pads[0].xyz.copy()
    assert first[0] > 5.3                                     # biased toward the image centre
    m.update(_frame(world, nearer), np.array(nearer))         # more of it in view: replaces
    assert m.pads[0].xyz[0] < first[0] and m.pads[0].area > 324
    m.update(_frame(world, edge), np.array(edge))             # less of it again: kept
    assert m.pads[0].xyz[0] < first[0]
    m.update(_frame(world, [5.0, 0.5, 3.5]), np.array([5.0, 0.5, 3.5]))
    whole = m.pads[0].xyz.copy()
    assert m.pads[0].whole and np.hypot(*(whole[:2] - TOPS[0, :2])) < 0.08
    m.update(_frame(world, nearer), np.array(nearer))
    assert len(m.pads) == 1 and np.allclose(m.pads[0].xyz, whole) and m.pads[0].sightings == 5


def test_a_full_resolution_frame_is_subsampled_and_maps_the_same_pad():
    for h, w in ((64, 64), (480, 848)):                       # the sim's frame and a RealSense D435i's
        f = (h / 2) / math.tan(math.radians(29.0))
        depth = np.full((h, w), 2.95, np.float32)              # floor from 3 m
        top = 2.15                                             # a 0.8 m pad, 1 m square, 0.5 m ahead (body +x)
        r0, c0, half = (h - 1) / 2 - f * 0.5 / top, (w - 1) / 2, f * 0.5 / top
        depth[int(round(r0 - half)):int(round(r0 + half)), int(round(c0 - half)):int(round(c0 + half))] = top
        m = PadMap()
        assert m.update(depth, np.array([0.0, 0.0, 3.0])) == 1
        assert np.hypot(m.pads[0].xyz[0] - 0.5, m.pads[0].xyz[1]) < 0.06 and m.pads[0].xyz[2] == pytest.approx(0.8)
    with pytest.raises(ValueError):
        RecallConfig(max_image_px=4)


def test_a_side_face_seen_low_beside_a_pad_is_not_a_pad(world):
    m = PadMap()
    beside = [6.0, 0.9, 1.6]                                  # mostly the pad's side face in view, its top a sliver
    assert m.update(_frame(world, beside), np.array(beside)) == 0
    assert m.pads == []


def _mapped(world, *positions) -> PadRecall:
    r = PadRecall()
    for pos in positions:
        r.observe(_frame(world, pos), np.array(pos))
    return r


def test_a_descent_over_the_floor_is_steered_back_to_the_pad_it_passed(world):
    pos = np.array([6.6, 0.4, 2.5])                      # 1.6 m past the pad, floor beneath
    r = _mapped(world, [5.0, 0.5, 3.5], pos)             # (in view from here: the ground 1.2 m beyond, no pad)
    u = np.array([0.0, 0.0, -0.5])
    actor = np.array([0.2, 0.1, -0.3])
    a = r.apply(u, np.zeros(3), actor, _frame(world, pos), pos, None, MAX_SPEED)
    assert a is not None
    assert a[0] == pytest.approx(-1.0) and abs(a[1]) < 1.0      # toward the pad (x), clipped at max_speed
    assert a[2] == actor[2]                                    # high over its top: the actor's vertical stays
    v = blend(u, a)
    assert v[0] < -0.4


def test_the_rule_stays_out_when_idle_high_over_it_leaving_or_disabled(world):
    r = _mapped(world, [5.0, 0.5, 3.5])
    pos = np.array([6.6, 0.4, 2.5])
    depth = _frame(world, pos)
    actor = np.zeros(3)
    assert r.apply(np.zeros(3), np.zeros(3), actor, depth, pos, None, MAX_SPEED) is None        # idle, 1.7 m over it
    leaving = np.array([1.0, 0.0, 0.0])                        # 1 s mean command away from the pad
    assert r.apply(np.array([1.0, 0, -0.5]), leaving, actor, depth, pos, None, MAX_SPEED) is None
    assert r.apply(np.array([1.0, 0, -0.5]), np.zeros(3), actor, depth, pos, None, MAX_SPEED) is None  # key now
    assert r.apply(np.array([0.0, 0, -0.5]), leaving, actor, depth, pos, None, MAX_SPEED) is None     # last second
    toward = -leaving
    assert r.apply(np.array([-1.0, 0, -0.5]), toward, actor, depth, pos, None, MAX_SPEED) is not None
    assert r.apply(np.array([0.3, 0, -0.5]), np.zeros(3), actor, depth, pos, None, MAX_SPEED) is not None  # a creep
    over = np.array([5.1, 0.5, 2.0])                           # over the pad: the actor sees it
    assert r.apply(np.array([0, 0, -0.5]), np.zeros(3), actor, _frame(world, over), over, None, MAX_SPEED) is None
    far = np.array([8.4, 2.5, 2.5])                            # 3.6 m from the pad seen, the other never seen
    assert r.apply(np.array([0, 0, -0.5]), np.zeros(3), actor, _frame(world, far), far, None, MAX_SPEED) is None
    off = PadRecall(RecallConfig(enabled=False))
    off.observe(_frame(world, [5.0, 0.5, 3.5]), np.array([5.0, 0.5, 3.5]))
    assert off.map.pads == []
    assert off.apply(np.array([0, 0, -0.5]), np.zeros(3), actor, depth, pos, None, MAX_SPEED) is None


def test_a_pad_behind_is_gone_back_to_only_after_a_look_beyond_where_a_nearer_one_may_be(world):
    # a glide pilot passed pad 0 and descends 2 m on, short of pad 1 (out of view: the camera sees ~1 m ahead)
    start = np.array([7.3, -0.2, 1.9])                         # 2.3 m past pad 0's centre, 1.7 m short of pad 1's
    r = _mapped(world, [5.0, 0.5, 3.5], [6.0, 0.3, 2.4], start)
    assert len(r.map.pads) == 1
    u = np.array([0.0, 0.0, -0.4])
    a = r.apply(u, np.zeros(3), np.array([-0.8, 0.0, -0.6]), _frame(world, start), start, None, MAX_SPEED)
    assert r.mode == 'scout' and a[0] > 0.5                   # on, not back (the actor pushed back)
    assert blend(u, a)[2] == pytest.approx(0.0)                # no descent while it looks: the camera sees farther
    pos = start.copy()
    for _ in range(40):                                        # fly what it asks (20 Hz), mapping as it goes
        if r.mode != 'scout':
            break
        pos[:2] += 0.05 * blend(u, a)[:2]
        r.observe(_frame(world, pos), pos)
        a = r.apply(u, np.zeros(3), np.zeros(3), _frame(world, pos), pos, None, MAX_SPEED)
    assert r.mode == 'recall' and len(r.map.pads) == 2         # pad 1 found, nearer: steered to it
    assert pos[0] - start[0] < 1.2 and a[0] > 0.0                # found before scout_max_m
    # a pilot coming back toward the pad behind knows it is there: straight back
    back = _mapped(world, [5.0, 0.5, 3.5], start)
    a = back.apply(np.array([-0.5, 0.0, -0.4]), np.zeros(3), np.zeros(3), _frame(world, start), start, None, MAX_SPEED)
    assert back.mode == 'recall' and a[0] < 0
    off = PadRecall(RecallConfig(scout_max_m=0.0))
    for p in ([5.0, 0.5, 3.5], start):
        off.observe(_frame(world, p), np.array(p))
    assert off.apply(u, np.zeros(3), np.zeros(3), _frame(world, start), start, None, MAX_SPEED)[0] < 0
    assert off.mode == 'recall'


def test_nothing_beyond_the_scout_goes_back_to_the_pad_as_far_as_it_went(world):
    start = np.array([11.0, -0.5, 1.9])                        # 2 m past the last pad (pad 1), nothing beyond
    r = _mapped(world, [9.0, -0.5, 3.0], start)
    u = np.array([0.0, 0.0, -0.4])
    pos, modes = start.copy(), []
    for _ in range(200):
        a = r.apply(u, np.zeros(3), np.zeros(3), _frame(world, pos), pos, None, MAX_SPEED)
        modes.append(r.mode)
        if r.mode != 'scout':
            break
        pos[:2] += 0.05 * blend(u, a)[:2]
        r.observe(_frame(world, pos), pos)
    assert modes[0] == 'scout' and modes[-1] == 'recall' and len(r.map.pads) == 1
    assert 0.1 < pos[0] - start[0] <= RecallConfig.scout_max_m     # looked ahead until it saw 1.6 m beyond
    assert a[0] < 0                                            # then back to pad 1
    near = pos + np.array([0.3, 0.0, 0.0])                     # within scout_margin_m of the farthest it looked
    r.observe(_frame(world, near), near)
    assert r.apply(u, np.zeros(3), np.zeros(3), _frame(world, near), near, None, MAX_SPEED)[0] < 0
    assert r.mode == 'recall'                                  # one look: no second one from here
    far = pos + np.array([1.0, 0.0, 0.0])                      # the pilot took it 1 m on: the pad now 3.x m off
    r.observe(_frame(world, far), far)
    a = r.apply(u, np.zeros(3), np.zeros(3), _frame(world, far), far, None, MAX_SPEED)
    assert a is not None and a[0] > 0 and r.mode == 'scout'    # still in reach, and a new look from there
    r.reset()
    assert r.map.seen == set() and r.map.pads == []


def test_low_beside_the_pad_it_climbs_over_its_side_first(world):
    r = _mapped(world, [5.0, 0.5, 3.5])
    pos = np.array([6.1, 0.5, 0.9])                            # 0.1 m over the pad top, beside it
    for u in (np.array([0.0, 0.0, -0.5]), np.zeros(3), np.array([0.0, 0.0, 0.5])):
        a = r.apply(u, np.zeros(3), np.array([0.0, 0.0, -0.6]), _frame(world, pos), pos, None, MAX_SPEED)
        assert a is not None and a[0] < 0
        climb = max(u[2], RecallConfig.climb_mps)             # V_z = climb, unless a_z hits max_speed (0.6)
        assert blend(u, a)[2] == pytest.approx((u[2] + min(2 * climb - u[2], MAX_SPEED[2])) / 2)
        assert blend(u, a)[2] > 0.0


def test_low_over_a_pad_seen_whole_a_descent_is_centred_on_it(world):
    r = _mapped(world, [5.0, 0.5, 3.5])                        # pad 0 seen whole from above
    pos = np.array([5.08, 0.54, 1.5])                          # 0.7 m over its top, 0.09 m off its centre
    depth = _frame(world, pos)
    u, actor = np.array([0.0, 0.0, -0.5]), np.array([0.1, 0.8, -0.6])     # the actor pushes it off the side
    a = r.apply(u, np.zeros(3), actor, depth, pos, None, MAX_SPEED)
    assert a is not None and r.mode == 'touchdown'
    pad = r.map.pads[0].xyz
    v = blend(u, a)
    assert v[:2] == pytest.approx(RecallConfig.gain_xy * (pad[:2] - pos[:2]))    # V_xy = gain (centre - p)
    assert v[0] < 0 and v[1] < 0 and a[2] == actor[2]          # toward the centre; the descent is the actor's
    # a pilot tapping a key across the pad is centred too (V_xy does not depend on u_xy)
    assert blend(np.array([0.3, 0.0, -0.5]), r.apply(np.array([0.3, 0.0, -0.5]), np.zeros(3), actor, depth, pos,
                                                    None, MAX_SPEED))[:2] == pytest.approx(v[:2])
    # it stays out: nobody descending, higher than touchdown_height_m over the top, the pilot leaving
    assert r.apply(np.zeros(3), np.zeros(3), np.array([0.1, 0.8, 0.0]), depth, pos, None, MAX_SPEED) is None
    assert r.mode is None
    high = np.array([5.08, 0.54, 1.9])
    assert r.apply(u, np.zeros(3), actor, _frame(world, high), high, None, MAX_SPEED) is None
    assert r.apply(np.array([1.0, 0.0, -0.5]), np.zeros(3), actor, depth, pos, None, MAX_SPEED) is None
    # off, and never for a pad only part seen (its centre is biased toward where the camera looked)
    off = PadRecall(RecallConfig(touchdown_height_m=0.0))
    off.observe(_frame(world, [5.0, 0.5, 3.5]), np.array([5.0, 0.5, 3.5]))
    assert off.apply(u, np.zeros(3), actor, depth, pos, None, MAX_SPEED) is None
    part = PadRecall()
    part.observe(_frame(world, [6.5, 0.5, 3.0]), np.array([6.5, 0.5, 3.0]))
    assert len(part.map.pads) == 1 and not part.map.pads[0].whole
    near_part = part.map.pads[0].xyz + np.array([0.1, 0.0, 0.7])
    assert part.apply(u, np.zeros(3), actor, _frame(world, near_part), near_part, None, MAX_SPEED) is None


def test_heading_rotates_the_steering_into_base_link(world):
    r = _mapped(world, [5.0, 0.5, 3.5])
    pos = np.array([6.6, 0.5, 2.5])
    q = _quat(0.0, 0.0, math.pi / 2)                           # base_link x points along odom +y
    r.observe(_frame(world, pos, q), pos, q)                   # (the ground beyond in view: no pad nearer)
    a = r.apply(np.array([0, 0, -0.5]), np.zeros(3), np.zeros(3), _frame(world, pos, q), pos, q, MAX_SPEED)
    assert a is not None and a[1] == pytest.approx(1.0) and abs(a[0]) < 0.2   # odom -x = base_link +y


def test_the_ground_seen_is_bounded_on_a_long_flight():
    m = PadMap(RecallConfig(max_seen_cells=1000, keep_seen_m=5.0))
    floor = np.full((64, 64), 2.95, np.float32)
    for x in np.arange(0.0, 40.0, 1.0):                      # 40 m of bare floor from 3 m (~190 cells a frame)
        m.update(floor, np.array([x, 0.0, 3.0]))
        assert len(m.seen) <= 1000 + 200
    xs = [i * 0.25 for i, _ in m.seen]
    assert min(xs) >= 39.0 - 5.0 - 0.25 and max(xs) > 40.0   # only what lies within 5 m of the last pose is kept
    assert m.unseen_near(np.array([39.0, 0.0]), 1.0, np.array([30.0, 0.0])) is None   # around it: still seen
    with pytest.raises(ValueError):
        RecallConfig(max_seen_cells=10)


def test_the_ground_seen_is_every_cell_a_depth_pixel_fell_on_on_both_sides_of_the_origin():
    m = PadMap(RecallConfig())
    floor = np.full((48, 64), 2.95, np.float32)
    pose = np.array([-0.3, 0.1, 3.0])                          # the view straddles x = 0 and y = 0
    m.update(floor, pose)
    xy = m.points(floor, pose, None)[..., :2].reshape(-1, 2)
    cells = {(int(i), int(j)) for i, j in np.floor(xy / m.cfg.cell_m).astype(int)}
    assert m.seen == cells and len(cells) > 100
    assert {i < 0 for i, _ in cells} == {True, False} and {j < 0 for _, j in cells} == {True, False}
    assert all(type(i) is int and type(j) is int for i, j in m.seen)


def test_config_rejects_nonsense():
    with pytest.raises(ValueError):
        RecallConfig(radius_m=float('nan'))
    with pytest.raises(ValueError):
        RecallConfig(min_top_m=2.0, max_top_m=1.0)


def test_policy_core_applies_the_recall_and_reports_it(tmp_path, world):
    path = constant_actor(tmp_path / 'still.pt', [0.0, 0.0, 0.0])
    core = PolicyCore(path, PolicyCoreConfig(mode='latent', flight=TELEPORTS))
    q = _quat(0.0, 0.0, 0.0)
    t = 0.0
    for pos in ([5.0, 0.5, 3.5], [6.6, 0.4, 2.5]):          # over the pad (mapped), then past it
        t += 0.05
        core.set_odom(t, pos, [0.0, 0.0, 0.0], q)
        core.set_depth(t, _frame(world, pos))
        core.set_latent(t, np.zeros(LATENT))
        core.set_pilot(t, [0.0, 0.0, -0.5])
        out = core.step(t)
    assert out.key == 'pad_recall' and core.engaged['pad_recall'] == 1
    assert out.agent[0] == pytest.approx(-1.0) and out.velocity[0] < -0.4
    core.reset()                                               # a new landing forgets the map
    assert core.recall.map.pads == []
    off = PolicyCore(path, PolicyCoreConfig(mode='latent', recall=RecallConfig(enabled=False)))
    off.set_odom(t, [6.6, 0.4, 2.5], [0.0, 0.0, 0.0], q)
    off.set_depth(t, _frame(world, [5.0, 0.5, 3.5]))
    off.set_latent(t, np.zeros(LATENT))
    off.set_pilot(t, [0.0, 0.0, -0.5])
    assert off.step(t).key != 'pad_recall'
    with pytest.raises(ValueError):
        core.set_odom(t, [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0])    # not a rotation
    assert core.rejections['odom_orientation'] == 1
    core.set_odom(t, [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0])        # unset: level
    assert core._attitude is None


def test_policy_core_scouts_beyond_before_going_back_and_says_so(tmp_path, world):
    path = constant_actor(tmp_path / 'still.pt', [0.0, 0.0, 0.0])
    core = PolicyCore(path, PolicyCoreConfig(mode='latent', flight=TELEPORTS))
    q = _quat(0.0, 0.0, 0.0)
    for k, pos in enumerate(([5.0, 0.5, 3.5], [7.3, -0.2, 1.9])):   # over pad 0 (mapped), then 2.3 m past it
        t = 0.05 * (k + 1)
        core.set_odom(t, pos, [0.0, 0.0, 0.0], q)
        core.set_depth(t, _frame(world, pos))
        core.set_latent(t, np.zeros(LATENT))
        core.set_pilot(t, [0.0, 0.0, -0.4])
        out = core.step(t)
    assert out.key == 'pad_recall' and 'looking beyond' in out.reason
    assert out.velocity[0] > 0.3 and out.velocity[2] == pytest.approx(0.0)   # on, holding its height
    assert core.assistant.modes['pad_recall:scout'] == core.engaged['pad_recall'] == 1


def test_env_steers_a_descent_past_the_last_pad_back_and_records_it():
    env = LandingAssistEnv(EnvConfig(condition='oracle', recall=RecallConfig()))
    env.reset(seed=3)
    last = env.world.pad_top_centers[int(np.argmax(env.world.pad_top_centers[:, 0]))]
    env.world.reset(seed=env.world.scene.seed, scene=env.world.scene,
                    start_position=[last[0], last[1], 3.5])          # over the last pad: it is mapped
    env._u = np.zeros(3)
    assert not env.step(np.zeros(3))[4]['recall'] and env.assistant.recall.map.pads
    env.world.reset(seed=env.world.scene.seed, scene=env.world.scene,
                    start_position=[last[0] + 1.8, last[1], 3.0])    # past it, no pad below
    seen = []
    for _ in range(20):                                             # the pilot descends, the actor idles
        env._u = np.array([0.0, 0.0, -0.5])
        _, _, term, _, info = env.step(np.zeros(3))
        seen.append(info['recall'])
        assert not term
    assert all(seen) and env.world.state.velocity[0] < -0.3         # carried back toward the pad
    _, a_mean = env.builder.history.means(env.elapsed_s)
    assert a_mean[0] < -0.5                                         # the history holds the applied action
    env.close()


def test_evaluate_recall_rows_and_column(tmp_path):
    actor = constant_actor(tmp_path / 'still.pt', [0.0, 0.0, 0.0], condition='oracle', latent_dim=0)
    args = EvalArgs(out=str(tmp_path / 'ev'), conditions=('oracle', 'scripted_nearest_pad'), betas=(0.5,),
                    landings=1, pilot='paper', safety=True, override=False, recall=True, damper=False,
                    oracle_model=str(actor), plot=False, max_episode_s=5.0)
    assert set(evaluate(args)) == {'oracle+guard+recall', 'scripted_nearest_pad+guard'}   # scripts stay as defined
    rows = {r['condition']: r for r in csv.DictReader(open(tmp_path / 'ev' / 'landings.csv'))}
    assert float(rows['scripted_nearest_pad+guard']['recall_fraction']) == 0.0
    assert 0.0 <= float(rows['oracle+guard+recall']['recall_fraction']) <= 1.0


def test_policy_core_maps_a_late_depth_frame_from_the_pose_it_was_taken_at(tmp_path, world):
    """A frame 100 ms old on arrival at 1.5 m/s: posed at its header stamp the pad is mapped where it is; posed
    with the latest odometry (no stamps) 0.15 m off; stamps of another clock fall back to the latest, counted."""
    path = constant_actor(tmp_path / 'still.pt', [0.0, 0.0, 0.0])
    q = _quat(0.0, 0.0, 0.0)
    shot = np.array([4.6, 0.5, 3.4])            # where the camera was when it took the frame (pad 0 below)
    errors = {}
    for case in ('stamped', 'unstamped', 'other_clock'):
        core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
        t = 100.0
        for k in range(6):                      # odometry at 50 Hz, 1.5 m/s along x, arriving 5 ms after its stamp
            stamp = t + 0.02 * k
            pos = shot + [1.5 * (stamp - t), 0.0, 0.0]
            core.set_odom(stamp + 0.005, pos, [1.5, 0.0, 0.0], q, None if case == 'unstamped' else stamp)
        arrive = t + 0.1                        # the frame arrives 100 ms after it was taken
        stamp = {'stamped': t, 'unstamped': None, 'other_clock': 5.0}[case]
        core.set_depth(arrive, _frame(world, shot), stamp)
        core.set_latent(arrive, np.zeros(LATENT))
        core.set_pilot(arrive, [0.0, 0.0, 0.0])
        core.step(arrive)
        pad = min(core.recall.map.pads, key=lambda m: np.hypot(*(m.xyz[:2] - TOPS[0, :2])))
        errors[case] = float(np.hypot(*(pad.xyz[:2] - TOPS[0, :2])))
        assert core.depth_pose_unmatched == (1 if case == 'other_clock' else 0), case
    assert errors['stamped'] < 0.05
    assert 0.1 < errors['unstamped'] < 0.2 and 0.1 < errors['other_clock'] < 0.2    # 1.5 m/s x ~0.1 s
    with pytest.raises(ValueError, match='depth_pose_match_s'):
        PolicyCoreConfig(depth_pose_match_s=-1.0)
