"""Feature memory: lagged scene features as extra actor inputs, declared in the actor metadata."""
import numpy as np
import pytest
import torch

from assist_lab.env import EnvConfig, LandingAssistEnv, over_pad
from assist_lab.evaluate import make_policy
from assist_policy.observation import (DISPLACEMENT_CLIP_M, DYNAMICS_DIM, ACTIONS_DIM, Condition, FeatureMemory,
                                       ObservationBuilder, oracle_feature, vector_dim)
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_lab.td3 import Actor, load_actor, save_actor, validate_actor_meta
from assist_lab.train import widen_state

LATENT = 4


def lag_actor(path, lags, latent_dim=LATENT, lag_gain=0.0):
    """Latent actor: raw x output tanh(lag_gain * first value of the last lagged latent) (no lags: zeros)."""
    vec = vector_dim('latent', latent_dim, len(lags))
    actor = Actor(vec, 3, hidden=(8,))
    with torch.no_grad():
        for prm in actor.parameters():
            prm.zero_()
        if lags:
            actor.head[0].weight[0, vec - latent_dim] = 1.0     # first value of the last lag copy
            actor.head[0].weight[1, vec - latent_dim] = -1.0
            actor.head[2].weight[0, 0] = lag_gain
            actor.head[2].weight[0, 1] = -lag_gain
    meta = {'vec_dim': vec, 'act_dim': 3, 'hidden': [8], 'image': False, 'condition': 'latent',
            'latent_dim': latent_dim, 'max_speed': [1.0, 1.0, 0.6], 'window_s': 1.0}
    if lags:
        meta['feature_lags_s'] = list(lags)
    save_actor(actor, meta, path)
    return path


def test_memory_returns_the_feature_seen_lag_seconds_ago():
    mem = FeatureMemory((1.0, 2.0))
    out = None
    for k in range(61):                      # 20 Hz for 3 s, feature = its own time
        t = k * 0.05
        out = mem.lagged(t, np.array([t, -t]))
    np.testing.assert_allclose(out, [2.0, -2.0, 1.0, -1.0], atol=1e-9)


def test_memory_before_the_lag_is_the_oldest_feature_and_a_clock_reset_clears_it():
    mem = FeatureMemory((1.0,))
    mem.lagged(5.0, np.array([5.0]))
    assert mem.lagged(5.5, np.array([5.5]))[0] == 5.0        # only 0.5 s of history: the oldest
    assert mem.lagged(0.0, np.array([0.0]))[0] == 0.0        # clock went back (new episode): forgotten
    assert FeatureMemory(()).lagged(1.0, np.array([1.0])).size == 0


@pytest.mark.parametrize('lags', [(0.0,), (-1.0,), (31.0,), tuple(range(1, 10))])
def test_memory_rejects_bad_lags(lags):
    with pytest.raises(ValueError):
        FeatureMemory(lags)


def test_builder_appends_lagged_features_after_the_original_layout():
    plain = ObservationBuilder(Condition.LATENT, latent_dim=LATENT)
    mem = ObservationBuilder(Condition.LATENT, latent_dim=LATENT, feature_lags_s=(1.0,))
    assert mem.dim == plain.dim + LATENT == LATENT * 2 + DYNAMICS_DIM + ACTIONS_DIM
    for k in range(30):
        t = k * 0.05
        f = np.full(LATENT, t)
        a = plain.build(t, f, np.zeros(3), 2.0, np.zeros(3))
        b = mem.build(t, f, np.zeros(3), 2.0, np.zeros(3))
    np.testing.assert_array_equal(b[:plain.dim], a)
    np.testing.assert_allclose(b[plain.dim:], 0.45, atol=1e-6)   # 1.45 s - 1 s
    with pytest.raises(ValueError):
        ObservationBuilder(Condition.END_TO_END, feature_lags_s=(1.0,))


def test_metadata_defaults_to_no_lags_and_checks_them():
    base = {'vec_dim': vector_dim('latent', LATENT), 'hidden': [8], 'condition': 'latent', 'latent_dim': LATENT}
    assert validate_actor_meta(dict(base))['feature_lags_s'] == []
    with pytest.raises(ValueError, match='vec_dim'):
        validate_actor_meta({**base, 'feature_lags_s': [1.0]})                       # size does not fit
    assert validate_actor_meta({**base, 'vec_dim': base['vec_dim'] + LATENT,
                                'feature_lags_s': [1.0]})['feature_lags_s'] == [1.0]
    for bad in ([-1.0], ['x'], 1.0, [1.0] * 9):
        with pytest.raises(ValueError, match='feature_lags_s'):
            validate_actor_meta({**base, 'feature_lags_s': bad})


