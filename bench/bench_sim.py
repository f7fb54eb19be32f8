"""Simulator speed: physics steps/s, camera frame time, real-time factor of whole landing episodes,
and the analytic renderer against pybullet's TinyRenderer on the same scenes and poses.

Figures are per CPU-second of this process (time.process_time), so other jobs on a shared machine
do not count; the renderer ratio times both renderers alternately, frame by frame, on the same
poses, so it holds even when the machine is busy.

Profile: nice .venv/bin/python -m cProfile -s tottime -m bench sim | head -40
     or: .venv/bin/py-spy record -o sim.svg -- .venv/bin/python -m bench sim
"""
from __future__ import annotations

import time

import numpy as np

from assist_sim.core.config import WorldConfig
from assist_sim.core.scripted import expert_command
from assist_sim.core.world import LandingWorld

EPISODES = 5


def _episodes(world: LandingWorld, cfg: WorldConfig) -> dict:
    """Scripted landings with the camera rendered every control step (20 Hz); poses kept for the ratio."""
    sim_s = wall = cpu = render_cpu = 0.0
    frames = 0
    outcomes, poses = [], []
    for ep in range(EPISODES):
        world.reset(100 + ep)
        t0, c0 = time.perf_counter(), time.process_time()
        t_sim0 = world.time
        while not world.done:
            world.step(expert_command(world.state.position, world.goal_position))
            rc0 = time.process_time()
            cam, r_wo = world.camera_pose()
            world.render_pose(cam, r_wo)
            render_cpu += time.process_time() - rc0
            frames += 1
            if frames % 4 == 0:
                poses.append((100 + ep, cam, r_wo))
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
        sim_s += world.time - t_sim0
        outcomes.append(world.result.outcome)
    return {'sim_s': sim_s, 'wall': wall, 'cpu': cpu, 'render_cpu': render_cpu, 'frames': frames,
            'outcomes': outcomes, 'poses': poses}


def _renderer_ratio(world: LandingWorld, poses: list) -> tuple[float, float, int]:
    """CPU ms per frame of TinyRenderer (+ analytic floor) and of the analytic renderer, alternating
    frame by frame on the same poses (scene set-up excluded for both)."""
    t_tiny = t_fast = 0.0
    scene = None
    for seed, cam, r_wo in poses:
        if seed != scene:                  # new scene: build both renderers' scenes untimed
            world.reset(seed)
            scene = seed
            world._render_pybullet(cam, r_wo)
            world.render_pose(cam, r_wo)
        c0 = time.process_time()
        world._render_pybullet(cam, r_wo)
        c1 = time.process_time()
        world.render_pose(cam, r_wo)
        c2 = time.process_time()
        t_tiny += c1 - c0
        t_fast += c2 - c1
    n = len(poses)
    return 1e3 * t_tiny / n, 1e3 * t_fast / n, n


def run() -> list[dict]:
    """Measure single-threaded (CPU time = one core, wall time as well)."""
    cfg = WorldConfig()
    cfg.camera.renderer = 'analytic'
    world = LandingWorld(cfg, seed=0)
    ep = _episodes(world, cfg)
    tiny_ms, fast_ms, n_poses = _renderer_ratio(world, ep['poses'])
    # physics alone (no camera)
    world.reset(1)
    n = 2400
    t0 = time.process_time()
    for _ in range(n // (cfg.physics_hz // cfg.control_hz)):
        world.step(np.array([0.5, 0.0, 0.0]))
    physics_s = (time.process_time() - t0) / n
    world.close()
    outcomes = ep['outcomes']
    return [
        {'name': 'physics step (240 Hz, no camera), CPU per step', 'value': 1e6 * physics_s, 'unit': 'us',
         'target': 'keep (68 us = 14.6k steps/s before)'},
        {'name': 'physics steps/s per CPU-second', 'value': 1.0 / physics_s, 'unit': 'steps/s', 'target': ''},
        {'name': 'camera frame (64x64 RGB + depth, analytic), CPU per frame',
         'value': 1e3 * ep['render_cpu'] / ep['frames'], 'unit': 'ms', 'target': '<= 0.5 ms'},
        {'name': 'camera frames/s per CPU-second (analytic)', 'value': ep['frames'] / ep['render_cpu'],
         'unit': 'frames/s', 'target': ''},
        {'name': f'TinyRenderer / analytic CPU per frame, same {n_poses} poses (baseline ratio)',
         'value': tiny_ms / fast_ms, 'unit': 'x', 'target': '> 1 (analytic faster)'},
        {'name': 'TinyRenderer (+ analytic floor) frame, same poses, CPU per frame', 'value': tiny_ms, 'unit': 'ms',
         'target': 'baseline'},
        {'name': f'landing episodes with camera at 20 Hz, x real time per CPU-second ({EPISODES} landings, one core)',
         'value': ep['sim_s'] / ep['cpu'], 'unit': 'x', 'target': '>= 50x'},
        {'name': 'landing episodes x real time, wall clock (shared machine)', 'value': ep['sim_s'] / ep['wall'],
         'unit': 'x', 'target': ''},
        {'name': 'scripted landings that succeeded', 'value': f'{outcomes.count("success")}/{EPISODES}',
         'unit': '', 'target': f'{EPISODES}/{EPISODES}'},
    ]
