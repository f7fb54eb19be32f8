"""The step code around the actor (assist_policy.loop.AssistLoop), shared by policy_node's core and the env."""
from __future__ import annotations

import numpy as np

from assist_policy.assistant import Assistant
from assist_policy.flight import FlightMonitor
from assist_policy.loop import AssistLoop
from assist_policy.observation import IMAGE_SHAPE, Condition, ObservationBuilder
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_policy.testing import LATENT, constant_actor


def _loop(condition: Condition, latent_dim: int = 0) -> AssistLoop:
    return AssistLoop(condition, ObservationBuilder(condition, latent_dim), Assistant(), FlightMonitor())


def test_the_observation_is_the_builders_vector_and_end_to_end_puts_the_image_feature_first():
    pos, vel, u = np.array([1.0, 2.0, 3.0]), np.array([0.1, -0.2, 0.3]), np.array([0.5, 0.0, -0.2])
    latent = _loop(Condition.LATENT, LATENT)
    mu = np.linspace(-1, 1, LATENT)
    np.testing.assert_array_equal(latent.observation(0.0, mu, vel, pos, u),
                                  ObservationBuilder(Condition.LATENT, LATENT).build(0.0, mu, vel, pos[2], u, pos))
    e2e = _loop(Condition.END_TO_END)
    image = np.full(int(np.prod(IMAGE_SHAPE)), 0.25)
    obs = e2e.observation(0.0, image, vel, pos, u)
    assert obs.dtype == np.float32 and obs.size == image.size + e2e.builder.dim
    np.testing.assert_array_equal(obs[:image.size], np.float32(0.25))
    np.testing.assert_array_equal(obs[image.size:], e2e.builder.build(0.0, np.zeros(0), vel, pos[2], u))


def test_act_records_what_was_applied_idle_records_no_action_and_forget_counts_by_reason():
    loop = _loop(Condition.ORACLE)
    u = np.array([0.4, 0.0, 0.0])
    ctx = loop.context(0.0, u, np.array([0.0, 0.0, 2.0]), np.zeros(3), None, None, (1.0, 1.0, 0.6))
    res = loop.act(ctx, np.array([0.6, 0.0, 0.0]))
    assert res.key == 'assisting'
    np.testing.assert_allclose(loop.builder.history.means(0.0)[1], [0.6, 0.0, 0.0])
    loop.idle(0.05, u)
    np.testing.assert_allclose(loop.builder.history.means(0.05)[1], [0.3, 0.0, 0.0])   # (0.6 + 0) / 2
    loop.forget('odom_jump')
    loop.forget('odom_jump')
    assert len(loop.builder.history) == 0 and loop.flight_resets == {'odom_jump': 2}
    loop.restart()
    assert loop.flight_resets == {'odom_jump': 2}      # a new episode is not a boundary inside a flight


def test_policy_core_steps_through_its_loop(tmp_path):
    core = PolicyCore(constant_actor(tmp_path / 'a.pt', [0.5, 0.0, 0.0], 'oracle', 0),
                      PolicyCoreConfig(mode='oracle', flight=None))
    assert core.loop.builder is core.builder and core.loop.assistant is core.assistant
    assert core.flight_resets is core.loop.flight_resets
    core.set_goal(np.array([3.0, 0.0, 0.0]))
    core.set_odom(0.0, np.array([0.0, 0.0, 3.0]), np.zeros(3))
    core.set_pilot(0.0, np.zeros(3))
    out = core.step(0.0)
    assert out.key == 'assisting' and len(core.builder.history) == 1
    core.reset()
    assert core.flight_resets['service'] == 1 and len(core.builder.history) == 0