def test_policy_core_feeds_the_lagged_latent_to_a_memory_actor(tmp_path):
    core = PolicyCore(lag_actor(tmp_path / 'm.pt', [1.0], lag_gain=20.0), PolicyCoreConfig(mode='latent'))
    assert core.builder.dim == core.meta['vec_dim']
    outs = []
    for k in range(41):                      # pad latent +1 for 1 s, then -1 (pad gone from view)
        t = k * 0.05
        core.set_odom(t, [0, 0, 2], [0, 0, 0])
        core.set_pilot(t, [0, 0, 0])
        core.set_latent(t, np.full(LATENT, 1.0 if t < 1.0 else -1.0))
        outs.append(core.step(t))
    # at 1.5 s the current latent is -1 but the one 1 s ago is +1: the actor still pushes +x
    assert outs[30].agent is not None and outs[30].agent[0] > 0.9
    assert outs[40].agent[0] < -0.9          # 2.0 s: the memory has caught up with the -1 latent


def test_old_actor_file_still_loads_and_runs(tmp_path):
    path = lag_actor(tmp_path / 'old.pt', [])
    assert 'feature_lags_s' not in torch.load(path, weights_only=True)['meta']
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    assert core.builder.dim == vector_dim('latent', LATENT)
    core.set_odom(0.0, [0, 0, 2], [0, 0, 0])
    core.set_pilot(0.0, [0.5, 0, 0])
    core.set_latent(0.0, np.zeros(LATENT))
    assert core.step(0.0).key == 'small_action'


def test_widened_actor_acts_like_the_original():
    torch.manual_seed(0)
    old = Actor(vector_dim('latent', LATENT), 3, hidden=(16, 16))
    new = Actor(vector_dim('latent', LATENT, 2), 3, hidden=(16, 16))
    new.load_state_dict(widen_state(old.state_dict(), [], [1.0, 2.0], vector_dim('latent', LATENT, 2), LATENT))
    x = torch.randn(5, vector_dim('latent', LATENT))
    x_new = torch.cat([x, torch.randn(5, 2 * LATENT)], dim=1)
    torch.testing.assert_close(new(x_new), old(x))
    with pytest.raises(ValueError, match='prefix'):
        widen_state(old.state_dict(), [2.0], [1.0, 2.0], vector_dim('latent', LATENT, 2), LATENT)


def test_widening_adds_displacement_inputs_last_and_keeps_old_ones_in_place():
    torch.manual_seed(1)
    lags, more = [1.0], [1.0, 2.0]
    old = Actor(vector_dim('latent', LATENT, 1), 3, hidden=(16,))
    dst = vector_dim('latent', LATENT, 2, displacement=True)
    mid = Actor(dst, 3, hidden=(16,))
    mid.load_state_dict(widen_state(old.state_dict(), lags, more, dst, LATENT, False, True))
    x = torch.randn(5, vector_dim('latent', LATENT, 1))
    torch.testing.assert_close(mid(torch.cat([x, torch.randn(5, LATENT + 6)], dim=1)), old(x))
    # an actor with displacement widened to the same lags keeps its displacement weights at the end
    src = Actor(vector_dim('latent', LATENT, 2, displacement=True), 3, hidden=(16,))
    same = widen_state(src.state_dict(), more, more, dst, LATENT, True, True)
    torch.testing.assert_close(same['head.0.weight'], src.state_dict()['head.0.weight'])
    with pytest.raises(ValueError, match='displacement'):
        widen_state(src.state_dict(), more, more + [3.0], vector_dim('latent', LATENT, 3, True), LATENT, True, True)
    with pytest.raises(ValueError, match='do not widen'):
        widen_state(old.state_dict(), lags, more, dst + 1, LATENT, False, True)


def test_memory_displacement_is_how_far_the_vehicle_moved_since_each_lag():
    mem = FeatureMemory((1.0, 2.0), displacement=True)
    out = None
    for k in range(61):                      # 20 Hz for 3 s at 0.5 m/s along x, 0.2 m/s down
        t = k * 0.05
        out = mem.lagged(t, np.array([t]), np.array([0.5 * t, 1.0, 3.0 - 0.2 * t]))
    np.testing.assert_allclose(out, [2.0, 1.0, 0.5, 0.0, -0.2, 1.0, 0.0, -0.4], atol=1e-9)
    # an odometry jump (e.g. an EKF reset) reaches the actor bounded; z: 3.0 now against 2.59 at 2.05 s
    jumped = mem.lagged(3.05, np.array([0.0]), np.array([100.0, -100.0, 3.0]))
    np.testing.assert_allclose(jumped[2:5], [DISPLACEMENT_CLIP_M, -DISPLACEMENT_CLIP_M, 0.41], atol=1e-9)
    with pytest.raises(ValueError, match='position'):
        mem.lagged(3.1, np.array([0.0]))
    with pytest.raises(ValueError, match='position'):
        mem.lagged(3.05, np.array([0.0]), np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match='needs feature lags'):
        FeatureMemory((), displacement=True)


