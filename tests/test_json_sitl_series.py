"""Landing series on ArduPilot SITL, without SITL: sim_node's JSON runner follows an evaluation plan's scene
seeds counted by landings (SITL stand-in), and evaluate_graph --autopilot sitl's node set, parameters and SITL
command line."""
from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from assist_lab.episodes_plan import evaluation_plans
from assist_lab.evaluate import rules_flying
from assist_lab.graph_eval import (GraphEvalArgs, check_sitl_args, node_params, runner_verdict, sitl_command,
                                      sitl_ports)
from assist_sim.core.config import WorldConfig
from assist_sim.core.runner import RunnerConfig
from assist_sim.core.world import LandingWorld
from assist_sim.json_backend import JsonBackendConfig, JsonSimRunner
from assist_sim.testing_sitl import SitlStandIn
from assist_common.domains import private_domain_id

RATE = 400
SEEDS = (101, 202, 303)


def _scene_of(seed: int) -> tuple[int, np.ndarray]:
    """(goal index, pad top centres) of scene `seed` in a world of its own."""
    world = LandingWorld(WorldConfig(), seed=0)
    try:
        world.reset(seed, start_position=(0.0, 0.0, 0.0), airborne=False)
        return world.goal_index, world.scene.pad_top_centers.copy()
    finally:
        world.close()


@pytest.fixture
def series():
    world = LandingWorld(WorldConfig(), seed=5)
    runner = JsonSimRunner(world, RunnerConfig(airborne_start=False, camera_rate_hz=0.0, episode_seeds=SEEDS),
                           JsonBackendConfig(port=0), seed=5)
    runner.reset()
    outs, stop = [], threading.Event()

    def serve():
        while not stop.is_set():
            outs.append(runner.step())
    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    sitl = SitlStandIn(port=runner.server.address[1], frame_rate=RATE)
    yield runner, world, sitl, outs
    stop.set()
    thread.join(timeout=5)
    sitl.close()
    runner.close()
    world.close()


def _until(sitl: SitlStandIn, outs: list, pwm, what, max_frames: int = 4 * RATE):
    """Exchange frames at `pwm` until `what(outs)` holds (the runner reports at the end of its control period)."""
    for _ in range(max_frames):
        sitl.exchange(pwm)
        if what(outs):
            return
    raise AssertionError('the runner never reported it')


def _assert_scene(world: LandingWorld, seed: int) -> None:
    goal, pads = _scene_of(seed)
    assert world.goal_index == goal
    np.testing.assert_allclose(world.scene.pad_top_centers, pads)


def test_json_episodes_follow_episode_seeds_counted_by_landings_not_sitl_restarts(series):
    runner, world, sitl, outs = series
    _assert_scene(world, SEEDS[0])
    assert world.episode == 0
    for _ in range(20):
        sitl.exchange([1000] * 4)
    # a SITL restart on the ground (a reboot, a refused arming): the same episode, the same scene again
    sitl.restart()
    _until(sitl, outs, [1000] * 4, lambda o: any(x.new_episode for x in o))
    assert world.episode == 0 and runner.episodes_finished == 0
    _assert_scene(world, SEEDS[0])
    # climb straight up (four equal motors) past the judge's arm height, then SITL restarts in flight
    s = None
    for _ in range(2 * RATE):
        s = sitl.exchange([1700] * 4)
        if s['position'][2] < -1.0:
            break
    assert s['position'][2] < -1.0
    n = len(outs)
    sitl.restart()
    _until(sitl, outs, [1000] * 4, lambda o: any(x.landing is not None for x in o[n:]))
    landings = [x.landing for x in outs if x.landing is not None]
    assert len(landings) == 1
    assert (landings[0].episode, landings[0].outcome, landings[0].reason) == (0, 'timeout', 'SITL restarted in flight')
    # the landing counted: episode 1 in the plan's second scene, landed at the start spot
    assert world.episode == 1 and runner.episodes_finished == 1
    _assert_scene(world, SEEDS[1])
    s = sitl.exchange([1000] * 4)
    np.testing.assert_allclose(s['position'], [0.0, 0.0, -world.cfg.vehicle.leg_length_m], atol=0.01)
    # and a restart on the ground again keeps it
    n = len(outs)
    sitl.restart()
    _until(sitl, outs, [1000] * 4, lambda o: any(x.new_episode for x in o[n:]))
    assert world.episode == 1
    _assert_scene(world, SEEDS[1])
    assert runner.server.counters['sitl_restarts'] == 3


