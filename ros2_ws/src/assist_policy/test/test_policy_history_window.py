"""The history window: the flight's recent steps as actor inputs, read by the actor's GRU, declared in its metadata."""
import numpy as np
import pytest
import torch

from assist_policy.actor import Actor, build_actor, load_actor, save_actor, validate_actor_meta
from assist_policy.observation import (DISPLACEMENT_CLIP_M, HISTORY_EXTRA_DIM, Condition, HistoryWindow,
                                       ObservationBuilder, history_steps, vector_dim)
from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
from assist_policy.recall import MappedPad

LATENT = 2


def fly(window: HistoryWindow, t: float, x: float) -> np.ndarray:
    """One 10 Hz step at time t: feature (t, -t), vehicle at (x, 0, 2) moving 1 m/s in x, pilot u = (t, 0, 0)."""
    out = window.window(t, np.array([t, -t]), np.array([1.0, 0, 0]), 2.0, np.array([t, 0, 0]), np.array([x, 0, 2.0]))
    window.applied(t, np.array([0, 0, -t]))
    return out


def test_rows_are_the_steps_sampled_back_from_now_oldest_first():
    w = HistoryWindow(LATENT, history_s=1.0, step_s=0.5)
    assert (w.steps, w.row_dim) == (2, LATENT + HISTORY_EXTRA_DIM)
    out = None
    for k in range(31):                   # 3 s at 10 Hz; the vehicle at x = t
        out = fly(w, k * 0.1, k * 0.1)
    rows = out.reshape(2, -1)
    # now = 3.0: rows at 2.0 (oldest) and 2.5: [feature, v, z/4, u, applied a, p_now - p_then, valid]
    np.testing.assert_allclose(rows[0], [2.0, -2.0, 1, 0, 0, 0.5, 2.0, 0, 0, 0, 0, -2.0, 1.0, 0, 0, 1.0], atol=1e-6)
    np.testing.assert_allclose(rows[1], [2.5, -2.5, 1, 0, 0, 0.5, 2.5, 0, 0, 0, 0, -2.5, 0.5, 0, 0, 1.0], atol=1e-6)


def test_a_young_flight_has_invalid_zero_rows_and_a_clock_reset_forgets():
    w = HistoryWindow(LATENT, history_s=1.0, step_s=0.5)
    assert not fly(w, 0.0, 0.0).any()                    # nothing before the first step
    rows = fly(w, 0.6, 0.6).reshape(2, -1)
    assert not rows[0].any() and rows[1, -1] == 1.0 and rows[1, 0] == 0.0   # 0.1 s: the step at t = 0 only
    assert not fly(w, 0.0, 5.0).any()                    # clock went back (new episode): forgotten


def test_a_gap_in_the_steps_leaves_invalid_rows_not_stale_ones():
    w = HistoryWindow(LATENT, history_s=2.0, step_s=0.5)
    for k in range(11):                       # 0 .. 1.0 s at 10 Hz, then nothing until 3.0 s (inputs stalled)
        fly(w, k * 0.1, 0.0)
    rows = fly(w, 3.0, 0.0).reshape(4, -1)    # rows at 1.0, 1.5, 2.0, 2.5: only 1.0 has a step within 0.5 s
    assert rows[0, -1] == 1.0 and rows[0, 0] == pytest.approx(1.0)
    assert not rows[1:].any()


def test_displacement_is_clipped_and_bad_inputs_refused():
    w = HistoryWindow(LATENT, history_s=0.5, step_s=0.5)
    fly(w, 0.0, 0.0)
    rows = fly(w, 0.5, 100.0).reshape(1, -1)
    assert rows[0, LATENT + 10] == DISPLACEMENT_CLIP_M
    with pytest.raises(ValueError, match='non-finite time'):
        fly(w, float('nan'), 0.0)
    with pytest.raises(ValueError, match='non-finite position'):
        fly(w, 1.0, float('inf'))


@pytest.mark.parametrize('history_s, step_s, match', [(1.0, 0.0, 'step'), (100.0, 0.1, '1000 rows')])
def test_window_settings_out_of_range_are_refused(history_s, step_s, match):
    with pytest.raises(ValueError, match=match):
        history_steps(history_s, step_s)


