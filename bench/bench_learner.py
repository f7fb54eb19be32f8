"""Learner section of `make bench`: train_td3's TD3 update and behaviour-cloning step on each device torch sees.

The latent actor (MLP on the latent observation) and the end-to-end actor (convolutional trunk on the
64x64 depth image) at train_td3's batch sizes; on the CPU with one thread (train_td3's --torch-threads
default) and, where torch sees a GPU, on CUDA (`--device cuda`). Wall-clock rates, the GPU synchronised
before each clock read. The update includes sampling the batch from the numpy replay buffer and moving
it to the device, as in training.
"""
from __future__ import annotations

import time

import numpy as np
import torch

BATCH_BC = 256                  # TD3.behaviour_clone's default batch


def _rate(fn, n: int, device: torch.device) -> float:
    fn()                                        # warm-up (cuDNN picks its kernels, allocator fills)
    if device.type == 'cuda':
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    if device.type == 'cuda':
        torch.cuda.synchronize()
    return n / (time.perf_counter() - t0)


def _learner_rows(condition: str, image: bool, device: str, n_update: int, n_bc: int) -> list[dict]:
    from assist_policy.observation import IMAGE_SHAPE, vector_dim
    from assist_lab.td3 import TD3, ReplayBuffer, TD3Config

    vec = vector_dim(condition, 10 if condition == 'latent' else 0)
    obs_dim = vec + (int(np.prod(IMAGE_SHAPE)) if image else 0)
    agent = TD3(vec, 3, TD3Config(), image=image, seed=0, device=device)
    rng = np.random.default_rng(0)
    buf = ReplayBuffer(obs_dim, 3, 4096, obs_dtype=np.float16 if image else np.float32)
    n = 2048 if not image else 512
    buf.extend(rng.normal(size=(n, obs_dim)), rng.uniform(-1, 1, (n, 3)), rng.normal(size=n),
               rng.normal(size=(n, obs_dim)), np.zeros(n))
    obs = rng.normal(size=(n, obs_dim)).astype(np.float32)
    act = rng.uniform(-0.9, 0.9, (n, 3)).astype(np.float32)
    dev = torch.device(device)
    what = f'{condition} actor ({"conv trunk + " if image else ""}MLP), {device}'
    ups = _rate(lambda: agent.update(buf), n_update, dev)
    agent.behaviour_clone(obs, act, 1)          # warm-up
    if dev.type == 'cuda':
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    agent.behaviour_clone(obs, act, n_bc)       # as train_td3 calls it: the demonstrations moved once
    if dev.type == 'cuda':
        torch.cuda.synchronize()
    bcs = n_bc / (time.perf_counter() - t0)
    return [{'name': f'TD3 update, {what} (batch {agent.cfg.batch_size})', 'value': ups, 'unit': 'updates/s'},
            {'name': f'behaviour-cloning step, {what} (batch {BATCH_BC})', 'value': bcs, 'unit': 'steps/s'}]


def run() -> list[dict]:
    """Measure and return rows (name, value, unit, target)."""
    torch.set_num_threads(1)
    devices = ['cpu'] + (['cuda'] if torch.cuda.is_available() else [])
    rows = []
    for device in devices:
        fast = device == 'cuda'
        rows += _learner_rows('latent', False, device, 2000 if fast else 300, 2000 if fast else 300)
        rows += _learner_rows('end_to_end', True, device, 500 if fast else 5, 500 if fast else 5)
    if 'cuda' in devices:
        by_name = {r['name']: r['value'] for r in rows}
        for name, value in list(by_name.items()):
            if name.endswith(')') and ', cuda' in name:
                cpu = by_name.get(name.replace(', cuda', ', cpu'))
                if cpu:
                    rows.append({'name': 'CUDA over CPU: ' + name.replace(', cuda', ''), 'value': value / cpu,
                                 'unit': 'x'})
    else:
        rows.append({'name': 'CUDA rows', 'value': 'no GPU seen by torch', 'unit': ''})
    return rows
