"""Pilot population in the env, evaluate --pilot / --safety, and train_td3's training-only pilots."""
import csv

import numpy as np
import pytest

from assist_lab.env import EnvConfig, LandingAssistEnv, run_episode
from assist_lab.evaluate import EvalArgs, evaluate, main
from assist_policy.safety import SafetyConfig
from assist_lab.train import TrainArgs, check_training_pilot, env_config_from
from assist_sim.pilots import HELDOUT_FAMILIES, TRAIN_FAMILIES


def test_a_pilot_who_changes_their_mind_is_judged_on_the_final_goal():
    env = LandingAssistEnv(EnvConfig(condition='none', pilot_family='change_mind', max_episode_s=60.0))
    for seed in (2024, 2027):
        _, info = env.reset(seed=seed, options={'beta': 0.5})
        first = info['goal_index']
        res = run_episode(env, None, seed, {'beta': 0.5})
        final = env.pilot.params['new_goal_index']
        # the world's goal followed the pilot: the landing is judged on the pad it wanted last
        assert final != first and res['goal_index'] == final == env.world.goal_index
        assert res['success'] == (res['landed_index'] == final)
    env.close()


def test_the_graph_refuses_a_pilot_whose_goal_changes(capsys):
    from assist_lab.graph_eval import main as graph_main
    with pytest.raises(SystemExit) as exit_info:
        graph_main(['--pilot', 'change_mind', '--out', 'unused'])
    assert exit_info.value.code == 2 and 'change_mind' in capsys.readouterr().err


def test_env_flies_the_named_family_and_mix_draws_held_out_families():
    env = LandingAssistEnv(EnvConfig(condition='none', pilot_family='late_correction'))
    _, info = env.reset(seed=3)
    assert info['pilot'] == 'late_correction' and 'notice_height_m' in info['pilot_params']
    pads = env.world.pad_top_centers
    est = env.pilot.goal_estimate
    # the wrong pad it flies to is a real pad of this scene, not the goal
    k = int(np.argmin(np.linalg.norm(pads[:, :2] - est[:2], axis=1)))
    assert k != env.world.goal_index and np.linalg.norm(pads[k, :2] - est[:2]) < 0.4
    seen = set()
    for s in range(12):
        _, info = env.reset(seed=s, options={'pilot': 'mix'})
        seen.add(info['pilot'])
    assert seen <= set(HELDOUT_FAMILIES) and len(seen) >= 3
    env.close()


def test_paper_pilot_episode_is_unchanged_by_the_population_code():
    """The default pilot through make_pilot gives the same landing as before (seeded, bit-identical pilot)."""
    a = LandingAssistEnv(EnvConfig(condition='none'))
    b = LandingAssistEnv(EnvConfig(condition='none', pilot_family='paper'))
    ra, rb = run_episode(a, None, 5, {'beta': 0.3}), run_episode(b, None, 5, {'beta': 0.3})
    assert ra['error_m'] == rb['error_m'] and ra['outcome'] == rb['outcome'] and ra['pilot'] == 'paper'
    a.close()
    b.close()


def test_evaluate_pilot_and_safety_columns(tmp_path):
    args = EvalArgs(out=str(tmp_path), conditions=('unassisted', 'scripted_nearest_pad'), betas=(0.0,),
                    landings=2, pilot='bang_bang', safety=True, plot=False)
    summary = evaluate(args)
    assert set(summary) == {'unassisted', 'scripted_nearest_pad+guard'}
    rows = list(csv.DictReader(open(tmp_path / 'landings.csv')))
    assert len(rows) == 4 and {r['pilot'] for r in rows} == {'bang_bang'}
    assert all(0.0 <= float(r['guard_fraction']) <= 1.0 for r in rows)
    assert all(float(r['guard_fraction']) == 0.0 for r in rows if r['condition'] == 'unassisted')
    with pytest.raises(SystemExit) as exc:          # a bad value: one error line, exit 2, before any work
        main(['--pilot', 'nobody', '--out', str(tmp_path / 'x'), '--landings', '1'])
    assert exc.value.code == 2 and not (tmp_path / 'x').exists()


