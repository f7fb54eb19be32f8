"""Floor guard (assist_policy.safety) on depth images rendered in the LandingWorld, and inside PolicyCore."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from assist_policy.blending import blend
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_policy.safety import FloorGuard, SafetyConfig
from assist_sim.core.scene import PadSpec, SceneSpec

_spec = importlib.util.spec_from_file_location('policy_core_helpers', Path(__file__).with_name('test_policy_core.py'))
_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_helpers)
constant_actor, LATENT = _helpers.constant_actor, _helpers.LATENT

PAD = PadSpec(center=(5.0, 0.0), length=1.0, width=1.0, height=0.6, yaw=0.0, material=3)
SCENE = SceneSpec(seed=0, pads=(PAD,), floor_material=1, wall_material=2, start_position=(0.0, 0.0, 3.0))
THR = 0.25


def test_floor_seen_under_every_leg_only_over_the_floor(depth_at):
    g = FloorGuard()
    assert g.floor_below(depth_at(0.0, 0.0, 0.8), 0.8) is True            # nothing but floor in view
    assert g.floor_below(depth_at(5.0, 0.0, 1.1), 1.1) is False           # over the pad
    assert g.floor_below(depth_at(5.55, 0.0, 1.0), 1.0) is False          # two legs over the pad edge
    d = depth_at(5.8, 0.0, 0.9)                                            # pad in view, no leg over it
    assert (d < 0.9 - 0.05 - 0.3).any()
    assert g.floor_below(d, 0.9) is True


def test_surface_below_gives_the_height_over_the_pad_or_floor_under_the_legs(depth_at):
    g = FloorGuard()
    floor, h = g.surface_below(depth_at(0.0, 0.0, 2.5), [0.0, 0.0, 2.5])
    assert floor is True and h == pytest.approx(2.5, abs=0.03)           # over the floor: the altitude
    floor, h = g.surface_below(depth_at(5.0, 0.0, 2.5), [5.0, 0.0, 2.5])
    assert floor is False and h == pytest.approx(2.5 - 0.6, abs=0.03)    # over the 0.6 m pad: 1.9 m over its top
    assert g.surface_below(np.full((64, 64), np.nan, np.float32), [0.0, 0.0, 2.5]) == (None, None)
    # settling on the pad, the camera inside its blind range sees the floor behind the pad top: the
    # guard's remembered pad counts (it saw it beneath the legs on the way down)
    g.apply(np.zeros(3), None, np.zeros(3), depth_at(5.0, 0.0, 1.1), [5.0, 0.0, 1.1], THR)
    blind = np.full((64, 64), 0.72 - 0.05, np.float32)                   # what the clipped render shows
    assert g.surface_below(blind, [5.0, 0.05, 0.72]) == (False, pytest.approx(0.12))
    assert g.surface_below(blind, [6.0, 0.05, 0.72])[0] is True          # beside it: the floor is real


def test_invalid_depth_is_unknown_and_never_blocks(depth_at):
    g = FloorGuard()
    holes = np.full((64, 64), np.nan, dtype=np.float32)
    assert g.floor_below(holes, 0.8) is None
    assert g.floor_below(np.zeros((64, 64), np.float32), 0.8) is None
    r = g.apply(np.array([0, 0, -0.5]), None, np.array([0, 0, -0.5]), holes, [0.0, 0.0, 0.8], THR)
    assert not r.engaged and r.velocity[2] == -0.5
    with pytest.raises(ValueError):
        g.floor_below(np.zeros((4, 4, 3)), 0.8)


def test_descent_over_floor_becomes_a_climb_visible_in_the_agent_action(depth_at):
    g = FloorGuard()
    u = np.array([0.6, 0.0, -0.5])
    r = g.apply(u, None, u.copy(), depth_at(0.0, 0.0, 0.8), [0.0, 0.0, 0.8], THR)     # actor relinquished: V = u
    assert r.engaged and r.floor is True
    assert r.velocity[2] == pytest.approx(0.15)
    np.testing.assert_allclose(r.agent, [0.0, 0.0, 0.8])                  # only the vertical part
    np.testing.assert_allclose(blend(u, r.agent, THR), r.velocity)        # a' blends to V'
    a = np.array([-0.8, 0.3, -0.6])                                       # an actor pushing down too
    r = g.apply(u, a, blend(u, a, THR), depth_at(0.0, 0.0, 0.8), [0.0, 0.0, 0.8], THR)
    np.testing.assert_allclose(r.agent[:2], a[:2])
    np.testing.assert_allclose(r.velocity, [(0.6 - 0.8) / 2, 0.15, 0.15])


def test_passes_through_over_a_pad_above_the_guard_height_climbing_or_disabled(depth_at):
    u = np.array([0.0, 0.0, -0.5])
    g = FloorGuard(SafetyConfig(edge_height_m=0.0))                    # the floor rule alone
    assert not g.apply(u, None, u, depth_at(5.0, 0.0, 1.1), [5.0, 0.0, 1.1], THR).engaged          # pad below
    assert not g.apply(u, None, u, depth_at(5.55, 0.0, 1.0), [5.55, 0.0, 1.0], THR).engaged  # edge: pad under 2 legs
    assert not g.apply(u, None, u, depth_at(0.0, 0.0, 1.3), [0.0, 0.0, 1.3], THR).engaged          # above 1 m
    up = np.array([0.0, 0.0, 0.5])
    assert not g.apply(up, None, up, depth_at(0.0, 0.0, 0.8), [0.0, 0.0, 0.8], THR).engaged        # not descending
    off = FloorGuard(SafetyConfig(enabled=False))
    r = off.apply(u, None, u, depth_at(0.0, 0.0, 0.8), [0.0, 0.0, 0.8], THR)
    assert not r.engaged and r.velocity[2] == -0.5


def test_never_descends_while_engaged_whatever_u_and_a(depth_at):
    rng = np.random.default_rng(0)
    d = depth_at(0.0, 0.0, 0.8)
    for thr in (0.1, 0.25, 0.6):
        g = FloorGuard(SafetyConfig(min_climb_mps=0.0))
        for _ in range(300):
            u = rng.uniform(-1, 1, 3)
            a = rng.uniform(-1, 1, 3) if rng.random() < 0.7 else None
            v = blend(u, np.zeros(3) if a is None else a, thr)
            r = g.apply(u, a, v, d, [0.0, 0.0, 0.8], thr)
            if v[2] < 0:
                assert r.engaged and r.velocity[2] > 0
                np.testing.assert_allclose(blend(u, r.agent, thr), r.velocity)
            else:
                assert not r.engaged


def test_millimetre_depth_gives_the_same_verdict(depth_at):
    d = depth_at(0.0, 0.0, 0.8)
    mm = np.round(d * 1000).astype(np.uint16).astype(np.float32) / 1000.0
    assert FloorGuard().floor_below(mm, 0.8) is True


def test_policy_core_applies_the_guard_with_fresh_depth_only(tmp_path, depth_at):
    path = constant_actor(tmp_path / 'down.pt', [0.0, 0.0, -0.9])        # actor pushes down
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    floor = depth_at(0.0, 0.0, 0.8)

    def feed(t, z, depth=floor, x=0.0):
        core.set_odom(t, [x, 0, z], [0, 0, 0])
        core.set_pilot(t, [0.0, 0.0, -0.5])
        core.set_latent(t, np.zeros(LATENT))
        if depth is not None:
            core.set_depth(t, depth)

    feed(1.0, 0.8)
    out = core.step(1.0)
    assert out.reason.startswith('floor guard') and core.engaged['floor_guard'] == 1
    assert out.velocity[2] > 0 and out.agent[2] > 0
    feed(2.0, 0.8, depth=None)                       # depth now 1 s old: the guard cannot see
    out = core.step(2.0)
    assert out.reason == 'assisting' and out.velocity[2] < 0
    feed(3.0, 1.1, depth=depth_at(5.0, 0.0, 1.1), x=5.0)    # over the pad: descent passes
    assert core.step(3.0).velocity[2] < 0
    core.guard.cfg.enabled = False                   # the parameter turns it off
    feed(4.0, 0.8)
    assert core.step(4.0).velocity[2] < 0
    core.guard.cfg.enabled = True
    core.set_odom(5.0, [0, 0, 0.8], [0, 0, 0])       # latent stale: relinquished, the guard still acts
    core.set_pilot(5.0, [0.0, 0.0, -0.5])
    core.set_depth(5.0, floor)
    out = core.step(5.0)
    assert out.reason.startswith('floor guard') and out.velocity[2] > 0
    core.reset()
    with pytest.raises(ValueError):
        core.set_depth(6.0, np.zeros((2, 2, 2)))


def test_touchdown_on_a_pad_inside_the_blind_range_is_not_pushed_back_up(depth_at):
    """Sim renderer clips a pad nearer than its near plane and shows the floor: the remembered pad wins."""
    g = FloorGuard()
    u = np.array([0.0, 0.0, -0.5])
    touching = [5.0, 0.0, PAD.height + 0.12]                  # legs on the pad, camera 7 cm above it
    blind = depth_at(*touching)
    assert g.floor_below(blind, touching[2]) is True          # the frame alone looks like floor
    assert not g.apply(u, None, u, depth_at(5.0, 0.0, 1.2), [5.0, 0.0, 1.2], THR).engaged   # sees the pad
    assert not g.apply(u, None, u, blind, touching, THR).engaged
    g.reset()                                                 # new episode: nothing remembered
    assert g.apply(u, None, u, blind, touching, THR).engaged
    g.reset()
    g.apply(u, None, u, depth_at(5.0, 0.0, 1.2), [5.0, 0.0, 1.2], THR)
    assert g.apply(u, None, u, depth_at(0.0, 0.0, 0.8), [0.0, 0.0, 0.8], THR).engaged       # far from it: floor


def test_edge_rule_holds_a_descent_straddling_a_pad_edge_only(depth_at):
    on, off = SafetyConfig(edge_height_m=0.5), SafetyConfig(edge_height_m=0.0)
    u = np.array([0.0, 0.0, -0.4])
    d = depth_at(5.55, 0.0, 1.0)                       # legs at x 5.4 (pad, top 0.6 m) and 5.7 (floor)
    assert FloorGuard(on).straddle_depth(d, 1.0) == pytest.approx(0.35, abs=0.02)
    r = FloorGuard(on).apply(u, None, blend(u, np.zeros(3), THR), d, [5.55, 0.0, 1.0], THR)
    assert r.engaged and r.velocity[2] > 0 and np.linalg.norm(r.agent) > THR
    assert not FloorGuard(off).apply(u, None, u.copy(), d, [5.55, 0.0, 1.0], THR).engaged
    # higher above the same edge (camera 0.55 m from the pad top) and over the pad centre: passed through
    assert not FloorGuard(on).apply(u, None, u.copy(), depth_at(5.55, 0.0, 1.2), [5.55, 0.0, 1.2], THR).engaged
    assert FloorGuard(on).straddle_depth(depth_at(5.0, 0.0, 1.0), 1.0) is None
    assert not FloorGuard(on).apply(u, None, u.copy(), depth_at(5.0, 0.0, 1.0), [5.0, 0.0, 1.0], THR).engaged
    assert FloorGuard(on).watch_height_m == 2.0 and FloorGuard(off).watch_height_m == pytest.approx(1.3)


def test_edge_rule_is_on_by_default_and_tunable_in_policy_core(tmp_path, depth_at):
    assert SafetyConfig().edge_height_m == pytest.approx(0.6)
    u = np.array([0.0, 0.0, -0.4])
    d = depth_at(5.55, 0.0, 1.0)                       # straddling the edge, camera 0.35 m from the pad top
    assert FloorGuard().apply(u, None, u.copy(), d, [5.55, 0.0, 1.0], THR).engaged
    path = constant_actor(tmp_path / 'down.pt', [0.0, 0.0, -0.9])
    for edge, held in ((0.6, True), (0.0, False)):
        core = PolicyCore(path, PolicyCoreConfig(mode='latent', safety=SafetyConfig(edge_height_m=edge)))
        core.set_odom(0.0, [5.55, 0.0, 1.0], [0.0, 0.0, 0.0])
        core.set_depth(0.0, d)
        core.set_latent(0.0, np.zeros(LATENT))
        core.set_pilot(0.0, u)
        out = core.step(0.0)
        assert (out.key == 'floor_guard') is held and bool(out.velocity[2] > 0) is held