def test_policy_core_feeds_the_displacement_from_odometry(tmp_path):
    vec = vector_dim('latent', LATENT, 1, displacement=True)
    actor = Actor(vec, 3, hidden=(8,))
    with torch.no_grad():                     # raw x = tanh(10 * displacement x since the lag)
        for prm in actor.parameters():
            prm.zero_()
        actor.head[0].weight[0, vec - 3] = 1.0
        actor.head[0].weight[1, vec - 3] = -1.0
        actor.head[2].weight[0, 0] = 10.0
        actor.head[2].weight[0, 1] = -10.0
    path = tmp_path / 'd.pt'
    save_actor(actor, {'vec_dim': vec, 'hidden': [8], 'condition': 'latent', 'latent_dim': LATENT,
                       'feature_lags_s': [1.0], 'memory_displacement': True}, path)
    core = PolicyCore(path, PolicyCoreConfig(mode='latent'))
    assert core.builder.dim == vec
    out = None
    for k in range(31):                      # flying +x at 0.4 m/s: 0.4 m moved in the last second
        t = k * 0.05
        core.set_odom(t, [0.4 * t, 0, 2], [0.4, 0, 0])
        core.set_pilot(t, [0, 0, 0])
        core.set_latent(t, np.zeros(LATENT))
        out = core.step(t)
    assert out.agent is not None and out.agent[0] == pytest.approx(np.tanh(4.0), abs=1e-3)
    base = {'vec_dim': vec, 'hidden': [8], 'condition': 'latent', 'latent_dim': LATENT, 'feature_lags_s': [1.0]}
    assert validate_actor_meta(dict(base, memory_displacement=True))['memory_displacement'] is True
    with pytest.raises(ValueError, match='vec_dim'):
        validate_actor_meta(base)                                     # without it the size does not fit
    with pytest.raises(ValueError, match='memory_displacement'):
        validate_actor_meta(dict(base, memory_displacement='yes'))
    with pytest.raises(ValueError, match='memory_displacement'):
        validate_actor_meta(dict(base, feature_lags_s=[], memory_displacement=True))


def test_env_and_evaluate_build_the_memory_observation(tmp_path):
    env = LandingAssistEnv(EnvConfig(condition='oracle', feature_lags_s=(0.5,)))
    obs, _ = env.reset(seed=3)
    assert obs.shape == (2 * 3 + DYNAMICS_DIM + ACTIONS_DIM,)
    feats = []
    for _ in range(15):
        feats.append(oracle_feature(env.world.goal_position, env.world.state.position))
        obs, *_ = env.step(np.zeros(3))
    # obs after 15 steps (t = 0.75 s) carries the feature of t = 0.25 s (step 5)
    np.testing.assert_allclose(obs[-3:], feats[5], atol=1e-5)
    env.close()
    path = tmp_path / 'o.pt'
    vec = vector_dim('oracle', 0, 1)
    save_actor(Actor(vec, 3, hidden=(8,)), {'vec_dim': vec, 'hidden': [8], 'condition': 'oracle',
                                            'feature_lags_s': [0.5]}, path)
    env, policy = make_policy('oracle', str(path), '', 5.0, 0.5)
    assert env.observation_space.shape == (vec,) and load_actor(path)[1]['feature_lags_s'] == [0.5]
    obs, _ = env.reset(seed=1)
    assert policy(obs).shape == (3,)
    env.close()


def test_over_pad_uses_the_yawed_footprint():
    from assist_sim.core.scene import PadSpec
    pad = PadSpec(center=(2.0, 1.0), length=1.0, width=0.4, height=0.5, yaw=np.pi / 2, material=0)  # long along y
    assert over_pad([pad], np.array([2.0, 1.45]))
    assert not over_pad([pad], np.array([2.45, 1.0]))
    assert over_pad([pad], np.array([2.3, 1.0]), margin_m=0.15)


def test_env_and_evaluate_build_the_displacement_observation(tmp_path):
    env = LandingAssistEnv(EnvConfig(condition='oracle', feature_lags_s=(0.5,), memory_displacement=True))
    obs, _ = env.reset(seed=3)
    assert obs.shape == (2 * 3 + DYNAMICS_DIM + ACTIONS_DIM + 3,)
    positions = []
    for _ in range(15):
        positions.append(env.world.state.position.copy())
        obs, *_ = env.step(np.array([1.0, 0.0, 0.0]))
    # after 15 steps (t = 0.75 s): the displacement since t = 0.25 s (step 5)
    moved = env.world.state.position - positions[5]
    assert moved[0] > 0.05
    np.testing.assert_allclose(obs[-3:], moved, atol=1e-5)
    env.close()
    path = tmp_path / 'od.pt'
    vec = vector_dim('oracle', 0, 1, displacement=True)
    save_actor(Actor(vec, 3, hidden=(8,)), {'vec_dim': vec, 'hidden': [8], 'condition': 'oracle',
                                            'feature_lags_s': [0.5], 'memory_displacement': True}, path)
    env, policy = make_policy('oracle', str(path), '', 5.0, 0.5)
    assert env.observation_space.shape == (vec,)
    obs, _ = env.reset(seed=1)
    assert policy(obs).shape == (3,)
    env.close()
