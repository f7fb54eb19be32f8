"""The goal-gated commit teacher: the commit teacher over the goal pad, nothing over any other."""
import numpy as np
import pytest

from assist_policy.scripted import make_nearest_pad

PADS = np.array([[0.0, 0.0, 0.5], [4.0, 0.0, 0.5]])
OVER_A = np.array([0.1, 0.0, 1.0])          # 0.5 m over pad A, 0.1 m off its centre
DESCENDING = np.array([0.0, 0.0, -0.5])


def test_it_helps_over_the_goal_pad_as_the_commit_teacher_does():
    gated, commit = make_nearest_pad('nearest_pad_goal_commit'), make_nearest_pad('nearest_pad_commit')
    helped = gated.velocity(PADS, OVER_A, DESCENDING, goal=PADS[0])
    np.testing.assert_array_equal(helped, commit.velocity(PADS, OVER_A, DESCENDING))
    assert helped[0] < 0                                 # centring on A


def test_it_relinquishes_over_any_other_pad_and_needs_the_goal():
    gated = make_nearest_pad('nearest_pad_goal_commit')
    np.testing.assert_array_equal(gated.velocity(PADS, OVER_A, DESCENDING, goal=PADS[1]), np.zeros(3))
    with pytest.raises(ValueError, match='needs the goal'):
        gated.velocity(PADS, OVER_A, DESCENDING)