def test_env_floor_guard_turns_a_floor_descent_into_a_climb():
    """Over the floor, below the guard height, a descending pilot is held up by the guard (oracle env)."""
    env = LandingAssistEnv(EnvConfig(condition='oracle', safety=SafetyConfig()))
    env.reset(seed=1)
    pads = env.world.pad_top_centers
    x = pads[:, 0].min() - 2.0                                   # well before the first pad: floor only
    env.world.reset(seed=env.world.scene.seed, scene=env.world.scene, start_position=[x, 0.0, 0.7])
    env._u = np.array([0.0, 0.0, -0.5])
    _, _, _, _, info = env.step(np.zeros(3))
    assert info['guard'] and info['active']
    assert env.world.state.velocity[2] > -0.2                     # not following the -0.5 m/s descent
    env.close()


def test_training_refuses_held_out_pilots():
    for name in TRAIN_FAMILIES + ('train_mix',):
        check_training_pilot(name)
    for name in HELDOUT_FAMILIES + ('mix', 'approach_mix'):
        with pytest.raises(ValueError, match='not for training'):
            env_config_from(TrainArgs(pilot=name))
    cfg = env_config_from(TrainArgs(pilot='train_mix', safety=True))
    assert cfg.pilot_family == 'train_mix' and cfg.safety.enabled


def test_paired_comparison_with_unassisted_on_the_same_landings():
    from assist_lab.evaluate import format_paired, paired_vs_unassisted

    def row(beta, seed, err, crash=False):
        return {'beta': beta, 'seed': seed, 'error_m': err, 'crash': crash}
    rows = {'unassisted': [row(0.0, 1, 0.5), row(0.0, 2, 1.0, True), row(1.0, 3, 0.2)],
            'latent': [row(0.0, 1, 0.1), row(0.0, 2, 0.1), row(1.0, 3, 0.6, True), row(1.0, 9, 0.0)]}
    p = paired_vs_unassisted(rows)
    assert set(p) == {'latent'} and p['latent']['n'] == 3                  # seed 9 has no unassisted twin
    assert p['latent']['delta_error'] == pytest.approx((-0.4 - 0.9 + 0.4) / 3)
    assert p['latent']['worse'] == pytest.approx(1 / 3) and p['latent']['new_crash'] == pytest.approx(1 / 3)
    assert 'latent' in format_paired(p)


def test_yielding_nearest_pad_script_lets_a_held_key_through_but_not_taps_or_descents():
    from assist_policy.scripted import YIELD_SPEED_MPS, ScriptedConfig, ScriptedNearestPad
    pads = np.array([[4.0, 0.0, 0.6], [8.0, 0.0, 0.8]])
    pos = np.array([4.2, 0.1, 1.2])                               # low over pad 0, off its centre
    ref = ScriptedNearestPad()
    yld = ScriptedNearestPad(ScriptedConfig(yield_speed_mps=YIELD_SPEED_MPS))
    leaving = np.array([1.0, 0.0, 0.0])                           # holds 'forward' toward pad 1
    held = ref.velocity(pads, pos, leaving, mean_pilot=leaving)
    assert held[0] < -0.5                                          # the reference cancels it and centres
    np.testing.assert_array_equal(yld.velocity(pads, pos, leaving, mean_pilot=leaving), 0.0)
    taps = np.array([0.5, 0.5, 0.0])                               # fine taps: mean 0.71 m/s < 0.75
    np.testing.assert_allclose(yld.velocity(pads, pos, leaving, mean_pilot=taps), held)
    down = np.array([1.0, 0.0, -0.5])                              # overshooting while descending: no yield
    np.testing.assert_allclose(yld.velocity(pads, pos, down, mean_pilot=leaving),
                               ref.velocity(pads, pos, down, mean_pilot=leaving))


