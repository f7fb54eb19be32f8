"""The `_lead` teachers aim where a lagging vehicle will be, not where it is."""
import numpy as np

from assist_lab.collect import demonstrator
from assist_policy.scripted import LEAD_S, ScriptedConfig, ScriptedOracle, make_nearest_pad


def test_a_vehicle_closing_fast_is_braked_before_it_reaches_the_goal():
    goal, pos, vel = np.array([1.0, 0.0, 0.5]), np.array([0.8, 0.0, 2.0]), np.array([1.0, 0.0, 0.0])
    plain = ScriptedOracle().velocity(goal, pos, np.zeros(3), vel)
    lead = ScriptedOracle(ScriptedConfig(lead_s=LEAD_S)).velocity(goal, pos, np.zeros(3), vel)
    assert plain[0] > 0.5                   # aimed at where it is: still pushes on towards the goal
    assert lead[0] < 0.0                    # aimed 0.3 s ahead (1.1 m): brakes
    # at rest, or without a velocity, the lead changes nothing
    assert np.allclose(ScriptedOracle(ScriptedConfig(lead_s=LEAD_S)).velocity(goal, pos, np.zeros(3), np.zeros(3)),
                       ScriptedOracle().velocity(goal, pos, np.zeros(3)))


def test_the_lead_teachers_are_named_demonstrators():
    assert demonstrator('oracle_lead', (1.0, 1.0, 0.6)).cfg.lead_s == LEAD_S
    assert demonstrator('oracle', (1.0, 1.0, 0.6)).cfg.lead_s == 0.0
    t = make_nearest_pad('nearest_pad_commit_lead')
    assert t.cfg.lead_s == LEAD_S and t.cfg.gentle_descent and t.cfg.commit_height_m > 0
    pads = np.array([[1.0, 0.0, 0.5], [5.0, 0.0, 0.5]])
    pos, vel = np.array([0.8, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    assert t.velocity(pads, pos, np.array([0.0, 0.0, -0.5]), None, vel)[0] < 0.0
    assert make_nearest_pad('nearest_pad_commit').velocity(pads, pos, np.array([0.0, 0.0, -0.5]), None, vel)[0] > 0.0
