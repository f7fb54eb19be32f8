"""train_td3 end to end on a tiny budget: run directory, metrics, checkpoints, --resume; scripted demos."""
import csv
import json

import pytest
import torch

from assist_lab.env import EnvConfig, LandingAssistEnv
from assist_policy.scripted import ScriptedOracle
from assist_lab.td3 import TD3, TD3Config, load_actor
from assist_lab.train import TrainArgs, load_checkpoint, train


def _tiny_run(tmp_path, total_steps: int, buffer_size: int, checkpoint_every_steps: int = 1000, **extra) -> dict:
    """TrainArgs fields of a seconds-long oracle run in tmp_path (32x32 actor, 4 s landings, no periodic eval, one
    landing per beta in the final one)."""
    torch.set_num_threads(1)
    return dict(runs_dir=str(tmp_path), total_steps=total_steps, start_steps=0,
                checkpoint_every_steps=checkpoint_every_steps, eval_every_episodes=1000, hidden=(32, 32),
                max_episode_s=4.0, buffer_size=buffer_size, **{'eval_episodes_per_beta': 1, **extra})


def _first_actor(base: dict):
    """Train run 'first' with `base`; (its run directory, its last actor)."""
    first = train(TrainArgs(name='first', **base))
    return first, load_actor(first / 'actor_last.pt')[0]


def test_train_writes_run_dir_and_resumes(tmp_path):
    torch.set_num_threads(1)
    args = TrainArgs(name='tiny', runs_dir=str(tmp_path), total_steps=400, start_steps=100,
                     checkpoint_every_steps=200, eval_every_episodes=1000, eval_episodes_per_beta=1, hidden=(32, 32),
                     max_episode_s=6.0, buffer_size=5000)
    run = train(args)
    cfg = json.loads((run / 'config.json').read_text())
    assert cfg['train']['total_steps'] == 400 and cfg['env']['condition'] == 'oracle'
    state, _ = load_checkpoint(run)
    assert state['step'] >= 400
    rows = list(csv.DictReader(open(run / 'metrics.csv')))
    assert len(rows) >= 3 and all(r['outcome'] for r in rows)
    actor, meta = load_actor(run / 'actor_last.pt')
    assert meta['condition'] == 'oracle' and meta['vec_dim'] == 16
    # no periodic evaluation ran (every 1000 landings): the final actor is evaluated, so the run still has
    # its progress line, a best actor and the figures
    evals = list(csv.DictReader(open(run / 'eval.csv')))
    assert len(evals) == 1 and int(evals[0]['step']) == state['step']
    assert (run / 'progress.txt').read_text().startswith(f"step {state['step']} ")
    assert load_actor(run / 'actor_best.pt')[1]['eval']['step'] == state['step']
    for png in ('learning_curve.png', 'training_landings.png'):
        assert (run / png).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n', png
    # resume with a larger budget: continues from the checkpoint (steps and episodes keep counting)
    train(TrainArgs(resume=str(run), total_steps=700))
    state2, _ = load_checkpoint(run)
    rows2 = list(csv.DictReader(open(run / 'metrics.csv')))
    assert state2['step'] >= 700 and state2['episode'] > state['episode']
    assert int(rows2[len(rows)]['episode']) == int(rows[-1]['episode']) + 1


def test_scripted_oracle_lands_a_novice_on_its_goal():
    env = LandingAssistEnv(EnvConfig(condition='oracle', max_episode_s=60.0))
    script = ScriptedOracle(max_speed=env.cfg.max_speed)
    env.reset(seed=2024, options={'beta': 0.0})
    while True:
        _, _, term, trunc, info = env.step(script.raw_action(env))
        if term or trunc:
            break
    env.close()
    assert info['result']['success'], info['result']
    assert info['result']['error_m'] < 0.35


def test_init_actor_starts_from_a_saved_actor_and_rejects_a_foreign_one(tmp_path):
    base = _tiny_run(tmp_path, total_steps=150, buffer_size=2000, checkpoint_every_steps=100)
    first, src = _first_actor(base)
    # the step-0 evaluation writes actor_best.pt: it must be the initial actor, weight for weight
    second = train(TrainArgs(name='second', init_actor=str(first / 'actor_last.pt'), **base))
    step0, meta = load_actor(second / 'actor_best.pt')
    rows = list(csv.DictReader(open(second / 'eval.csv')))
    assert rows[0]['step'] == '0'
    for a, b in zip(src.state_dict().values(), step0.state_dict().values()):
        assert torch.equal(a, b)
    bad = TrainArgs(name='third', init_actor=str(first / 'actor_last.pt'), **{**base, 'hidden': (16,)})
    try:
        train(bad)
    except ValueError as exc:
        assert 'does not fit' in str(exc)
    else:
        raise AssertionError('a mismatched actor was accepted')


