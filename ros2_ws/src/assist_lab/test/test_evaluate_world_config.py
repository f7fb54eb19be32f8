"""evaluate --world-config: the landing world from a YAML file (e.g. the SITL series' start), checked up front."""
from pathlib import Path

import numpy as np
import pytest

from assist_lab.evaluate import EvalArgs, evaluate, make_policy

SITL_START = Path(__file__).resolve().parents[2] / 'assist_sim' / 'config' / 'world_sitl_start.yaml'


def test_the_sitl_start_file_starts_every_landing_over_the_start_spot_with_the_same_scene():
    env, _ = make_policy('unassisted', '', '', 60.0, 0.5, flight_controller='arducopter', world_config=str(SITL_START))
    plain, _ = make_policy('unassisted', '', '', 60.0, 0.5, flight_controller='arducopter')
    try:
        assert env.world.flight_controller is not None
        for seed in (11, 12):
            _, info = env.reset(seed=seed, options={'beta': 0.5})
            assert np.allclose(env.world.state.position, [0.0, 0.0, 2.0], atol=1e-6)
            _, info_plain = plain.reset(seed=seed, options={'beta': 0.5})
            assert info['scene_seed'] == info_plain['scene_seed'] and info['goal_index'] == info_plain['goal_index']
            assert np.allclose(env.world.pad_top_centers, plain.world.pad_top_centers)
            assert not np.allclose(plain.world.state.position, [0.0, 0.0, 2.0], atol=1e-3)
    finally:
        env.close()
        plain.close()


def test_a_world_config_that_cannot_be_read_is_refused_before_anything_flies(tmp_path):
    bad = tmp_path / 'bad.yaml'
    bad.write_text('bogus_field: 1\n')
    for path in (bad, tmp_path / 'missing.yaml'):
        with pytest.raises(ValueError, match='--world-config'):
            evaluate(EvalArgs(out=str(tmp_path / 'out'), conditions=('unassisted',), betas=(0.5,), landings=1,
                              world_config=str(path), plot=False))
    assert not (tmp_path / 'out').exists()