def _plans(n: int = 3):
    return [p for _, p in evaluation_plans(11, (0.5,), n, 'paper', 0.5)]


def test_sitl_graph_nodes_and_parameters_follow_the_plan_and_instance():
    plans = _plans()
    args = GraphEvalArgs(autopilot='sitl', sitl_instance=1, conditions=('latent',))
    on = rules_flying(GraphEvalArgs(override=False, recall=False, damper=False), 'latent')
    params = node_params(args, 'latent', plans, on, runner_results='/runs/x/landing_runner.csv')
    assert set(params) == {'sim_node', 'mavlink_bridge_node', 'landing_runner', 'sim_pilot_node', 'encoder_node',
                           'policy_node'}
    sim = params['sim_node']
    assert sim['physics'] == 'ardupilot_json' and sim['json_port'] == 9012
    assert sim['episode_seeds'] == [p.scene_seed for p in plans]
    assert 'real_time_factor' not in sim and 'flight_controller' not in sim   # SITL sets the pace; autopilot real
    assert params['mavlink_bridge_node'] == {'use_sim_time': True, 'allow_force_disarm': True,
                                             'connection': 'tcp:127.0.0.1:5770'}
    assert params['landing_runner'] == {'episodes': 3, 'reboot_after_crash': True,
                                        'results_file': '/runs/x/landing_runner.csv'}
    pilot = params['sim_pilot_node']
    assert pilot['start_altitude_m'] == 1.5
    assert pilot['episode_seeds'] == [p.pilot_seed for p in plans]
    assert params['encoder_node']['level_camera'] is True
    assert params['policy_node']['mode'] == 'latent'
    assert {k: params['policy_node'][k] for k in ('floor_guard', 'pilot_override', 'pad_recall',
                                                  'oscillation_damper')} == {
        'floor_guard': True, 'pilot_override': False, 'pad_recall': False, 'oscillation_damper': False}

    unassisted = node_params(args, 'unassisted', plans, on)
    assert set(unassisted) == {'sim_node', 'mavlink_bridge_node', 'landing_runner', 'sim_pilot_node'}
    assert unassisted['sim_node']['camera_rate_hz'] == 0.0

    connected = node_params(GraphEvalArgs(autopilot='sitl', sitl_connection='tcp:127.0.0.1:5800'), 'oracle', plans, on)
    assert connected['mavlink_bridge_node']['connection'] == 'tcp:127.0.0.1:5800'
    assert connected['sim_node']['json_port'] == 9002

    plain = node_params(GraphEvalArgs(), 'oracle', plans, on)           # --autopilot none: as before
    assert set(plain) == {'sim_node', 'sim_pilot_node', 'policy_node'}
    assert 'physics' not in plain['sim_node'] and 'start_altitude_m' not in plain['sim_pilot_node']


def test_sitl_ports_follow_arducopter_instance_offsets():
    # AP_HAL_SITL/SITL_cmdline.cpp: -I N adds 10 N to SERIAL0 (5760) and SIM_OUT_PORT (9002)
    assert sitl_ports(0) == (5760, 9002)
    assert sitl_ports(1) == (5770, 9012)
    assert sitl_ports(3) == (5790, 9032)