def test_dagger_round_labels_the_actors_own_states(tmp_path):
    import numpy as np
    base = _tiny_run(tmp_path, total_steps=50, buffer_size=20000, eval_episodes_per_beta=1, demo_episodes=2,
                     bc_steps=50)
    plain = train(TrainArgs(name='plain', **base))
    dag = train(TrainArgs(name='dag', dagger_rounds=1, dagger_episodes=2, **base))
    with np.load(plain / 'demos_bc.npz') as a, np.load(dag / 'demos_bc.npz') as b:
        n_demo, n_all = len(a['obs']), len(b['obs'])
        # the first n_demo rows are the same scripted demonstrations; the rest are the actor's states
        np.testing.assert_array_equal(a['obs'], b['obs'][:n_demo])
        assert n_all >= n_demo + 2 * 10           # two more landings, >= 0.5 s each at 20 Hz
        assert np.all(np.abs(b['act'][n_demo:]) <= 1.0)
    try:
        train(TrainArgs(name='nodemo', dagger_rounds=1, **{**base, 'demo_episodes': 0}))
    except ValueError as exc:
        assert 'needs demonstrations' in str(exc)
    else:
        raise AssertionError('DAgger without demonstrations was accepted')


def test_actor_start_steps_keeps_the_actor_while_the_critic_learns_and_lags_widen_it(tmp_path):
    base = _tiny_run(tmp_path, total_steps=150, buffer_size=2000)
    first, src = _first_actor(base)
    # critic-only for the whole run, fine-tuned with one lagged copy of the feature: the widened actor is unchanged
    held = train(TrainArgs(name='held', init_actor=str(first / 'actor_last.pt'), actor_start_steps=10_000,
                           feature_lags_s=(1.0,), **base))
    out, meta = load_actor(held / 'actor_last.pt')
    assert meta['feature_lags_s'] == [1.0] and meta['vec_dim'] == 16 + 3
    sd_src, sd_out = src.state_dict(), out.state_dict()
    torch.testing.assert_close(sd_out['head.0.weight'][:, :16], sd_src['head.0.weight'])
    assert torch.count_nonzero(sd_out['head.0.weight'][:, 16:]) == 0
    for k in sd_src:
        if k != 'head.0.weight':
            torch.testing.assert_close(sd_out[k], sd_src[k])
    state, _ = load_checkpoint(held)
    critic0 = TD3(19, cfg=TD3Config(hidden=(32, 32)), seed=0).critic    # the run's critic as initialised
    moved = any(not torch.equal(a, b) for a, b in zip(critic0.state_dict().values(), state['agent']['critic'].values()))
    assert moved                                  # the critic did learn meanwhile


def test_init_actor_demonstrations_are_the_starting_actors_own_actions(tmp_path):
    """--demo-policy init_actor: the frozen starting actor labels the demos (TD3+BC anchored to it)."""
    import numpy as np
    base = _tiny_run(tmp_path, total_steps=60, buffer_size=20000)
    first, src = _first_actor(base)
    anch = train(TrainArgs(name='anch', init_actor=str(first / 'actor_last.pt'), demo_policy='init_actor',
                           demo_episodes=2, demo_noise=0.1, bc_alpha=2.5, feature_lags_s=(1.0,), **base))
    with np.load(anch / 'demos_bc.npz') as d:
        obs, act = d['obs'], d['act']
    assert len(obs) >= 2 * 10
    with torch.no_grad():    # the widened actor's new inputs start at zero weight: the source actor's actions
        ref = src(torch.as_tensor(obs[:, :16])).numpy()
    np.testing.assert_allclose(act, ref, atol=1e-5)
    for bad, text in ((dict(init_actor=''), 'needs --init-actor'),
                      (dict(init_actor=str(first / 'actor_last.pt'), dagger_rounds=1), 'DAgger')):
        try:
            train(TrainArgs(name='bad', demo_policy='init_actor', demo_episodes=1, **bad, **base))
        except ValueError as exc:
            assert text in str(exc)
        else:
            raise AssertionError(f'{bad} was accepted')


