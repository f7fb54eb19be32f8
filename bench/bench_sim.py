"""Simulator speed: physics steps/s, camera frames/s, real-time factor of whole landing episodes."""
from __future__ import annotations

import time

import numpy as np

from assist_sim.core.config import WorldConfig
from assist_sim.core.scripted import expert_command
from assist_sim.core.world import LandingWorld

EPISODES = 5


def run() -> list[dict]:
    """Measure single-threaded (CPU time = one core, wall time as well): a full landing per episode, camera rendered at 20 Hz (every control step)."""
    cfg = WorldConfig()
    world = LandingWorld(cfg, seed=0)
    sim_s = wall = cpu = render_s = render_cpu = 0.0
    frames = physics_steps = 0
    outcomes = []
    for ep in range(EPISODES):
        world.reset(100 + ep)
        t0, c0 = time.perf_counter(), time.process_time()
        t_sim0 = world.time
        while not world.done:
            world.step(expert_command(world.state.position, world.goal_position))
            physics_steps += cfg.physics_hz // cfg.control_hz
            r0, rc0 = time.perf_counter(), time.process_time()
            world.render()
            render_s += time.perf_counter() - r0
            render_cpu += time.process_time() - rc0
            frames += 1
        wall += time.perf_counter() - t0
        cpu += time.process_time() - c0
        sim_s += world.time - t_sim0
        outcomes.append(world.result.outcome)
    # physics alone (no camera)
    world.reset(1)
    n = 2000
    t0 = time.process_time()
    for _ in range(n // (cfg.physics_hz // cfg.control_hz)):
        world.step(np.array([0.5, 0.0, 0.0]))
    physics_rate = n / (time.process_time() - t0)
    world.close()
    return [
        {'name': 'physics steps/s per CPU-second (240 Hz, no camera)', 'value': physics_rate, 'unit': 'steps/s'},
        {'name': 'camera frames/s per CPU-second (64x64 RGB-D)', 'value': frames / render_cpu, 'unit': 'frames/s'},
        {'name': 'camera frames/s, wall clock', 'value': frames / render_s, 'unit': 'frames/s'},
        {'name': f'real-time factor per CPU-second, {EPISODES} landings, camera 20 Hz', 'value': sim_s / cpu,
         'unit': 'x', 'target': '>= 50x (one core)'},
        {'name': 'real-time factor, wall clock (shared machine)', 'value': sim_s / wall, 'unit': 'x'},
        {'name': 'scripted landings that succeeded', 'value': f'{outcomes.count("success")}/{EPISODES}',
         'unit': '', 'target': ''},
    ]