def test_sitl_command_line_and_bad_binary(tmp_path):
    ap = tmp_path / 'ardupilot'
    binary = ap / 'build' / 'sitl' / 'bin' / 'arducopter'
    binary.parent.mkdir(parents=True)
    binary.write_text('#!/bin/sh\n')
    binary.chmod(0o755)
    copter = ap / 'Tools' / 'autotest' / 'default_params' / 'copter.parm'
    copter.parent.mkdir(parents=True)
    copter.write_text('FRAME_CLASS 1\n')
    cmd = sitl_command(GraphEvalArgs(autopilot='sitl', sitl_binary=str(binary), sitl_instance=1, sitl_speedup=4.0))
    assert cmd[0] == str(binary.resolve())
    assert cmd[cmd.index('--model') + 1] == 'JSON:127.0.0.1'
    assert cmd[cmd.index('--speedup') + 1] == '4'
    assert '-I1' in cmd and '--wipe' in cmd
    defaults = cmd[cmd.index('--defaults') + 1].split(',')
    assert defaults[0] == str(copter.resolve()) and defaults[1].endswith('config/ardupilot_json_quad.parm')
    assert os.path.isfile(defaults[1])
    with pytest.raises(ValueError, match='--sitl-binary'):
        check_sitl_args(GraphEvalArgs(autopilot='sitl', sitl_binary=str(tmp_path / 'nope')))
    with pytest.raises(ValueError, match='flight-controller'):
        check_sitl_args(GraphEvalArgs(autopilot='sitl', sitl_binary=str(binary), flight_controller='arducopter'))
    check_sitl_args(GraphEvalArgs(flight_controller='arducopter'))     # --autopilot none: nothing to check


def test_runner_verdict_reads_the_landing_runner_results_file(tmp_path):
    path = tmp_path / 'landing_runner.csv'
    path.write_text('episode,goal_index,outcome,autopilot_landed\n0,2,success,True\n1,1,timeout,\n2,0,edge,False\n',
                    encoding='utf-8')
    assert runner_verdict(path, 0, 0.0) is True
    assert runner_verdict(path, 1, 0.0) == ''
    assert runner_verdict(path, 2, 0.0) is False
    assert runner_verdict(path, 3, 0.3) == ''                    # no row (yet): no verdict after the wait
    old = tmp_path / 'old.csv'                                   # a runner without the column
    old.write_text('episode,goal_index,outcome\n0,2,success\n', encoding='utf-8')
    assert runner_verdict(old, 0, 0.0) == ''


def _row(name: str, seed: int, plan) -> dict:
    return {'condition': name, 'beta': float(plan.beta), 'seed': seed, 'scene_seed': plan.scene_seed, 'goal_index': 0,
            'landed_index': 0, 'nearest_index': 0, 'aimed_index': 0, 'error_m': 0.1, 'nearest_error_m': 0.1,
            'outcome': 'success', 'success': True, 'crash': False, 'duration_s': 20.0, 'active_fraction': 0.0,
            'pilot': 'paper', 'guard_fraction': 0.0, 'override_fraction': 0.0, 'recall_fraction': 0.0,
            'damper_fraction': 0.0, 'wall_fraction': 0.0, 'autopilot_landed': True}


@pytest.mark.parametrize('autopilot', ['sitl', 'none'])
def test_a_graph_that_fails_mid_series_is_started_afresh_for_the_missing_landings_with_sitl(
        tmp_path, monkeypatch, autopilot):
    import assist_lab.graph_eval as graph_eval
    calls = []

    def fake_fly(args, cond, name, on, todo, domain_id, log_dir, results, rows):
        calls.append([seed for seed, _ in todo])
        for k, (seed, plan) in enumerate(todo):
            if len(calls) == 1 and k == 1:       # SITL went silent during the second landing
                raise graph_eval.GraphError('no landing 1 within 300 s (wall)')
            row = _row(name, seed, plan)
            results.write(row)
            rows.append(row)
        return rows
    monkeypatch.setattr(graph_eval, 'fly_condition', fake_fly)
    monkeypatch.setattr(graph_eval, 'check_sitl_args', lambda args: None)
    args = GraphEvalArgs(out=str(tmp_path / 'eval'), autopilot=autopilot, conditions=('unassisted',), betas=(0.5,),
                         landings=3, seed=11, domain_id=private_domain_id(), plot=False, sitl_restarts=1)
    if autopilot == 'none':                      # the simulator's graph does not stall: an error ends the run
        with pytest.raises(graph_eval.GraphError):
            graph_eval.evaluate_graph(args)
        assert calls == [[11, 12, 13]]
        return
    summary = graph_eval.evaluate_graph(args)
    assert calls == [[11, 12, 13], [12, 13]]     # the plan's landings still missing, in order
    assert summary['unassisted']['n'] == 3