def test_demonstrations_and_cloning_show_progress_on_a_terminal(monkeypatch):
    import io
    import sys

    from assist_lab.env import EnvConfig, LandingAssistEnv
    from assist_lab.td3 import TD3, ReplayBuffer, TD3Config
    from assist_lab.collect import collect_demos

    class Terminal(io.StringIO):
        def isatty(self):
            return True
    term = Terminal()
    monkeypatch.setattr(sys, 'stderr', term)
    env = LandingAssistEnv(EnvConfig(condition='oracle', max_episode_s=2.0))
    try:
        buf = ReplayBuffer(env.observation_space.shape[0], 3, 5000)
        obs, act, res = collect_demos(env, 2, 0.0, 1, buf, desc='DAgger 1/3')
        agent = TD3(obs.shape[1], 3, TD3Config(hidden=(16, 16)), seed=0)
        agent.behaviour_clone(obs, act, 5)
    finally:
        env.close()
    out = term.getvalue()
    assert len(res) == 2 and 'DAgger 1/3' in out and '2/2' in out
    assert 'behaviour cloning' in out and '5/5' in out


def test_device_choice(tmp_path, monkeypatch, capsys):
    """--device auto trains on the CPU where torch sees no GPU (as before); cuda without one is refused before any
    work; a resumed run may change the device."""
    import torch as _torch

    from assist_lab.train import SettingsError, main, prepare_run, training_device
    monkeypatch.setattr(_torch.cuda, 'is_available', lambda: False)
    assert training_device('auto') == 'cpu' and training_device('cpu') == 'cpu'
    with pytest.raises(SettingsError, match='no CUDA GPU'):
        training_device('cuda')
    with pytest.raises(SystemExit) as exit_:
        main(['--name', 'gpu', '--runs-dir', str(tmp_path), '--device', 'cuda', '--total-steps', '10'])
    assert exit_.value.code == 2 and 'no CUDA GPU' in capsys.readouterr().err
    assert not (tmp_path / 'gpu').exists()
    monkeypatch.setattr(_torch.cuda, 'is_available', lambda: True)
    assert training_device('auto') == 'cuda'
    run = train(TrainArgs(name='cpu', **_tiny_run(tmp_path, total_steps=30, buffer_size=2000, device='cpu')))
    resumed = prepare_run(TrainArgs(resume=str(run), device='cuda', total_steps=60), given=['resume', 'device',
                                                                                          'total_steps'])
    assert resumed.device == 'cuda' and resumed.total_steps == 60


def test_a_memory_actor_with_a_goal_head_clones_the_true_goal_and_evaluate_reports_its_inference(tmp_path):
    """--history-s and --goal-head: demonstrations carry the true goal, the goal head learns it, the shipped file
    declares the window, an init-actor without it is refused in one line, and evaluate scores the head."""
    import numpy as np
    from assist_lab.evaluate import GOAL_FIELDS, GoalHeadPolicy, make_policy, run_landing
    from assist_lab.td3 import goal_nll
    base = _tiny_run(tmp_path, total_steps=0, buffer_size=20000)
    run = train(TrainArgs(name='mem', history_s=1.0, history_step_s=0.5, history_hidden=8, goal_head=True,
                          demo_episodes=2, demo_noise=0.1, dagger_rounds=1, dagger_episodes=1, bc_steps=200,
                          **base))
    actor, meta = load_actor(run / 'actor_last.pt')
    assert (meta['history_steps'], meta['goal_head'], meta['vec_dim']) == (2, True, 16 + 2 * (3 + 14))
    with np.load(run / 'demos_bc.npz') as d:
        obs, act = d['obs'], d['act']
    # the label's goal is the true goal at that state: what the oracle observes first
    assert act.shape[1] == 6 and np.allclose(act[:, 3:], obs[:, :3], atol=1e-5)
    with torch.no_grad():
        _, head = actor.act_and_goal(torch.as_tensor(obs))
        untrained = TD3(meta['vec_dim'], cfg=TD3Config(hidden=(32, 32), history_hidden=8, goal_head=True),
                        history_steps=2, history_row=3 + 14, seed=5).actor
        _, head0 = untrained.act_and_goal(torch.as_tensor(obs))
    goal = torch.as_tensor(act[:, 3:])
    assert goal_nll(head, goal) < goal_nll(head0, goal) - 1.0                 # the head learned the goal
    with pytest.raises(ValueError, match='history_s 1.0'):                   # a window that does not fit: one line
        train(TrainArgs(name='other', init_actor=str(run / 'actor_last.pt'), history_s=2.0, history_step_s=0.5,
                        history_hidden=8, goal_head=True, demo_episodes=1, **base))
    env, policy = make_policy('oracle', str(run / 'actor_last.pt'), '', 4.0, 0.5)
    assert isinstance(policy, GoalHeadPolicy)
    row = run_landing(env, policy, 11, 0.5)
    assert 0.0 <= row['goal_acc'] <= 1.0 and row['goal_acc_0_1s'] != '' and len(env.goal_trace) > 10
    env2, plain = make_policy('oracle', str(first_plain(tmp_path, base)), '', 4.0, 0.5)
    assert all(run_landing(env2, plain, 11, 0.5)[k] == '' for k in GOAL_FIELDS)


