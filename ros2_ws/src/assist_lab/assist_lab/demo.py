"""`make demo`: simulated pilots land unassisted and assisted (shipped actors); prints a results table.

    python -m assist_lab.demo [--landings 3] [--betas 0 0.3 0.6 1] [--out runs/demo]

Uses the latent assistant when its actor and the CM-VAE are shipped, the oracle assistant when
its actor is, and says which ones it could not run.
"""
from __future__ import annotations

import argparse
import logging
import sys

import torch

from .evaluate import EvalArgs, evaluate, format_table
from assist_perception.latent import default_encoder_path
from assist_policy.policy_core import default_model_path


def available_assistants() -> list[str]:
    """Assistant conditions whose shipped files exist."""
    out = []
    for cond in ('latent', 'oracle'):
        if not default_model_path(cond).is_file():
            continue
        if cond == 'latent':
            try:
                default_encoder_path()
            except ValueError:
                continue
        out.append(cond)
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the demo and print the table."""
    logging.basicConfig(level=logging.WARNING, format='%(levelname)s %(name)s: %(message)s')
    torch.set_num_threads(1)
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--landings', type=int, default=3, help='landings per beta and condition')
    parser.add_argument('--betas', type=float, nargs='*', default=[0.0, 0.3, 0.6, 1.0])
    parser.add_argument('--seed', type=int, default=7)
    parser.add_argument('--out', default='runs/demo')
    ns = parser.parse_args(argv)
    assistants = available_assistants()
    if not assistants:
        print('no shipped assistant found (models/td3_latent_actor.pt + models/cmvae.pt, or '
              'models/td3_oracle_actor.pt): showing the unassisted pilots only')
    conds = ('unassisted', *assistants)
    print(f'simulated pilots, alpha 0.5, beta {ns.betas}, {ns.landings} landing(s) each; '
          f'conditions: {", ".join(conds)} ...', flush=True)
    summary = evaluate(EvalArgs(out=ns.out, conditions=conds, betas=tuple(ns.betas), landings=ns.landings,
                                seed=ns.seed, plot=True))
    print(format_table(summary))
    print(f'every landing: {ns.out}/landings.csv; plot: {ns.out}/error_vs_beta.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
