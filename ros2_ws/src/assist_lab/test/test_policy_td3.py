"""TD3 pieces: learning on an easy task, replay buffer persistence, actor files, OU decay."""
import numpy as np
import pytest
import torch

from assist_lab.td3 import TD3, OUNoise, ReplayBuffer, TD3Config, load_actor, save_actor


def test_td3_learns_easy_contextual_task():
    """One-step task: reward -|a - target(obs)|^2. TD3 must learn a = target."""
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    agent = TD3(4, 3, TD3Config(hidden=(64, 64), batch_size=64), seed=0)
    buf = ReplayBuffer(4, 3, 10_000)
    w = np.array([[0.8, 0.0, 0.0, 0.1], [0.0, -0.6, 0.0, 0.0], [0.0, 0.0, 0.5, -0.3]])

    def target(o):
        return np.clip(w @ o, -1, 1)

    def err():
        obs = rng.uniform(-1, 1, (200, 4))
        return float(np.mean([np.linalg.norm(agent.act(o) - target(o)) for o in obs]))

    before = err()
    for step in range(2500):
        o = rng.uniform(-1, 1, 4)
        a = np.clip(agent.act(o) + rng.normal(0, 0.3, 3), -1, 1) if step > 500 else rng.uniform(-1, 1, 3)
        buf.add(o, a, -float(np.sum((a - target(o)) ** 2)), o, True)
        if buf.size >= 64:
            agent.update(buf)
    after = err()
    assert before > 0.4
    assert after < 0.15, (before, after)


def test_replay_buffer_save_load_preserves_order_after_wrap(tmp_path):
    buf = ReplayBuffer(2, 3, capacity=5)
    for k in range(8):
        buf.add([k, k], [k, 0, 0], float(k), [k + 1, k + 1], k == 7)
    buf.save(tmp_path / 'r.npz')
    other = ReplayBuffer(2, 3, capacity=100)
    assert other.load(tmp_path / 'r.npz') == 5
    np.testing.assert_array_equal(other.rew[:5, 0], [3, 4, 5, 6, 7])
    assert other.done[4, 0] == 1.0
    with pytest.raises(ValueError):
        ReplayBuffer(3, 3).load(tmp_path / 'r.npz')


def test_replay_buffer_load_appends_and_wraps(tmp_path):
    src = ReplayBuffer(2, 3, capacity=10)
    for k in range(6):
        src.add([k, -k], [k, 1, 2], float(k), [k + 1, 0], k == 5)
    src.save(tmp_path / 'six.npz')
    dst = ReplayBuffer(2, 3, capacity=8)
    for k in range(4):
        dst.add([100 + k, 0], [0, 0, 0], 100.0 + k, [0, 0], False)
    assert dst.load(tmp_path / 'six.npz') == 6          # 4 + 6 > 8: the ring wraps
    assert dst.size == 8 and dst.ptr == 2
    # the ring now holds, in slot order: loaded 4, 5, then old 102, 103, then loaded 0..3
    np.testing.assert_array_equal(dst.rew[:, 0], [4, 5, 102, 103, 0, 1, 2, 3])
    np.testing.assert_array_equal(dst.obs[1], [5, -5])
    np.testing.assert_array_equal(dst.act[0], [4, 1, 2])
    assert dst.done[1, 0] == 1.0 and dst.done[0, 0] == 0.0
    small = ReplayBuffer(2, 3, capacity=3)
    assert small.load(tmp_path / 'six.npz') == 6          # only the newest 3 fit
    np.testing.assert_array_equal(small.rew[:, 0], [3, 4, 5])
    assert small.size == 3 and small.ptr == 0


def test_actor_file_roundtrip_and_corrupt_file(tmp_path):
    agent = TD3(7, 3, TD3Config(hidden=(16,)), seed=1)
    save_actor(agent.actor, agent.meta, tmp_path / 'a.pt')
    actor, meta = load_actor(tmp_path / 'a.pt')
    x = torch.randn(5, 7)
    torch.testing.assert_close(actor(x), agent.actor(x))
    assert meta['vec_dim'] == 7
    (tmp_path / 'bad.pt').write_bytes(b'not a torch file')
    with pytest.raises(ValueError, match='bad.pt'):
        load_actor(tmp_path / 'bad.pt')
    with pytest.raises(ValueError, match='not found'):
        load_actor(tmp_path / 'missing.pt')


def test_checkpoint_state_dict_roundtrip():
    a = TD3(5, 3, TD3Config(hidden=(8,)), seed=2)
    b = TD3(5, 3, TD3Config(hidden=(8,)), seed=3)
    b.load_state_dict(a.state_dict())
    o = np.ones(5, np.float32)
    np.testing.assert_allclose(a.act(o), b.act(o))


def test_ou_noise_decays_over_landings():
    n = OUNoise(sigma=0.4, sigma_min=0.05, decay=0.5, rng=np.random.default_rng(0))
    s0 = np.std([n.sample() for _ in range(2000)])
    for _ in range(2):
        n.landed()
    assert n.sigma == pytest.approx(0.1)
    n.reset()
    s2 = np.std([n.sample() for _ in range(2000)])
    assert s2 < 0.4 * s0
    for _ in range(20):
        n.landed()
    assert n.sigma == 0.05


def test_end_to_end_networks_accept_images():
    agent = TD3(16, 3, TD3Config(hidden=(32,), image_channels=(8, 8, 8, 8)), image=True, seed=0)
    obs = np.zeros(4 * 64 * 64 + 16, np.float32)
    assert agent.act(obs).shape == (3,)


