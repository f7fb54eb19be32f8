"""Policy section of `make bench`: actor inference time, policy-core step, env and training throughput."""
from __future__ import annotations

import time

import numpy as np
import torch


def _rate(fn, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - t0)


def run() -> list[dict]:
    """Measure and return rows (name, value, unit, target)."""
    from assist_lab.env import EnvConfig, LandingAssistEnv
    from assist_policy.observation import vector_dim
    from assist_lab.td3 import TD3, ReplayBuffer, TD3Config

    torch.set_num_threads(1)
    rows = []
    dim = vector_dim('latent', 10)
    agent = TD3(dim, 3, TD3Config(), seed=0)
    obs = np.zeros(dim, np.float32)
    agent.act(obs)
    hz = _rate(lambda: agent.act(obs), 2000)
    rows.append({'name': 'actor inference (latent, 256x256 MLP, 1 thread)', 'value': 1e3 / hz, 'unit': 'ms',
                 'target': '< 2 ms (20 Hz policy)'})
    rows += _actor_backend_rows()
    buf = ReplayBuffer(dim, 3, 10_000)
    rng = np.random.default_rng(0)
    for _ in range(1000):
        buf.add(rng.normal(size=dim), rng.uniform(-1, 1, 3), 0.0, rng.normal(size=dim), False)
    c0 = time.process_time()
    for _ in range(200):
        agent.update(buf)
    ups = 200 / (time.process_time() - c0)
    rows.append({'name': 'TD3 update per CPU-second (batch 100, 1 thread; one per env step in train_td3)',
                 'value': ups, 'unit': 'updates/s', 'target': '> 100'})
    env = LandingAssistEnv(EnvConfig(condition='oracle'))
    env.reset(seed=0)
    state = {'done': False}

    def step():
        if state['done']:
            env.reset()
        _, _, term, trunc, _ = env.step(np.zeros(3, np.float32))
        state['done'] = term or trunc
    sps = _rate(step, 2000)
    env.close()
    rows.append({'name': 'env steps (oracle, sim physics 240 Hz)', 'value': sps, 'unit': 'steps/s',
                 'target': '> 20 (real time)'})
    try:
        from assist_perception.latent import make_latent_fn
        latent_fn, dim = make_latent_fn()
    except ValueError:
        return rows   # no shipped CM-VAE: the latent rows need it
    torch.set_num_threads(1)          # make_latent_fn leaves torch's thread count alone
    env = LandingAssistEnv(EnvConfig(condition='latent', latent_dim=dim), latent_fn=latent_fn)
    env.reset(seed=0)
    state['done'] = False
    for _ in range(20):
        step()
    c0 = time.process_time()
    n = 400
    for _ in range(n):
        step()
    sps = n / (time.process_time() - c0)
    env.close()
    rows.append({'name': 'latent env steps/s per CPU-second (render + depth noise + CM-VAE, 1 thread)',
                 'value': sps, 'unit': 'steps/s', 'target': '>= 500'})
    rows += _batched_encoder_rows()
    return rows


def _actor_backend_rows(n: int = 2000) -> list[dict]:
    """The shipped latent actor one observation at a time on torch and on ONNX Runtime (policy_node's backends), and
    the CPU seconds of importing policy_node's module with and without torch."""
    import subprocess
    import sys

    from assist_policy.actor_runtime import load_actor_runtime, observation_size
    from assist_policy.policy_core import default_model_path
    path = default_model_path('latent')
    rows = []
    for backend in ('torch', 'onnxruntime'):
        actor = load_actor_runtime(path, backend, threads=1)
        obs, pos = np.zeros(observation_size(actor.meta), np.float32), np.zeros(3)
        actor(obs, pos)
        hz = _rate(lambda a=actor, o=obs, p=pos: a(o, p), n)
        rows.append({'name': f'shipped latent actor per step, {backend} (1 thread)', 'value': 1e3 / hz, 'unit': 'ms',
                     'target': '< 2 ms (20 Hz policy)'})
    for what, code in (('policy_node module (no torch)', 'import assist_policy.policy_node'),
                       ('policy_node module + torch', 'import assist_policy.policy_node, torch')):
        out = subprocess.run([sys.executable, '-c', f'import resource; {code}; r = resource.getrusage(0); '
                              'print(r.ru_utime + r.ru_stime)'], capture_output=True, text=True, check=True)
        rows.append({'name': f'import CPU time: {what}', 'value': float(out.stdout.split()[-1]), 'unit': 's',
                     'target': 'lower is better (once per node start)'})
    return rows


def _batched_encoder_rows(batch: int = 8, n: int = 100) -> list[dict]:
    """CM-VAE mu per frame at batch 1 and batched (as vectorised envs would call it), same frames."""
    from assist_perception.encoder_core import LatentEncoder

    from assist_sim.core.world import LandingWorld

    enc = LatentEncoder(threads=1)
    world = LandingWorld(seed=0)
    world.reset(7)
    frames = [world.render_from(world.goal_position + np.array([dx, 0.0, 2.5])) for dx in np.linspace(-2, 2, batch)]
    world.close()
    rgbs, depths = [f.rgb for f in frames], [f.depth for f in frames]
    enc.encode_mu_batch(rgbs, depths)
    t_one = t_batch = 0.0
    for _ in range(n):                      # alternate, so machine load hits both alike
        c0 = time.process_time()
        for r, d in zip(rgbs, depths):
            enc.encode(r, d, want_xyz=False)
        c1 = time.process_time()
        enc.encode_mu_batch(rgbs, depths)
        t_batch += time.process_time() - c1
        t_one += c1 - c0
    per_one, per_batch = 1e3 * t_one / (n * batch), 1e3 * t_batch / (n * batch)
    return [
        {'name': 'CM-VAE mu per frame, batch 1 (1 thread, CPU)', 'value': per_one, 'unit': 'ms', 'target': ''},
        {'name': f'CM-VAE mu per frame, batch {batch} (encode_mu_batch, vectorised envs)', 'value': per_batch,
         'unit': 'ms', 'target': ''},
        {'name': f'batch 1 / batch {batch} CPU per frame (same frames)', 'value': per_one / per_batch, 'unit': 'x',
         'target': '> 1'},
    ]
