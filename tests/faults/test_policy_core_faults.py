"""Fault injection, policy core: arbitrary finite / non-finite / huge values, wrong lengths, wrong frames
and stamps thrown at PolicyCore's inputs and step, the observation builder, blending and action scaling.

Contract (ARCHITECTURE.md, "Timing and safety rules"): every input is accepted or refused with
InputRejected (counted per reason, the last good value kept); step() never raises; V is always
finite and within the speed limits; the agent action is absent or finite and within max_speed;
a failed step relinquishes (V = u).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from assist_policy.actions import scale_action, unscale_action
from assist_policy.blending import blend
from assist_policy.observation import ActionHistory, ObservationBuilder, build_vector, vector_dim
from assist_policy.policy_core import InputRejected, PolicyCore, PolicyCoreConfig
from assist_lab.td3 import Actor, save_actor

LATENT = 10
SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                              HealthCheck.too_slow])

# values that break naive code: non-finite, overflowing float32 (1e39 is inf as float32), denormals
NASTY = st.sampled_from([math.nan, math.inf, -math.inf, 1e39, -1e39, 3.5e38, 1e308, -1e308, 5e-324, -0.0])
ANY_FLOAT = st.one_of(st.floats(allow_nan=True, allow_infinity=True), NASTY)
SANE = st.floats(-3.0, 3.0)


def vectors(n: int) -> st.SearchStrategy:
    """Mostly well-formed n-vectors (so steps get to run the actor), some with nasty values or lengths."""
    return st.one_of(st.lists(SANE, min_size=n, max_size=n),
                     st.lists(st.one_of(SANE, ANY_FLOAT), min_size=n, max_size=n),
                     st.lists(ANY_FLOAT, min_size=0, max_size=n + 3))


STAMPS = st.one_of(st.floats(0.0, 3.0), ANY_FLOAT)
FRAMES = st.sampled_from(['', 'base_link', 'base_link', 'map', 'odom', 'BASE_LINK', 'base_link ', '\x00'])
OPS = st.one_of(
    st.tuples(st.just('pilot'), STAMPS, vectors(3), FRAMES),
    st.tuples(st.just('odom'), STAMPS, vectors(3), vectors(3)),
    st.tuples(st.just('latent'), STAMPS, vectors(LATENT)),
    st.tuples(st.just('step'), STAMPS),
    st.tuples(st.just('step'), st.floats(0.0, 3.0)),
)


def random_actor(path, condition='latent', latent_dim=LATENT, seed=0, scale=1.0):
    """A real (random, untrained) actor file: its output depends on every input."""
    torch.manual_seed(seed)
    vec = vector_dim(condition, latent_dim)
    actor = Actor(vec, 3, hidden=(32, 32))
    with torch.no_grad():
        for prm in actor.parameters():
            prm.mul_(scale)
    save_actor(actor, {'vec_dim': vec, 'act_dim': 3, 'hidden': [32, 32], 'image': False, 'condition': condition,
                       'latent_dim': latent_dim, 'max_speed': [1.0, 1.0, 0.6], 'window_s': 1.0}, path)
    return path


@pytest.fixture(scope='module')
def actor_file(tmp_path_factory):
    return random_actor(tmp_path_factory.mktemp('actor') / 'latent.pt', scale=4.0)


def check_output(core: PolicyCore, out) -> None:
    """The step contract: finite V within the limits, agent absent or finite within max_speed."""
    v = out.velocity
    assert v.shape == (3,) and np.all(np.isfinite(v)), out
    assert math.hypot(v[0], v[1]) <= core.cfg.max_speed_mps + 1e-9, out
    assert abs(v[2]) <= core.cfg.max_vertical_mps + 1e-9, out
    if out.agent is not None:
        assert np.all(np.isfinite(out.agent)) and np.all(np.abs(out.agent) <= np.array(core.max_speed) + 1e-9)
    assert out.key in ('assisting', 'small_action', 'odom_stale', 'feature_stale', 'goal_absent',
                       'actor_nonfinite', 'step_error')


@SETTINGS
@given(ops=st.lists(OPS, min_size=1, max_size=25))
def test_core_survives_any_input_sequence(actor_file, ops):
    core = PolicyCore(actor_file, PolicyCoreConfig(mode='latent'))
    bad_clock = 0
    for op in ops:
        kind = op[0]
        if kind == 'step':
            out = core.step(op[1])
            check_output(core, out)
            if not math.isfinite(op[1]):      # a broken clock is a failed step: relinquish, u = 0
                bad_clock += 1
                assert out.key == 'step_error' and np.all(out.velocity == 0)
            continue
        before = (core._pilot, core._odom, core._feature, sum(core.rejections.values()))
        try:
            if kind == 'pilot':
                core.set_pilot(op[1], op[2], op[3])
            elif kind == 'odom':
                core.set_odom(op[1], op[2], op[3])
            else:
                core.set_latent(op[1], op[2])
        except InputRejected as exc:
            # refused: counted once under its reason, and the last good value is kept
            assert sum(core.rejections.values()) == before[3] + 1 and core.rejections[exc.reason] >= 1
            assert (core._pilot, core._odom, core._feature) == before[:3]
        else:
            assert sum(core.rejections.values()) == before[3]
    check_output(core, core.step(1.0))
    assert sum(core.faults.values()) == bad_clock, core.faults    # nothing that got in made a step throw


@SETTINGS
@given(goal=vectors(3), pos=vectors(3), vel=vectors(3), t=STAMPS)
def test_oracle_core_goal_and_odom(tmp_path_factory, goal, pos, vel, t):
    path = tmp_path_factory.getbasetemp() / 'oracle.pt'
    if not path.exists():
        random_actor(path, condition='oracle', latent_dim=0, scale=4.0)
    core = PolicyCore(path, PolicyCoreConfig(mode='oracle'))
    core.set_pilot(1.0, [0.5, 0.0, -0.2])
    for fn in (lambda: core.set_goal(goal), lambda: core.set_odom(t, pos, vel)):
        try:
            fn()
        except InputRejected:
            pass
    check_output(core, core.step(1.0))
    assert not core.faults


# ------------------------------------------------------------------ regressions: hostile and broken inputs
def test_odometry_overflowing_float32_is_rejected_and_step_keeps_flying_the_pilot(actor_file):
    """An /odom twist of 1e39 (finite double, inf as float32) used to make step() raise."""
    core = PolicyCore(actor_file, PolicyCoreConfig(mode='latent'))
    core.set_pilot(1.0, [0.0, 1.0, 0.0])
    core.set_latent(1.0, np.zeros(LATENT))
    core.set_odom(1.0, [0, 0, 2], [0, 0, 0])
    with pytest.raises(InputRejected) as info:
        core.set_odom(1.0, [0, 0, 2], [1e39, 0, 0])
    assert info.value.reason == 'odom_velocity_range' and core.rejections['odom_velocity_range'] == 1
    out = core.step(1.0)
    check_output(core, out)
    assert out.key in ('assisting', 'small_action')     # the last good odometry is still used


def test_any_exception_inside_step_relinquishes_to_the_pilot(actor_file):
    core = PolicyCore(actor_file, PolicyCoreConfig(mode='latent', max_speed_mps=1.5))
    core.set_pilot(1.0, [3.0, 0.0, 0.5])
    core.set_latent(1.0, np.zeros(LATENT))
    core.set_odom(1.0, [0, 0, 2], [0, 0, 0])

    def broken(obs):
        raise RuntimeError('simulated actor failure')
    core.actor.net.forward = broken         # the network itself raises (PolicyCore runs torch by default)
    out = core.step(1.0)
    assert out.agent is None and out.key == 'step_error' and out.fault == 'RuntimeError'
    np.testing.assert_allclose(out.velocity, [1.5, 0.0, 0.5])      # V = u, clamped
    assert core.faults['RuntimeError'] == 1
    out = core.step(float('nan'))       # even a NaN clock: relinquish, u = 0 (pilot cannot be fresh)
    assert out.key == 'step_error' and np.all(out.velocity == 0)


# ------------------------------------------------------------------ item 2: core-level config
@pytest.mark.parametrize('field,value', [('max_speed_mps', -1.0), ('max_speed_mps', 0.0), ('max_speed_mps', math.nan),
                                         ('max_vertical_mps', -1.0), ('max_vertical_mps', math.inf),
                                         ('blend_threshold', -0.1), ('blend_threshold', math.nan),
                                         ('pilot_timeout_s', 0.0), ('odom_timeout_s', -1.0),
                                         ('feature_timeout_s', math.nan), ('max_input_mps', 0.0)])
def test_config_refuses_limits_that_reverse_or_invent_motion(field, value):
    with pytest.raises(ValueError, match=field):
        PolicyCoreConfig(**{field: value})


def test_negative_vertical_limit_cannot_make_the_vehicle_descend(actor_file):
    """max_vertical_speed -1 with no input at all used to publish a continuous 1 m/s descent."""
    core = PolicyCore(actor_file, PolicyCoreConfig(mode='latent'))
    with pytest.raises(ValueError):
        core.configure(max_vertical_mps=-1.0)
    with pytest.raises(ValueError):
        core.configure(max_speed_mps=-1.0)
    assert core.cfg.max_vertical_mps == 1.0 and core.cfg.max_speed_mps == 1.5    # unchanged
    np.testing.assert_allclose(core.step(1.0).velocity, np.zeros(3))
    core.configure(max_speed_mps=0.5)
    core.set_pilot(1.0, [0.0, 2.0, 0.0])
    np.testing.assert_allclose(core.step(1.0).velocity, [0.0, 0.5, 0.0])   # same direction, slower


# ------------------------------------------------------------------ item 11: frame and speed norm
@pytest.mark.parametrize('frame', ['map', 'odom', 'camera_optical_frame', 'base_link '])
def test_pilot_command_in_another_frame_is_rejected(actor_file, frame):
    core = PolicyCore(actor_file, PolicyCoreConfig(mode='latent'))
    core.set_pilot(1.0, [0.0, 1.0, 0.0], 'base_link')
    with pytest.raises(InputRejected) as info:
        core.set_pilot(1.0, [1.0, 0.0, 0.0], frame)
    assert info.value.reason == 'pilot_frame' and core.rejections['pilot_frame'] == 1
    np.testing.assert_allclose(core.pilot_command(1.0), [0.0, 1.0, 0.0])
    core.set_pilot(1.0, [0.2, 0.0, 0.0], '')          # no frame: taken as the body frame


def test_max_input_speed_applies_to_the_speed_not_each_axis(actor_file):
    core = PolicyCore(actor_file, PolicyCoreConfig(mode='latent', max_input_mps=5.0))
    core.set_pilot(1.0, [2.8, 2.8, 2.8])        # 4.85 m/s: accepted
    core.rejections.clear()
    with pytest.raises(InputRejected) as info:
        core.set_pilot(1.0, [4.0, 4.0, 0.0])    # 5.66 m/s
    assert info.value.reason == 'pilot_range'
    core.set_pilot(1.0, [3.0, 4.0, 0.0])        # exactly 5 m/s: accepted


# ------------------------------------------------------------------ observation builder
@SETTINGS
@given(feature=st.lists(ANY_FLOAT, max_size=12), vel=st.lists(ANY_FLOAT, min_size=3, max_size=3),
       alt=ANY_FLOAT, u=st.lists(ANY_FLOAT, min_size=3, max_size=3), now=STAMPS)
def test_observation_builder_returns_finite_float32_or_raises_value_error(feature, vel, alt, u, now):
    b = ObservationBuilder('latent', LATENT)
    try:
        obs = b.build(now, feature, vel, alt, u)
    except ValueError:
        return
    assert obs.dtype == np.float32 and obs.shape == (b.dim,) and np.all(np.isfinite(obs))


@SETTINGS
@given(items=st.lists(st.tuples(STAMPS, st.lists(st.one_of(st.floats(-1e6, 1e6), NASTY.filter(
    lambda x: not math.isfinite(x) or abs(x) < 1e6)), min_size=3, max_size=3)), max_size=30))
def test_action_history_stays_bounded_and_finite(items):
    """Speeds the core lets in are bounded (pilot <= max_input_mps, agent <= max_speed); non-finite
    values and stamps are refused."""
    h = ActionHistory(1.0)
    for t, u in items:
        try:
            h.push(t, u, np.zeros(3))
        except ValueError:
            continue
        mu, ma = h.means(t)
        assert np.all(np.isfinite(mu)) and np.all(np.isfinite(ma))
        assert all(math.isfinite(it[0]) for it in h._items)            # no unprunable NaN stamps
        assert all(t - 1.0 < it[0] <= t for it in h._items) or h._items[-1][0] == t


def test_nan_stamp_is_refused_by_the_history():
    """A NaN stamp used to be stored and never pruned (the window grew without bound)."""
    h = ActionHistory(1.0)
    with pytest.raises(ValueError):
        h.push(math.nan, np.zeros(3), np.zeros(3))
    assert len(h) == 0


@SETTINGS
@given(parts=st.tuples(*(st.lists(ANY_FLOAT, min_size=n, max_size=n) for n in (LATENT, 3, 1, 3, 3, 3))))
def test_build_vector_overflow_is_caught(parts):
    f, v, (alt,), u, mu, ma = parts
    try:
        obs = build_vector(f, v, alt, u, mu, ma)
    except ValueError:
        return
    assert np.all(np.isfinite(obs))


# ------------------------------------------------------------------ blending and action scaling
@SETTINGS
@given(u=st.lists(st.floats(-1e300, 1e300), min_size=3, max_size=3), a=st.lists(ANY_FLOAT, min_size=3, max_size=3),
       thr=st.floats(0.0, 10.0))
def test_blend_is_u_or_the_mean_and_always_finite(u, a, thr):
    v = blend(u, a, thr)
    assert np.all(np.isfinite(v))
    u, a = np.array(u), np.array(a)
    if np.all(np.isfinite(a)) and np.linalg.norm(a) > thr:
        np.testing.assert_allclose(v, (u / 2 + a / 2))
    else:
        np.testing.assert_array_equal(v, u)


@SETTINGS
@given(u=st.lists(ANY_FLOAT, min_size=3, max_size=3), thr=ANY_FLOAT)
def test_blend_refuses_invented_pilot_commands_and_bad_thresholds(u, thr):
    bad = not all(math.isfinite(x) for x in u) or not (math.isfinite(thr) and thr >= 0)
    try:
        v = blend(u, np.zeros(3), thr)
    except ValueError:
        assert bad
        return
    assert not bad and np.array_equal(v, np.array(u, dtype=float))


@SETTINGS
@given(raw=st.lists(ANY_FLOAT, min_size=3, max_size=3),
       ms=st.lists(st.one_of(st.floats(0.01, 20.0), ANY_FLOAT), min_size=3, max_size=3))
def test_scale_action_is_bounded_and_never_reverses(raw, ms):
    valid = all(math.isfinite(x) and x > 0 for x in ms)
    if not valid:
        with pytest.raises(ValueError):
            scale_action(raw, ms)
        with pytest.raises(ValueError):
            unscale_action(raw, ms)
        return
    a = scale_action(raw, ms)
    for r, x, m in zip(raw, a, ms):
        if math.isnan(r):
            assert math.isnan(x)        # stays non-finite: blend() then treats the action as absent
            continue
        assert abs(x) <= m + 1e-12 and (x == 0 or math.copysign(1, x) == math.copysign(1, r))
    back = unscale_action(np.nan_to_num(a), ms)
    assert np.all(np.abs(back) <= 1.0)


def test_nan_max_speed_reaching_the_core_relinquishes_instead_of_crashing(actor_file):
    """Refused at load (test_policy_model_files); should one get in anyway, the tick must not crash."""
    core = PolicyCore(actor_file, PolicyCoreConfig(mode='latent'))
    core.max_speed = (math.nan, 1.0, 0.6)
    core.set_pilot(1.0, [0.0, 1.0, 0.0])
    core.set_latent(1.0, np.zeros(LATENT))
    core.set_odom(1.0, [0, 0, 2], [0, 0, 0])
    out = core.step(1.0)
    assert out.key == 'step_error' and out.agent is None
    np.testing.assert_allclose(out.velocity, [0.0, 1.0, 0.0])


@pytest.fixture(scope='module')
def e2e_file(tmp_path_factory):
    from assist_lab.td3 import TD3, TD3Config
    agent = TD3(vector_dim('end_to_end'), 3, TD3Config(hidden=(8,), image_channels=(4, 4, 4, 4)), image=True)
    path = tmp_path_factory.mktemp('e2e') / 'e2e.pt'
    save_actor(agent.actor, {**agent.meta, 'condition': 'end_to_end', 'latent_dim': 0,
                             'max_speed': [1.0, 1.0, 0.6]}, path)
    return path


IMAGE_DTYPES = st.sampled_from([np.uint8, np.uint16, np.float32, np.float64, np.int8, np.bool_])


@SETTINGS
@given(rgb_shape=st.sampled_from([(64, 64, 3), (32, 32, 3), (64, 64), (64, 64, 4), (0, 64, 3), (1, 1, 3)]),
       depth_shape=st.sampled_from([(64, 64), (32, 32), (64, 64, 1), (0, 64)]), rgb_dtype=IMAGE_DTYPES,
       depth_dtype=IMAGE_DTYPES, fill=ANY_FLOAT, t=STAMPS)
def test_end_to_end_images_are_used_or_rejected(e2e_file, rgb_shape, depth_shape, rgb_dtype, depth_dtype, fill, t):
    core = PolicyCore(e2e_file, PolicyCoreConfig(mode='end_to_end'))
    core.set_pilot(1.0, [0.0, 1.0, 0.0])
    core.set_odom(1.0, [0, 0, 2], [0, 0, 0])
    with np.errstate(all='ignore'):
        rgb = np.full(rgb_shape, fill).astype(rgb_dtype) if math.isfinite(fill) or rgb_dtype in (
            np.float32, np.float64) else np.zeros(rgb_shape, rgb_dtype)
        depth = np.full(depth_shape, fill).astype(depth_dtype) if math.isfinite(fill) or depth_dtype in (
            np.float32, np.float64) else np.zeros(depth_shape, depth_dtype)
    try:
        core.set_image(t, rgb, depth)
    except InputRejected as exc:
        assert exc.reason.startswith('image_') and sum(core.rejections.values()) == 1
    out = core.step(1.0)
    check_output(core, out)
    assert not core.faults, core.faults
