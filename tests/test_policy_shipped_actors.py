"""The shipped TD3 actors still do what their model cards say, on landings they were not selected on."""
from pathlib import Path

import numpy as np
import torch

from assist_lab.env import run_episode
from assist_lab.evaluate import make_policy

REPO = Path(__file__).resolve().parents[1]
SEED = 777_000           # unseen: the cards use seed 2024 (evaluate) and 12345 (train_td3's evaluations)


def _fly(condition: str, betas, per_beta: int) -> list[dict]:
    """Fly the shipped actor (through the shipped CM-VAE for latent) as `evaluate` does."""
    torch.set_num_threads(1)
    env, policy = make_policy(condition, str(REPO / 'models' / f'td3_{condition}_actor.pt'), '', 60.0, 0.5)
    try:
        return [run_episode(env, policy, SEED + 100 * i + k, {'beta': float(b)})
                for i, b in enumerate(betas) for k in range(per_beta)]
    finally:
        env.close()


def test_shipped_oracle_actor_lands_on_the_goal_centre():
    rows = _fly('oracle', np.linspace(0.0, 1.0, 6), 2)
    err = np.array([r['error_m'] for r in rows])
    # card: 0.093 +- 0.062 m, 99.5 % success over 840 landings
    assert err.mean() < 0.16, err.round(3)
    assert sum(r['success'] for r in rows) >= 11, [r['outcome'] for r in rows]
    assert not any(r['crash'] for r in rows)


def test_shipped_latent_actor_centres_skilled_pilots_on_their_goal():
    """Through the shipped CM-VAE; pilots beta >= 0.5, where its card gives 0.10-0.19 m per beta."""
    rows = _fly('latent', (0.5, 0.75, 1.0), 3)
    err = np.array([r['error_m'] for r in rows])
    assert np.median(err) < 0.2, err.round(3)
    assert sum(r['success'] for r in rows) >= 7, [r['outcome'] for r in rows]
    assert not any(r['crash'] for r in rows)
