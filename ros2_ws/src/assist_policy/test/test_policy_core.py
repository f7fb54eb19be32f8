"""Pure policy core: staleness, relinquishing, NaN rejection, blending, clamping, model checks."""
import math

import numpy as np
import pytest
import torch

from assist_policy.observation import vector_dim
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_policy.actor import Actor, save_actor
from assist_policy.testing import LATENT, constant_actor



@pytest.fixture
def core(tmp_path):
    return PolicyCore(constant_actor(tmp_path / 'a.pt', [0.8, 0.0, 0.0]), PolicyCoreConfig(mode='latent'))


def feed(core, t, u=(0.0, 1.0, 0.0), latent=True):
    core.set_odom(t, [1, 0, 2], [0, 0, 0])
    core.set_pilot(t, u)
    if latent:
        core.set_latent(t, np.zeros(LATENT))


def test_assists_with_blend_when_inputs_fresh(core):
    feed(core, 10.0)
    out = core.step(10.05)
    np.testing.assert_allclose(out.agent, [0.8, 0, 0], atol=1e-6)
    np.testing.assert_allclose(out.velocity, [0.4, 0.5, 0.0], atol=1e-6)


def test_relinquishes_when_latent_stale_or_absent(core):
    feed(core, 10.0, latent=False)
    out = core.step(10.0)
    assert out.agent is None and 'stale or absent' in out.reason
    np.testing.assert_allclose(out.velocity, [0, 1, 0])
    core.set_latent(10.0, np.zeros(LATENT))
    core.set_odom(10.6, [1, 0, 2], [0, 0, 0])
    core.set_pilot(10.6, [0, 1, 0])
    out = core.step(10.6)      # latent 0.6 s old > 0.5 s
    assert out.agent is None
    np.testing.assert_allclose(out.velocity, [0, 1, 0])


def test_relinquishes_when_odom_stale_and_pilot_absent_is_zero(core):
    feed(core, 0.0)
    out = core.step(1.0)
    assert out.agent is None
    np.testing.assert_allclose(out.velocity, np.zeros(3))   # pilot stale too: u = 0


def test_nonfinite_inputs_rejected(core):
    with pytest.raises(ValueError):
        core.set_pilot(0.0, [math.nan, 0, 0])
    with pytest.raises(ValueError):
        core.set_latent(0.0, np.full(LATENT, math.inf))
    with pytest.raises(ValueError):
        core.set_latent(0.0, np.zeros(LATENT + 1))


def test_nonfinite_actor_output_never_reaches_velocity(tmp_path):
    # NaN weights are refused at load (test_policy_td3); a network can still overflow at run time
    core = PolicyCore(constant_actor(tmp_path / 'a.pt', [0.5, 0.5, 0.5]), PolicyCoreConfig(mode='latent'))
    with torch.no_grad():
        core.actor.net.head[-1].bias.fill_(float('nan'))
    feed(core, 1.0)
    out = core.step(1.0)
    assert out.agent is None and 'not finite' in out.reason and out.key == 'actor_nonfinite'
    np.testing.assert_allclose(out.velocity, [0, 1, 0])
    assert core.rejected == 1


def test_small_actions_relinquish_and_speed_is_clamped(tmp_path):
    core = PolicyCore(constant_actor(tmp_path / 's.pt', [0.1, 0.1, 0.0]), PolicyCoreConfig(mode='latent'))
    feed(core, 1.0, u=(0.0, 1.0, 0.0))
    out = core.step(1.0)
    assert out.reason == 'relinquished'
    np.testing.assert_allclose(out.velocity, [0, 1, 0])
    feed(core, 2.0, u=(3.0, 0.0, -4.0))
    out = core.step(2.0)
    assert np.hypot(*out.velocity[:2]) == pytest.approx(1.5)
    assert out.velocity[2] == pytest.approx(-1.0)


