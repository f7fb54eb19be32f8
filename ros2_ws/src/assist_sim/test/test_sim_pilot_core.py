"""Simulated pilot core on a fake world state (kinematic integration of its own commands)."""
import numpy as np
import pytest

from assist_sim.pilot import PilotConfig, SimulatedPilot

GOAL = np.array([12.0, 0.5, 0.8])
START = np.array([0.0, 0.0, 3.5])


def fly(pilot, steps=2000, agent=None):
    """Integrate the pilot's commands as velocities (perfect tracking) until it is down on the goal height."""
    p = START.copy()
    dt = 1.0 / pilot.cfg.control_hz
    cmds = []
    for _ in range(steps):
        u = pilot.act(p, agent)
        cmds.append(u)
        p = p + u * dt
        if p[2] <= GOAL[2]:
            break
    return p, np.array(cmds)


def test_paper_update_equation_exact():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    pilot = SimulatedPilot(alpha=0.5, beta=0.4, cfg=cfg, rng=0)
    g0 = GOAL + np.array([2.0, 0.0, 0.0])
    pilot.reset(GOAL, START, goal_estimate=g0)
    a = np.array([0.0, 1.0, 0.0])
    g1 = pilot.update_estimate(a)
    expected = g0 + 0.5 * a / cfg.k_alpha + 0.4 * (GOAL - g0) / cfg.k_beta
    np.testing.assert_allclose(g1, expected)


def test_initial_estimate_wrong_mostly_in_depth_and_grows_with_range():
    pilot = SimulatedPilot(0.5, 0.5, rng=1)
    near = np.array([pilot.initial_estimate(np.array([4.0, 0, 1]), START) - [4.0, 0, 1] for _ in range(400)])
    far = np.array([pilot.initial_estimate(np.array([20.0, 0, 1]), START) - [20.0, 0, 1] for _ in range(400)])
    assert np.abs(far[:, 0]).mean() > 3 * np.abs(far[:, 1]).mean()
    assert np.abs(far[:, 0]).mean() > 4 * np.abs(near[:, 0]).mean()
    assert np.abs(far[:, 0]).max() > 3.0          # far pads: confused with the adjacent one (~4 m away)
    assert (far[:, 0] > 0).mean() == pytest.approx(0.5, abs=0.1)
    np.testing.assert_allclose(far[:, 2], 0.0)


def test_expert_lands_near_goal_novice_keeps_its_error():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    wrong = GOAL + np.array([3.0, 0.0, 0.0])
    expert = SimulatedPilot(0.5, 1.0, cfg, rng=2)
    expert.reset(GOAL, START, goal_estimate=wrong)
    p_e, _ = fly(expert)
    novice = SimulatedPilot(0.5, 0.0, cfg, rng=2)
    novice.reset(GOAL, START, goal_estimate=wrong)
    p_n, _ = fly(novice)
    assert p_e[2] <= GOAL[2] and p_n[2] <= GOAL[2]          # both descended to the goal height
    # tau_beta = 12 s and a ~17 s flight: an expert removes ~75% of a 3 m depth error
    assert np.linalg.norm(p_e[:2] - GOAL[:2]) < 1.0
    assert np.linalg.norm(p_n[:2] - GOAL[:2]) > 2.7
    assert np.linalg.norm(p_n[:2] - wrong[:2]) < 0.3        # beta = 0: lands where it believed


def test_assistant_action_pulls_estimate_with_conformance():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    wrong = GOAL + np.array([3.0, 0.0, 0.0])
    pilot = SimulatedPilot(alpha=1.0, beta=0.0, cfg=cfg, rng=3)
    pilot.reset(GOAL, START, goal_estimate=wrong)
    for _ in range(int(3.0 * cfg.control_hz)):        # 3 s of a = -1 m/s along x
        pilot.update_estimate(np.array([-1.0, 0.0, 0.0]))
    np.testing.assert_allclose(pilot.goal_estimate, GOAL, atol=1e-9)


def test_keyboard_commands_discrete_and_descent_only_over_goal():
    pilot = SimulatedPilot(0.5, 0.3, PilotConfig(perception_sigma_m=(0.0, 0.0)), rng=4)
    pilot.reset(GOAL, START, goal_estimate=GOAL)
    _, cmds = fly(pilot)
    c = pilot.cfg
    assert set(np.unique(cmds[:, 0])) <= {-c.speed_xy_mps, 0.0, c.speed_xy_mps}
    assert set(np.unique(cmds[:, 2])) <= {-c.speed_down_mps, 0.0, c.speed_up_mps}
    first_descent = int(np.argmax(cmds[:, 2] < 0))
    # it crossed ~12 m at <= 1 m/s before descending
    assert first_descent * (1.0 / c.control_hz) > 10.0


def test_novices_tap_experts_hold():
    cfg = PilotConfig(perception_sigma_m=(0.0, 0.0))
    far = np.array([30.0, 0.0, 0.8])
    duty = {}
    for beta in (0.0, 1.0):
        pilot = SimulatedPilot(0.5, beta, cfg, rng=5)
        pilot.reset(far, START, goal_estimate=far)
        cmds = np.array([pilot.command(START) for _ in range(80)])
        duty[beta] = float(np.mean(cmds[:, 0] != 0))
    assert duty[0.0] == pytest.approx(0.5, abs=0.05)
    assert duty[1.0] == 1.0


def test_bad_parameters_rejected():
    with pytest.raises(ValueError):
        SimulatedPilot(alpha=1.5, beta=0.5)
