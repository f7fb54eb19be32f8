"""The env's plant: the world's own, or ArduCopter's drawn per landing (randomised) for training."""
import numpy as np

from assist_lab.env import EnvConfig, LandingAssistEnv
from assist_sim.core.arducopter import ArduCopterConfig
from assist_sim.core.config import WorldConfig


def _reset(cfg: EnvConfig, seed: int):
    env = LandingAssistEnv(cfg)
    try:
        _, info = env.reset(seed=seed, options={'beta': 0.5})
        fc = env.world.flight_controller
        return info, None if fc is None else fc.cfg
    finally:
        env.close()


def test_plant_draws_leave_the_landing_itself_unchanged_and_randomise_the_arducopter_dynamics():
    base_info, base_fc = _reset(EnvConfig(condition='oracle'), 7)
    assert base_fc is None and base_info['plant'] == 'ideal'
    plants, cfgs = set(), []
    for seed in range(7, 17):
        info, fc = _reset(EnvConfig(condition='oracle', arducopter_share=0.5, arducopter_spread=0.3), seed)
        plants.add(info['plant'])
        if seed == 7:       # the scene, goal, pilot and camera noise of a landing do not depend on its plant
            assert {k: info[k] for k in ('scene_seed', 'goal_index', 'beta', 'pilot')} == \
                   {k: base_info[k] for k in ('scene_seed', 'goal_index', 'beta', 'pilot')}
        if info['plant'] == 'arducopter':
            cfgs.append(fc)
        else:
            assert fc is None
    assert plants == {'ideal', 'arducopter'}
    base = ArduCopterConfig()
    assert all(c != base for c in cfgs)
    assert all(0.7 * base.attitude_tc_s <= c.attitude_tc_s <= 1.3 * base.attitude_tc_s for c in cfgs)
    assert len({c.attitude_tc_s for c in cfgs}) == len(cfgs)


def test_an_arducopter_world_flies_arducopter_without_randomisation():
    info, fc = _reset(EnvConfig(condition='oracle', world=WorldConfig(flight_controller='arducopter')), 3)
    assert info['plant'] == 'arducopter' and fc == ArduCopterConfig()


def test_the_same_seed_draws_the_same_plant():
    cfg = EnvConfig(condition='oracle', arducopter_share=0.5, arducopter_spread=0.3)
    a = [_reset(cfg, s) for s in (21, 22, 23)]
    b = [_reset(cfg, s) for s in (21, 22, 23)]
    assert [x[0]['plant'] for x in a] == [x[0]['plant'] for x in b]
    assert [x[1] for x in a] == [x[1] for x in b]
    assert np.all([x[0]['scene_seed'] == y[0]['scene_seed'] for x, y in zip(a, b)])