def test_replay_buffer_keeps_privileged_values_beside_each_observation(tmp_path):
    buf = ReplayBuffer(2, 3, capacity=10, priv_dim=1)
    assert buf.obs_dim == 3
    buf.add([1, 2], [0, 0, 0], 0.5, [3, 4], False, priv=[9], next_priv=[8])
    buf.extend(np.array([[5, 6]]), np.zeros((1, 3)), [1.0], np.array([[7, 8]]), [True],
               priv=np.array([[7]]), next_priv=np.array([[6]]))
    np.testing.assert_array_equal(buf.obs[:2], [[1, 2, 9], [5, 6, 7]])
    np.testing.assert_array_equal(buf.next_obs[:2], [[3, 4, 8], [7, 8, 6]])
    with pytest.raises(ValueError, match='keeps 1 privileged'):
        buf.add([1, 2], [0, 0, 0], 0.0, [3, 4], False)
    with pytest.raises(ValueError, match='2 privileged values, expected 1'):
        buf.add([1, 2], [0, 0, 0], 0.0, [3, 4], False, priv=[1, 2], next_priv=[1, 2])
    with pytest.raises(ValueError, match='keeps none'):
        ReplayBuffer(2, 3, 10).add([1, 2], [0, 0, 0], 0.0, [3, 4], False, priv=[1], next_priv=[1])
    buf.save(tmp_path / 'p.npz')
    again = ReplayBuffer(2, 3, capacity=10, priv_dim=1)
    assert again.load(tmp_path / 'p.npz') == 2
    np.testing.assert_array_equal(again.obs[:2], buf.obs[:2])
    with pytest.raises(ValueError, match=r'observation size 3 != 2'):
        ReplayBuffer(2, 3, 10).load(tmp_path / 'p.npz')


def test_asymmetric_critic_sees_the_privileged_values_and_the_actor_does_not():
    """One-step task whose best action depends on a value only the critic sees in training (the 'goal' side,
    +-1) but that the observation also carries: the critic learns from it, the actor acts on the observation."""
    torch.set_num_threads(1)
    rng = np.random.default_rng(0)
    agent = TD3(2, 3, TD3Config(hidden=(32, 32), batch_size=32, privileged_dim=1), seed=0)
    assert agent.critic.q1[0].in_features == 2 + 1 + 3 and agent.actor.head[0].in_features == 2
    buf = ReplayBuffer(2, 3, 10_000, priv_dim=1)
    with pytest.raises(ValueError, match='the buffer keeps 0'):
        agent.update(ReplayBuffer(2, 3, 10))
    for step in range(1000):
        side = rng.choice([-1.0, 1.0])
        o = np.array([side, rng.uniform(-1, 1)])
        a = np.clip(agent.act(o) + rng.normal(0, 0.3, 3), -1, 1) if step > 300 else rng.uniform(-1, 1, 3)
        buf.add(o, a, -float((a[0] - 0.6 * side) ** 2), o, True, priv=[side], next_priv=[side])
        if buf.size >= 32:
            agent.update(buf)
    for side in (-1.0, 1.0):
        assert agent.act(np.array([side, 0.0]))[0] == pytest.approx(0.6 * side, abs=0.15)
    # the privileged value reaches the critic only: the actor's action for an observation is the same whatever
    # was stored beside it
    with torch.no_grad():
        act = agent.actor(torch.tensor([[1.0, 0.0]]))
        q_plus = float(agent.critic.q1_only(torch.tensor([[1.0, 0.0, 1.0]]), act))
        q_minus = float(agent.critic.q1_only(torch.tensor([[1.0, 0.0, -1.0]]), act))
    assert q_plus > q_minus       # the action suits side +1: the critic, told the side, values it there


def test_td3_keeps_a_goal_head_trained_on_the_privileged_goal():
    """The first three privileged values are the goal head's label: TD3's actor updates keep the head on them; an
    actor with a head but no privileged values is refused (its head would drift with the shared layers)."""
    from assist_lab.td3 import goal_nll
    torch.set_num_threads(1)
    rng = np.random.default_rng(1)
    cfg = TD3Config(hidden=(16, 16), batch_size=32, goal_head=True, privileged_dim=3, goal_weight=1.0)
    agent = TD3(2, 3, cfg, seed=1)
    buf = ReplayBuffer(2, 3, 2000, priv_dim=3)
    obs = rng.uniform(-1, 1, (500, 2)).astype(np.float32)
    goal = np.stack([obs[:, 0], -obs[:, 1], obs[:, 0] * 0.5], axis=1)      # a function of what the actor sees
    buf.extend(obs, rng.uniform(-1, 1, (500, 3)), np.zeros(500), obs, np.ones(500), priv=goal, next_priv=goal)

    def nll() -> float:
        with torch.no_grad():
            return float(goal_nll(agent.actor.act_and_goal(torch.as_tensor(obs))[1], torch.as_tensor(goal)))
    before = nll()
    out = {}
    for _ in range(400):
        out = agent.update(buf) or out
    assert nll() < before - 1.0 and 'goal_nll' in out
    plain = TD3(2, 3, TD3Config(hidden=(16, 16), batch_size=32, goal_head=True), seed=1)
    flat = ReplayBuffer(2, 3, 100)
    flat.extend(obs[:50], np.zeros((50, 3)), np.zeros(50), obs[:50], np.ones(50))
    with pytest.raises(ValueError, match='goal head learns in TD3 only with'):
        for _ in range(cfg.policy_delay):
            plain.update(flat)
