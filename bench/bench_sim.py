"""Simulator speed: physics steps/s, camera frames/s, real-time factor of whole landing episodes."""
from __future__ import annotations

import time

import numpy as np

from assist_sim.core.config import WorldConfig
from assist_sim.core.scripted import expert_command
from assist_sim.core.world import LandingWorld

EPISODES = 5


def run() -> list[dict]:
    """Measure on one core: a full landing per episode, camera rendered at 20 Hz (every control step)."""
    cfg = WorldConfig()
    world = LandingWorld(cfg, seed=0)
    sim_s = wall = render_s = 0.0
    frames = physics_steps = 0
    outcomes = []
    for ep in range(EPISODES):
        world.reset(100 + ep)
        t0 = time.perf_counter()
        t_sim0 = world.time
        while not world.done:
            st = world.step(expert_command(world.state.position, world.goal_position))
            physics_steps += cfg.physics_hz // cfg.control_hz
            r0 = time.perf_counter()
            world.render()
            render_s += time.perf_counter() - r0
            frames += 1
        wall += time.perf_counter() - t0
        sim_s += world.time - t_sim0
        outcomes.append(world.result.outcome)
    # physics alone (no camera)
    world.reset(1)
    n = 2000
    t0 = time.perf_counter()
    for _ in range(n // (cfg.physics_hz // cfg.control_hz)):
        world.step(np.array([0.5, 0.0, 0.0]))
    physics_rate = n / (time.perf_counter() - t0)
    world.close()
    return [
        {'name': 'physics steps/s (240 Hz physics, no camera)', 'value': physics_rate, 'unit': 'steps/s'},
        {'name': 'camera frames/s (64x64 RGB-D)', 'value': frames / render_s, 'unit': 'frames/s'},
        {'name': f'real-time factor, {EPISODES} full landings, camera 20 Hz', 'value': sim_s / wall, 'unit': 'x',
         'target': '>= 50x'},
        {'name': 'scripted landings that succeeded', 'value': f'{outcomes.count("success")}/{EPISODES}',
         'unit': '', 'target': ''},
    ]