def test_a_flight_boundary_forgets_the_window():
    b = ObservationBuilder(Condition.LATENT, LATENT, history_s=0.5, history_step_s=0.5)
    assert b.dim == vector_dim('latent', LATENT, n_history=1) == vector_dim('latent', LATENT) + LATENT + 14
    args = (np.ones(LATENT), np.zeros(3), 2.0, np.zeros(3), np.zeros(3))
    b.build(0.0, *args)
    assert b.build(0.5, *args)[-1] == 1.0
    b.reset()                                            # what AssistLoop.forget does at a boundary
    assert b.build(1.0, *args)[-1] == 0.0


def history_meta(**extra) -> dict:
    steps = history_steps(1.0, 0.5)
    return {'vec_dim': vector_dim('latent', LATENT, n_history=steps), 'act_dim': 3, 'hidden': [8], 'image': False,
            'condition': 'latent', 'latent_dim': LATENT, 'history_s': 1.0, 'history_step_s': 0.5,
            'history_hidden': 6, **extra}


def test_a_history_actor_saves_loads_and_reads_its_window(tmp_path):
    meta = validate_actor_meta(history_meta(goal_head=True))
    actor = build_actor(meta)
    save_actor(actor, meta, tmp_path / 'a.pt')
    loaded, got = load_actor(tmp_path / 'a.pt')
    assert (got['history_steps'], got['history_row'], got['goal_head']) == (2, LATENT + 14, True)
    obs = torch.randn(5, meta['vec_dim'])
    torch.testing.assert_close(loaded(obs), actor(obs))
    changed = obs.clone()
    changed[:, -3] += 1.0                                # a displacement in the oldest-but-newest row
    assert not torch.allclose(loaded(changed), loaded(obs))
    action, goal = loaded.act_and_goal(obs)
    assert action.shape == (5, 3) and goal.shape == (5, 4)


@pytest.mark.parametrize('change, match', [
    ({'history_s': 2.0}, '4 history rows'),                   # the window does not fit vec_dim
    ({'history_s': 5.0, 'history_step_s': 0.01}, 'history: a history of 5 s'),
    ({'goal_head': 'yes'}, 'goal_head'),
    ({'condition': 'end_to_end', 'image': True}, 'history_s'),
])
def test_history_metadata_that_does_not_fit_is_one_line(change, match):
    with pytest.raises(ValueError, match=match) as info:
        validate_actor_meta(history_meta(**change))
    assert '\n' not in str(info.value)


def test_weights_without_the_window_s_gru_are_refused(tmp_path):
    meta = validate_actor_meta(history_meta())
    plain = Actor(meta['vec_dim'], 3, hidden=(8,))      # no GRU: weights that do not match the metadata
    save_actor(plain, meta, tmp_path / 'bad.pt')
    with pytest.raises(ValueError, match='weights do not match'):
        load_actor(tmp_path / 'bad.pt')


def test_policy_core_builds_the_window_and_publishes_the_goal_head_s_estimate(tmp_path):
    meta = validate_actor_meta(history_meta(goal_head=True))
    actor = build_actor(meta)
    with torch.no_grad():
        for prm in actor.parameters():
            prm.zero_()
        actor.goal_head.bias.copy_(torch.tensor([0.5, 0.0, -0.25, np.log(0.25)]))   # 2 m ahead in x, 1 m down, sd 1 m
    save_actor(actor, meta, tmp_path / 'a.pt')
    core = PolicyCore(tmp_path / 'a.pt', PolicyCoreConfig(mode='latent'))
    assert core.builder.window.steps == 2 and core.builder.dim == meta['vec_dim']
    core.set_odom(1.0, [1, 0, 2], [0, 0, 0])
    core.set_pilot(1.0, [0, 1, 0])
    core.set_latent(1.0, np.zeros(LATENT))
    assert core.step(1.0).intent.goal is None                 # no pad mapped yet (no depth image): no estimate
    recall = core.assistant.recall                            # pads mapped near (3, 0) and at (7, 0)
    recall.map.pads[:] = [MappedPad(np.array([3.2, 0.0, 0.8]), True, 100),
                          MappedPad(np.array([7.0, 0.0, 0.8]), True, 100)]
    out = core.step(1.05)
    np.testing.assert_allclose(out.intent.goal, [3.2, 0.0, 0.8])     # the head's mean is (3, 0, 1), sd 1 m
    assert out.intent.confidence > 0.99
