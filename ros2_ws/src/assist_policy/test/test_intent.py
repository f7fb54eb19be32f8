"""The assistant's intent: the goal belief over mapped pads follows the command, and the descent flag."""
import numpy as np
import pytest

from assist_common.settings import SettingsError
from assist_policy.intent import ROTATION_VARIANCE, IntentConfig, IntentEstimator, LearnedGoal
from assist_policy.recall import MappedPad, PadRecall, RecallConfig
from assist_policy.stage import DepthFrame, StepContext

DT = 0.05
PAD_A = np.array([0.0, 0.0, 0.8])
PAD_B = np.array([4.0, 0.0, 0.6])
CAMERA_OFFSET = 0.05


def estimator(**cfg) -> IntentEstimator:
    recall = PadRecall(RecallConfig())
    recall.map.pads[:] = [MappedPad(PAD_A.copy(), True, 200), MappedPad(PAD_B.copy(), False, 80)]
    return IntentEstimator(IntentConfig(**cfg), recall)


def ctx(t: float, position, velocity=(0.0, 0.0, 0.0), depth: np.ndarray | None = None) -> StepContext:
    p = np.asarray(position, dtype=float)
    frame = None if depth is None else DepthFrame(t, lambda: depth, lambda: (p, None))
    return StepContext(t, np.zeros(3), np.zeros(3), p, np.asarray(velocity, dtype=float), None, frame,
                       (1.0, 1.0, 1.0))


def fly(est: IntentEstimator, t0: float, seconds: float, position, command):
    """Steps of a constant command from a fixed position; the last intent."""
    out = None
    for k in range(int(round(seconds / DT))):
        out = est.update(ctx(t0 + k * DT, position), np.asarray(command, dtype=float))
    return out


def test_the_estimate_is_the_pad_the_command_leads_to_and_switches_when_it_turns():
    est = estimator()
    toward_b = fly(est, 0.0, 3.0, (1.5, 0.0, 3.0), (1.0, 0.0, 0.0))
    assert toward_b.index == 1
    np.testing.assert_array_equal(toward_b.goal, PAD_B)
    assert toward_b.confidence > 0.95
    # seen only in part: its centre's own uncertainty is the wider one; the other pad adds almost nothing
    assert 0.3 ** 2 <= toward_b.covariance[0, 0] < 0.3 ** 2 + 0.05
    turned = fly(est, 3.0, 0.2, (1.5, 0.0, 3.0), (-1.0, 0.0, 0.0))
    assert turned.index == 1 and turned.confidence < toward_b.confidence    # one step does not flip it
    toward_a = fly(est, 3.2, 3.0, (1.5, 0.0, 3.0), (-1.0, 0.0, 0.0))
    assert toward_a.index == 0 and toward_a.confidence > 0.95
    np.testing.assert_array_equal(toward_a.goal, PAD_A)
    assert toward_a.covariance[0, 0] < 0.1 ** 2 + 0.05


def test_a_command_between_two_pads_spreads_the_covariance_over_both():
    est = estimator()
    out = fly(est, 0.0, 3.0, (2.0, 0.0, 3.0), (0.0, 0.0, 0.0))     # hovering half way: no pad stands out
    assert 0.4 < out.confidence < 0.6
    assert out.covariance[0, 0] > 3.0                            # ~ 0.25 x 4 m squared: the two pads apart
    assert out.covariance[1, 1] < 0.1                            # they stand in a row along x
    cov6 = out.pose_covariance()
    assert len(cov6) == 36 and cov6[0] == out.covariance[0, 0] and cov6[35] == ROTATION_VARIANCE


def test_no_mapped_pad_no_estimate_and_a_known_goal_is_the_estimate():
    est = IntentEstimator(IntentConfig(), PadRecall(RecallConfig()))
    out = est.update(ctx(0.0, (0.0, 0.0, 3.0)), np.array([1.0, 0.0, 0.0]))
    assert out.goal is None and out.confidence == 0.0
    goal = np.array([7.0, -1.0, 0.4])
    known = est.update(ctx(0.05, (0.0, 0.0, 3.0)), np.array([-1.0, 0.0, 0.0]), known_goal=goal)
    np.testing.assert_array_equal(known.goal, goal)
    assert known.confidence == 1.0 and known.covariance[0, 0] < 1e-3


