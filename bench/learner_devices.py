"""Does training on CUDA give what training on the CPU gives? train_td3's learner, offline, on one device.

    python -m bench.learner_devices --run runs/latent_data --device cuda --seed 0 --out actor_cuda_0.pt
    evaluate --conditions latent --latent-model actor_cuda_0.pt --out runs/cuda_0 ...   # then fly it

The learner steps of a train_td3 run, on the data that run collected (`--run`: its demos_bc.npz, the
demonstrator's labelled states, and demos.npz, its transitions; its actor_last.pt gives the network
sizes and the metadata evaluate needs): behaviour cloning from a freshly seeded actor
(TD3.behaviour_clone, train_td3's --bc-steps), critic warm-up (TD3.update without the actor, its
--critic-warmup-updates) and TD3+BC updates (TD3.update with bc_alpha, its TD3 phase) on the replay
data. Nothing here needs the simulator, so it runs on a GPU machine that has only torch and numpy; the
actor written (with the run's metadata) is flown where the simulator is. Run it with two seeds on each
device: CUDA matches the CPU when its actors land as the CPU's do, within the spread between seeds.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from assist_policy.actor import load_actor, save_actor
from assist_lab.td3 import TD3, ReplayBuffer, TD3Config

ARCH_KEYS = ('vec_dim', 'act_dim', 'image', 'hidden', 'image_channels')


def train_offline(run: Path, device: str, seed: int, bc_steps: int, warmup: int, updates: int,
                  bc_alpha: float, actor_lr: float) -> tuple[TD3, dict, dict]:
    """(agent, run actor's metadata, losses and seconds per phase) after the learner's three phases."""
    _, meta = load_actor(run / 'actor_last.pt')
    with np.load(run / 'demos_bc.npz', allow_pickle=False) as data:
        d_obs, d_act = data['obs'], data['act']
    agent = TD3(meta['vec_dim'], meta['act_dim'], TD3Config(hidden=tuple(meta['hidden']), actor_lr=actor_lr),
                image=meta['image'], seed=seed, device=device)
    with np.load(run / 'demos.npz', allow_pickle=False) as data:
        n = data['act'].shape[0]
    buffer = ReplayBuffer(d_obs.shape[1], 3, n)
    buffer.load(run / 'demos.npz')
    out: dict = {'device': device, 'seed': seed, 'transitions': buffer.size, 'demonstrations': len(d_obs)}

    def timed(name, fn):
        if agent.device.type == 'cuda':
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        value = fn()
        if agent.device.type == 'cuda':
            torch.cuda.synchronize()
        out[f'{name}_s'] = round(time.perf_counter() - t0, 2)
        return value
    out['bc_mse'] = timed('bc', lambda: agent.behaviour_clone(d_obs, d_act, bc_steps))
    timed('warmup', lambda: [agent.update(buffer, train_actor=False) for _ in range(warmup)])
    losses = timed('td3', lambda: [agent.update(buffer, demos=(d_obs, d_act), bc_alpha=bc_alpha)
                                   for _ in range(updates)])
    tail = losses[-100:]
    out['critic_loss_last100'] = float(np.mean([x['critic_loss'] for x in tail])) if tail else None
    out['bc_loss_last100'] = float(np.mean([x['bc_loss'] for x in tail if 'bc_loss' in x])) if tail else None
    return agent, meta, out


def main(argv: list[str] | None = None) -> int:
    """Command line: train on one device, write the actor and a JSON line of losses and times."""
    parser = argparse.ArgumentParser(prog='learner_devices', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--run', required=True, type=Path, help='train_td3 run directory with demos_bc.npz, '
                        'demos.npz and actor_last.pt')
    parser.add_argument('--device', choices=('cpu', 'cuda'), default='cpu')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--bc-steps', type=int, default=3000)
    parser.add_argument('--warmup', type=int, default=500, help='critic warm-up updates')
    parser.add_argument('--updates', type=int, default=2000, help='TD3+BC updates')
    parser.add_argument('--bc-alpha', type=float, default=2.5)
    parser.add_argument('--actor-lr', type=float, default=1e-3)
    parser.add_argument('--out', type=Path, required=True, help='actor file to write')
    args = parser.parse_args(argv)
    if args.device == 'cuda' and not torch.cuda.is_available():
        parser.error('--device cuda: torch sees no GPU')
    if min(args.bc_steps, args.warmup, args.updates) < 0:
        parser.error('step counts must be >= 0')
    torch.set_num_threads(1)
    agent, meta, out = train_offline(args.run, args.device, args.seed, args.bc_steps, args.warmup, args.updates,
                                     args.bc_alpha, args.actor_lr)
    extra = {k: v for k, v in meta.items() if k not in ARCH_KEYS and k != 'eval'}
    save_actor(agent.actor, {**agent.meta, **extra, 'trained_on': args.device}, args.out)
    print(json.dumps(out))
    return 0


if __name__ == '__main__':
    sys.exit(main())