def test_gentle_nearest_pad_script_adds_no_descent_to_a_descending_pilot_but_still_centres():
    from assist_policy.scripted import NEAREST_PAD_VARIANTS, ScriptedNearestPad, make_nearest_pad
    pads = np.array([[4.0, 0.0, 0.6], [8.0, 0.0, 0.8]])
    pos = np.array([4.05, 0.1, 1.2])                              # low, within 0.25 m of pad 0's centre
    ref, gentle = make_nearest_pad('nearest_pad'), make_nearest_pad('nearest_pad_gentle')
    assert isinstance(gentle, ScriptedNearestPad) and set(NEAREST_PAD_VARIANTS) >= {'nearest_pad', 'nearest_pad_gentle'}
    down = np.array([0.0, 0.0, -0.5])
    r, g = ref.velocity(pads, pos, down), gentle.velocity(pads, pos, down)
    assert r[2] == pytest.approx(-0.6) and g[2] == 0.0            # the reference pushes down (clipped), gentle not
    np.testing.assert_allclose(g[:2], r[:2])                      # both centre: 2 * 4 /s * (-0.05, -0.1)
    np.testing.assert_allclose(g[:2], [-0.4, -0.8])
    hover = np.zeros(3)                                           # a pilot hovering low: both bring it down
    assert gentle.velocity(pads, pos, hover)[2] == pytest.approx(-0.6)
    with pytest.raises(ValueError, match='unknown nearest-pad variant'):
        make_nearest_pad('nearest_pad_fast')


def test_commit_teacher_is_gentle_high_up_and_pushes_down_in_the_last_half_metre():
    from assist_policy.scripted import COMMIT_HEIGHT_M, make_nearest_pad
    pads = np.array([[4.0, 0.0, 0.6], [8.0, 0.0, 0.8]])
    commit, gentle = make_nearest_pad('nearest_pad_commit'), make_nearest_pad('nearest_pad_gentle')
    down = np.array([0.0, 0.0, -0.5])
    high = np.array([4.05, 0.1, 0.6 + COMMIT_HEIGHT_M + 0.3])      # over pad 0, above the commit height
    np.testing.assert_allclose(commit.velocity(pads, high, down), gentle.velocity(pads, high, down))
    assert commit.velocity(pads, high, down)[2] == 0.0
    low = np.array([4.05, 0.1, 0.6 + COMMIT_HEIGHT_M - 0.1])       # inside the last half metre: committed
    c = commit.velocity(pads, low, down)
    assert c[2] == pytest.approx(-0.6) and gentle.velocity(pads, low, down)[2] == 0.0
    np.testing.assert_allclose(c[:2], [-0.4, -0.8])               # centring is the same for every variant


def test_commit_yield_teacher_is_the_commit_teacher_until_a_held_key_then_yields():
    from assist_policy.scripted import COMMIT_HEIGHT_M, make_nearest_pad
    pads = np.array([[4.0, 0.0, 0.6], [8.0, 0.0, 0.8]])
    cy, commit = make_nearest_pad('nearest_pad_commit_yield'), make_nearest_pad('nearest_pad_commit')
    down, leaving = np.array([0.0, 0.0, -0.5]), np.array([1.0, 0.0, 0.0])
    for h in (COMMIT_HEIGHT_M + 0.3, COMMIT_HEIGHT_M - 0.1):       # gentle high up, committed low: as commit
        pos = np.array([4.05, 0.1, 0.6 + h])
        np.testing.assert_allclose(cy.velocity(pads, pos, down, mean_pilot=down), commit.velocity(pads, pos, down))
    pos = np.array([4.2, 0.1, 1.2])                                # low over pad 0; the pilot holds 'forward'
    assert commit.velocity(pads, pos, leaving, mean_pilot=leaving)[0] < -0.5
    np.testing.assert_array_equal(cy.velocity(pads, pos, leaving, mean_pilot=leaving), 0.0)


def test_evaluate_runs_the_gentle_reference_as_a_baseline():
    from assist_lab.evaluate import BASELINES, make_policy
    assert 'scripted_nearest_pad_gentle' in BASELINES
    env, policy = make_policy('scripted_nearest_pad_gentle', '', '', 5.0, 0.5)
    obs, _ = env.reset(seed=3, options={'beta': 0.5})
    a = policy(obs)
    assert a.shape == (3,) and np.all(np.abs(a) <= 1.0)