def test_not_assisting_reports_no_goal_and_reset_forgets_the_belief():
    est = estimator()
    fly(est, 0.0, 3.0, (1.5, 0.0, 3.0), (1.0, 0.0, 0.0))
    quiet = est.update(ctx(3.0, (1.5, 0.0, 3.0)), np.array([1.0, 0.0, 0.0]), assisting=False)
    assert quiet.goal is None and quiet.candidates == 2
    est.reset()
    assert est.last.goal is None
    # after the reset the belief starts afresh: one step toward A decides it at once
    out = est.update(ctx(10.0, (1.5, 0.0, 3.0)), np.array([-1.0, 0.0, 0.0]))
    assert out.index == 0


def test_switched_off_estimates_nothing():
    est = estimator(enabled=False)
    out = fly(est, 0.0, 1.0, (1.5, 0.0, 3.0), (1.0, 0.0, 0.0))
    assert out.goal is None and out.descent_ok is None


def depth_over(altitude: float, surface_top: float, shape=(64, 64)) -> np.ndarray:
    """A downward depth image of a flat surface `surface_top` over the floor, seen from `altitude`."""
    return np.full(shape, altitude - CAMERA_OFFSET - surface_top, dtype=np.float32)


def test_descent_ok_over_the_estimated_pad_only():
    est = estimator()
    over_a = (0.1, 0.0, 2.5)
    fly(est, 0.0, 2.0, over_a, (0.0, 0.0, -0.5))
    on_pad = est.update(ctx(2.0, over_a, depth=depth_over(2.5, 0.8)), np.array([0.0, 0.0, -0.5]))
    assert on_pad.index == 0 and on_pad.descent_ok is True
    floor = est.update(ctx(2.05, over_a, depth=depth_over(2.5, 0.0)), np.array([0.0, 0.0, -0.5]))
    assert floor.descent_ok is False                             # the legs over the floor
    drifting = est.update(ctx(2.1, over_a, velocity=(0.9, 0.0, 0.0), depth=depth_over(2.5, 0.8)),
                          np.array([0.0, 0.0, -0.5]))
    assert drifting.descent_ok is False                          # sliding across it
    edge = depth_over(2.5, 0.8)
    edge[:, :32] = 2.5 - CAMERA_OFFSET                           # half the image shows the floor: legs straddle
    assert est.update(ctx(2.15, over_a, depth=edge), np.zeros(3)).descent_ok is False
    holes = np.zeros((64, 64), dtype=np.float32)
    assert est.update(ctx(2.2, over_a, depth=holes), np.zeros(3)).descent_ok is None
    assert est.update(ctx(2.25, over_a), np.zeros(3)).descent_ok is None          # no fresh frame
    # over the other pad (not the estimate): not here
    far = estimator()
    fly(far, 0.0, 2.0, (1.0, 0.0, 2.5), (-1.0, 0.0, 0.0))        # the command leads to A
    assert far.update(ctx(2.0, (3.9, 0.0, 2.5), depth=depth_over(2.5, 0.6)),
                      np.array([-1.0, 0.0, 0.0])).descent_ok is False


def test_settings_out_of_range_are_refused():
    with pytest.raises(SettingsError, match='spread_m'):
        IntentConfig(spread_m=0.0)
    with pytest.raises(SettingsError, match='memory_s'):
        IntentConfig(memory_s=-1.0)


