"""episodes_plan.landing_plan draws exactly what LandingAssistEnv.reset draws (scene, goal, pilot, noise seed)."""
import numpy as np
import pytest
from assist_lab.env import EnvConfig, LandingAssistEnv
from assist_lab.episodes_plan import evaluation_plans, landing_plan
from assist_sim.pilots import make_pilot

LATENT_DIM = 4


class FakeLatent:
    """latent_fn stand-in that records the noise seed env.reset gives it."""

    def __init__(self):
        self.seeds = []

    def __call__(self, rgb, depth):
        return np.zeros(LATENT_DIM)

    def reset(self, seed):
        self.seeds.append(int(seed))


@pytest.fixture(scope='module')
def envs():
    made = {}

    def get(family: str, paper_share: float = 0.0):
        key = (family, paper_share)
        if key not in made:
            latent = FakeLatent()
            env = LandingAssistEnv(EnvConfig(condition='latent', latent_dim=LATENT_DIM, pilot_family=family,
                                             paper_share=paper_share), latent_fn=latent)
            made[key] = (env, latent)
        return made[key]
    yield get
    for env, _ in made.values():
        env.close()


def _same_pilot(env: LandingAssistEnv, plan) -> None:
    """The plan's pilot, built and started as the env does, is the env's pilot (params, estimate, first command)."""
    pilot = make_pilot(plan.pilot_family, plan.alpha, plan.beta, env.pilot_cfg,
                       np.random.default_rng(plan.pilot_seed), pads=env.world.pad_top_centers)
    start = np.asarray(env.world.scene.start_position, dtype=float)
    pilot.reset(env.world.goal_position, start)
    u = pilot.act(start, None)
    assert pilot.name == env.pilot.name == plan.pilot_family_resolved
    assert pilot.params == env.pilot.params
    np.testing.assert_array_equal(pilot.goal_estimate, env.pilot.goal_estimate)
    np.testing.assert_array_equal(u, env.pilot_action)


@pytest.mark.parametrize('family', ['paper', 'mix', 'late_correction', 'train_mix'])
def test_plan_equals_env_reset(envs, family):
    env, latent = envs(family)
    for seed, beta in ((2024, 0.0), (3025, 0.5), (4031, 1.0), (7, 0.35)):
        plan = landing_plan(seed, beta, family, 0.5)
        _, info = env.reset(seed=seed, options={'beta': beta})
        assert info['scene_seed'] == plan.scene_seed
        assert info['beta'] == plan.beta          # (info's alpha is the pilot's own: follower families draw it)
        assert info['pilot'] == plan.pilot_family_resolved
        assert latent.seeds[-1] == plan.noise_seed
        # the world the scene seed builds: same scene, same goal
        goal = env.world.goal_index
        scene = env.world.pad_top_centers.copy()
        env.world.reset(seed=plan.scene_seed)
        assert env.world.goal_index == goal
        np.testing.assert_array_equal(env.world.pad_top_centers, scene)
        env.reset(seed=seed, options={'beta': beta})
        _same_pilot(env, plan)


def test_mix_draws_several_families():
    names = {landing_plan(s, 0.5, 'mix').pilot_family_resolved for s in range(2024, 2044)}
    assert len(names) >= 3 and 'mix' not in names


def test_drawn_beta_and_paper_share_follow_reset(envs):
    env, latent = envs('train_mix', paper_share=0.5)
    kinds = set()
    for seed in range(11, 19):
        plan = landing_plan(seed, None, 'train_mix', 0.5, paper_share=0.5, pilot_named=False)
        _, info = env.reset(seed=seed)            # beta drawn, paper share drawn
        assert (info['scene_seed'], info['beta'], info['pilot']) == (plan.scene_seed, plan.beta,
                                                                     plan.pilot_family_resolved)
        assert latent.seeds[-1] == plan.noise_seed
        _same_pilot(env, plan)
        kinds.add(plan.pilot_family == 'paper')
    assert kinds == {True, False}                  # both branches of the paper share were taken


def test_generator_argument_continues_the_episode_stream():
    rng = np.random.default_rng(5)
    first, second = landing_plan(rng, 0.5), landing_plan(rng, 0.5)
    assert first.scene_seed != second.scene_seed


def test_evaluation_plans_are_evaluates_seeds():
    plans = evaluation_plans(2024, (0.0, 0.5), 3, 'mix')
    assert [s for s, _ in plans] == [2024, 2025, 2026, 3024, 3025, 3026]
    assert [p.beta for _, p in plans] == [0.0] * 3 + [0.5] * 3
    assert plans[4][1] == landing_plan(3025, 0.5, 'mix')