def first_plain(tmp_path, base: dict):
    """An oracle actor without goal head or window (a few cloning steps)."""
    return train(TrainArgs(name='plain', demo_episodes=1, bc_steps=5, **base)) / 'actor_last.pt'


def test_goal_inference_is_scored_per_window_of_time_before_the_landing_ended():
    from assist_lab.evaluate import GOAL_FIELDS, goal_inference
    out = goal_inference([(0.0, True), (7.0, True), (9.5, False), (9.8, True)], 10.0)
    assert out == {'goal_acc': 0.75, 'goal_acc_0_1s': 0.5, 'goal_acc_1_2s': '', 'goal_acc_2_4s': 1.0,
                   'goal_acc_4_8s': ''}
    assert goal_inference([], 10.0) == dict.fromkeys(GOAL_FIELDS, '')


@pytest.mark.parametrize('extra', [{}, {'demo_episodes': 2, 'demo_bc_file': 'demos_bc.npz'},
                                   {'demo_episodes': 2, 'demo_policy': 'init_actor', 'init_actor': 'a.pt'}])
def test_a_goal_head_without_scripted_demonstrations_is_refused_up_front(extra):
    from assist_common.settings import SettingsError
    with pytest.raises(SettingsError, match='--goal-head is cloned from the true goal'):
        TrainArgs(goal_head=True, **extra).check_relations()
    TrainArgs(goal_head=True, demo_episodes=2, total_steps=0).check_relations()
    with pytest.raises(SettingsError, match='add --asymmetric-critic true'):  # a TD3 phase keeps the head on the goal
        TrainArgs(goal_head=True, demo_episodes=2, total_steps=100).check_relations()
    TrainArgs(goal_head=True, demo_episodes=2, total_steps=100, asymmetric_critic=True).check_relations()


def test_an_asymmetric_critic_learns_on_the_privileged_values_stored_beside_each_observation(tmp_path):
    import numpy as np
    from assist_lab.collect import LandingTask, LandingWorker
    from assist_lab.env import PRIVILEGED_DIM
    from assist_lab.td3 import ReplayBuffer
    base = _tiny_run(tmp_path, total_steps=60, buffer_size=2000, demo_episodes=1, bc_steps=5)
    run = train(TrainArgs(name='asym', asymmetric_critic=True, action_rate_weight=0.1, **base))
    state, replay = load_checkpoint(run)
    assert state['agent']['critic']['q1.0.weight'].shape[1] == 16 + PRIVILEGED_DIM + 3
    assert state['agent']['actor']['head.0.weight'].shape[1] == 16             # the actor sees no more than before
    with np.load(replay) as data:
        obs, nxt = data['obs'], data['next_obs']
    assert obs.shape[1] == 16 + PRIVILEGED_DIM and len(obs) == state['buffer_size']
    priv = obs[:, 16:]
    assert np.all(priv[:, 6] == np.float32(0.5)) and np.all((priv[:, 7] >= 0) & (priv[:, 7] <= 1))   # alpha, beta
    np.testing.assert_array_equal(priv[:, :3], obs[:, :3])     # the oracle's feature is the true goal offset
    np.testing.assert_array_equal(obs[1:4, 16:], nxt[:3, 16:])  # a landing's next values are its next step's
    assert json.loads((run / 'config.json').read_text())['td3']['privileged_dim'] == PRIVILEGED_DIM
    # a pool's worker hands the values back with the landing, and the landing fills either kind of buffer
    worker = LandingWorker(json_env(run), 'oracle')
    try:
        landing = worker.fly(LandingTask('td3', 0, 5, noise_seed=(0, 0), random_actions=True), None)
    finally:
        worker.close()
    assert landing.priv.shape == (landing.steps, PRIVILEGED_DIM)
    np.testing.assert_array_equal(landing.priv[1:], landing.next_priv[:-1])
    wide, plain = ReplayBuffer(16, 3, 5000, priv_dim=PRIVILEGED_DIM), ReplayBuffer(16, 3, 5000)
    landing.into(wide)
    landing.into(plain)
    np.testing.assert_array_equal(wide.obs[:landing.steps, :16], plain.obs[:landing.steps])
    np.testing.assert_array_equal(wide.obs[:landing.steps, 16:], landing.priv)


def json_env(run):
    """The EnvConfig a run trained on, from its config.json."""
    from assist_lab.train import env_config_from
    saved = json.loads((run / 'config.json').read_text())['train']
    return env_config_from(TrainArgs(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()}))