def test_the_policy_core_reports_the_intent_it_publishes_and_changes_its_settings_at_run_time(tmp_path):
    from assist_policy.policy_core import PolicyCore, PolicyCoreConfig
    from assist_policy.testing import constant_actor
    core = PolicyCore(constant_actor(tmp_path / 'a.pt', [0.5, 0.0, 0.0], condition='oracle', latent_dim=0),
                      PolicyCoreConfig(mode='oracle'))
    goal = np.array([6.0, 1.0, 0.8])
    core.set_goal(goal)
    core.set_odom(0.0, [0.0, 0.0, 3.0], [0.0, 0.0, 0.0])
    core.set_pilot(0.0, [1.0, 0.0, 0.0])
    out = core.step(0.05)
    assert out.key == 'assisting'
    np.testing.assert_array_equal(out.intent.goal, goal)           # the oracle's intent is the goal it is given
    assert out.intent.descent_ok is None                           # no depth frame yet: unknown
    core.configure(intent={'spread_m': 0.4, 'memory_s': 2.0})
    assert core.loop.intent.cfg.spread_m == 0.4 and core.cfg.intent.memory_s == 2.0
    with pytest.raises(ValueError, match='spread_m'):
        core.configure(intent={'spread_m': 0.0})
    assert core.loop.intent.cfg.spread_m == 0.4                     # refused: nothing changed
    core.configure(intent={'enabled': False})
    assert core.step(0.1).intent.goal is None
    assert core.pass_through(0.15).intent.goal is None             # switched off: no intent at all


def test_the_belief_starts_afresh_when_the_recall_is_switched_and_its_map_no_longer_serves():
    est = estimator()
    fly(est, 0.0, 2.0, (1.5, 0.0, 3.0), (1.0, 0.0, 0.0))
    assert est.last.index == 1
    est.recall.cfg.enabled = False          # the recall's map no longer serves; the own map has seen nothing
    out = est.update(ctx(2.0, (1.5, 0.0, 3.0)), np.array([1.0, 0.0, 0.0]))
    assert out.goal is None and out.candidates == 0
    est.recall.cfg.enabled = True           # back: a fresh belief over the recall's two pads
    out = est.update(ctx(2.05, (1.5, 0.0, 3.0)), np.array([-1.0, 0.0, 0.0]))
    assert out.index == 0 and out.candidates == 2


def test_the_horizontal_sigma_is_the_wider_axis_of_the_covariance():
    out = fly(estimator(), 0.0, 3.0, (2.0, 0.0, 3.0), (0.0, 0.0, 0.0))
    assert out.sigma_xy_m == pytest.approx(np.sqrt(out.covariance[0, 0]))      # the pads stand in a row along x
    assert estimator().last.sigma_xy_m == np.inf                                # no estimate


def test_a_goal_head_s_estimate_weighs_the_mapped_pads_whatever_the_command():
    est = estimator()
    fly(est, 0.0, 3.0, (1.5, 0.0, 3.0), (1.0, 0.0, 0.0))           # the command leads to B
    # the head puts the goal near A (sd 1 m): A is the estimate, the command notwithstanding
    near_a = LearnedGoal(np.array([0.5, 0, 0]), 1.0)
    out = est.update(ctx(3.0, (1.5, 0.0, 3.0)), np.array([1.0, 0.0, 0.0]), learned=near_a)
    assert out.index == 0 and out.confidence == pytest.approx(1 / (1 + np.exp(-(3.5 ** 2 - 0.5 ** 2) / 2)))
    np.testing.assert_array_equal(out.goal, PAD_A)
    # unsure (sd 4 m) half way: split between the two
    out = est.update(ctx(3.05, (1.5, 0.0, 3.0)), np.zeros(3), learned=LearnedGoal(np.array([2.0, 0, 0]), 4.0))
    assert out.confidence == pytest.approx(0.5)
    # nothing mapped: no estimate (the goal estimate is a pad's centre)
    bare = IntentEstimator(IntentConfig(), PadRecall(RecallConfig()))
    out = bare.update(ctx(0.0, (0.0, 0.0, 3.0)), np.zeros(3), learned=LearnedGoal(np.array([9.0, 1.0, 0.5]), 0.5))
    assert out.goal is None and out.confidence == 0.0