def test_oracle_needs_goal_and_mode_mismatch_is_an_error(tmp_path):
    path = constant_actor(tmp_path / 'o.pt', [0.0, 0.9, 0.0], condition='oracle', latent_dim=0)
    with pytest.raises(ValueError, match='trained for'):
        PolicyCore(path, PolicyCoreConfig(mode='latent'))
    core = PolicyCore(path, PolicyCoreConfig(mode='oracle'))
    feed(core, 1.0, u=(0.0, 0.5, 0.0), latent=False)     # not a held key: the pilot override stays out
    assert core.step(1.0).agent is None
    core.set_goal([5, 0, 1])
    np.testing.assert_allclose(core.step(1.0).agent, [0, 0.9, 0], atol=1e-6)


def test_end_to_end_core_needs_fresh_images(tmp_path):
    actor = Actor(vector_dim('end_to_end'), 3, hidden=(8,), image=True, image_channels=(4, 4, 4, 4))
    meta = {'vec_dim': vector_dim('end_to_end'), 'act_dim': 3, 'image': True, 'hidden': [8],
            'image_channels': [4, 4, 4, 4], 'condition': 'end_to_end', 'latent_dim': 0, 'max_speed': [1.0, 1.0, 0.6]}
    save_actor(actor, meta, tmp_path / 'e2e.pt')
    core = PolicyCore(tmp_path / 'e2e.pt', PolicyCoreConfig(mode='end_to_end'))
    feed(core, 1.0, latent=False)
    assert core.step(1.0).agent is None                      # no image yet: relinquish
    core.set_image(1.0, np.zeros((64, 64, 3), np.uint8), np.full((64, 64), 2.0, np.float32))
    out = core.step(1.05)
    assert out.agent is not None and np.all(np.isfinite(out.velocity))
    assert core.step(2.0).agent is None                      # image stale after 0.5 s


def test_actor_velocity_odom_rotates_the_twist_with_the_attitude(tmp_path, monkeypatch):
    """actor_velocity 'odom' (evaluate's env, replay of its bags): the actor sees R(q) twist; 'twist'
    (policy_node): as given."""
    seen = {}
    yaw90 = [0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
    for frame in ('twist', 'odom'):
        core = PolicyCore(constant_actor(tmp_path / f'{frame}.pt', [0.8, 0.0, 0.0]),
                          PolicyCoreConfig(mode='latent', actor_velocity=frame))
        build = core.builder.build

        def spy(now, feature, vel, *rest, frame=frame, build=build):
            seen[frame] = np.array(vel, dtype=float)
            return build(now, feature, vel, *rest)
        monkeypatch.setattr(core.builder, 'build', spy)
        core.set_odom(10.0, [1, 0, 2], [1.0, 0.0, 0.2], yaw90)
        core.set_pilot(10.0, [0, 0, 0])
        core.set_latent(10.0, np.zeros(LATENT))
        assert core.step(10.05).agent is not None
    np.testing.assert_allclose(seen['twist'], [1.0, 0.0, 0.2], atol=1e-12)
    np.testing.assert_allclose(seen['odom'], [0.0, 1.0, 0.2], atol=1e-12)     # base_link x is odom y at yaw 90
    with pytest.raises(ValueError, match='actor_velocity'):
        PolicyCoreConfig(actor_velocity='world')


def test_pass_through_flies_the_pilot_with_no_agent_action(core):
    """assist_enabled false (a study's unassisted block): V = u, clamped, no agent action, an OK reason key."""
    feed(core, 10.0, u=(0.5, -0.3, -0.2))
    out = core.pass_through(10.01)
    assert out.agent is None and out.key == 'switched_off'
    np.testing.assert_allclose(out.velocity, [0.5, -0.3, -0.2])
    feed(core, 10.02, u=(4.5, 0.0, 0.0))                    # accepted input, above the output speed limit
    assert np.linalg.norm(core.pass_through(10.03).velocity) == pytest.approx(core.cfg.max_speed_mps)
