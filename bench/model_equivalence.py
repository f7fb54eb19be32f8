"""Do the shipped models see any difference between the renderers? (issue: nothing observable changes)

    nice .venv/bin/python -m bench.model_equivalence cmvae            # CM-VAE held-out metrics
    nice .venv/bin/python -m bench.model_equivalence actors           # paired landings, latent + oracle
    (or per renderer in parallel: actors --renderers pybullet --out a.json; ... analytic --out b.json;
     then: compare a.json b.json)

`cmvae` re-renders the card's 2,500 held-out frames (models/cmvae.metrics.json: the 50 scenes that
split_by_scene(val_fraction=0.05, seed=0) holds out of make_dataset.yaml's 1,000 scenes; scenes are
deterministic in (seed, scene index), so only those scenes need rendering) with each renderer,
labels them as make_dataset does, and runs evaluate.compute_metrics (noise seed 1, the card's single
noise stream) on both; it prints both metric sets beside the card's, the pixel differences between
the two renders, and a paired comparison with the noise seeded per frame (the noise model's draws
depend on the depth edges, so in one stream a single differing edge pixel reshuffles the noise of
every later frame).

`actors` lands the shipped latent and oracle actors with simulated pilots (alpha 0.5) at the given
betas, `--landings` per beta, once with each renderer: landing k at beta b has the same seed
(evaluate's 2024 + 1000 b + k) in both, so the pairs differ only in the renderer; prints the
per-renderer summary (evaluate.summarize) and the paired differences.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from assist_sim.core.config import WorldConfig
from assist_sim.core.world import LandingWorld

ROOT = Path(__file__).resolve().parents[1]
RENDERERS = ('pybullet', 'analytic')


def _world(renderer: str, seed: int = 0) -> LandingWorld:
    cfg = WorldConfig()
    cfg.camera.renderer = renderer
    return LandingWorld(cfg, seed=seed)


def heldout_scenes(n_scenes: int = 1000, val_fraction: float = 0.05, split_seed: int = 0) -> np.ndarray:
    """Scene indices split_by_scene holds out of a dataset of `n_scenes` scenes (sorted)."""
    scenes = np.arange(n_scenes)
    rng = np.random.default_rng(split_seed)
    n_val = max(1, int(round(val_fraction * len(scenes))))
    return np.sort(rng.choice(scenes, size=n_val, replace=False))


def cmvae(args: argparse.Namespace) -> dict:
    """Card metrics of the shipped CM-VAE on the held-out frames rendered by each renderer."""
    import yaml

    from assist_lab.cmvae_dataset import DatasetConfig, FrameSet, render_scene
    from assist_lab.cmvae_evaluate import compute_metrics
    from assist_perception.model import load_model

    torch.set_num_threads(1)
    ds = DatasetConfig(**yaml.safe_load(
        (ROOT / 'ros2_ws/src/assist_lab/config/make_dataset.yaml').read_text(encoding='utf-8')))
    n_scenes = -(-ds.frames // ds.frames_per_scene)
    scenes = heldout_scenes(n_scenes, 0.05, 0)[:args.scenes]
    model = load_model(ROOT / 'models' / 'cmvae.pt', torch.device('cpu'))
    card = json.loads((ROOT / 'models' / 'cmvae.metrics.json').read_text())['heldout']
    sets, out = {}, {'scenes': [int(s) for s in scenes], 'card': card}
    for r in RENDERERS:
        world = _world(r, ds.seed)
        t0 = time.process_time()
        parts = [render_scene(world, int(s), ds, ds.frames_per_scene) for s in scenes]
        cpu = time.process_time() - t0
        world.close()
        a = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        sets[r] = FrameSet(a['rgb'], a['depth_mm'].astype(np.float32) / 1000.0, a['xyz'].astype(np.float32),
                           a['visible'].astype(bool), a['scene'], a['pad_index'])
        out[r] = compute_metrics(model, sets[r], np.arange(len(sets[r])), noise_seed=1)
        out[r]['render_and_label_cpu_s'] = round(cpu, 2)
        print(f'{r}: {len(sets[r])} frames rendered + labelled in {cpu:.1f} CPU-s', file=sys.stderr)
    a, b = sets['pybullet'], sets['analytic']
    drgb = np.abs(a.rgb.astype(int) - b.rgb.astype(int))
    out['pixels'] = {
        'frames': len(a), 'rgb_mean_abs_diff': float(drgb.mean()),
        'rgb_pixels_differing_fraction': float((drgb.max(-1) > 0).mean()),
        'depth_mm_pixels_differing_fraction': float((np.abs(a.depth - b.depth) > 5e-4).mean()),
        'labels_identical': bool(np.array_equal(a.visible, b.visible) and np.array_equal(a.pad_index, b.pad_index)
                                 and np.allclose(a.xyz, b.xyz, equal_nan=True, atol=1e-4)),
    }
    # the noise model draws a data-dependent number of samples (flying pixels at depth edges), so
    # one edge pixel that differs shifts the noise of every later frame in a single stream; paired
    # frame by frame, each frame with its own noise seed, only the renderers' effect shows
    per_frame = {r: [compute_metrics(model, sets[r], np.array([i]), noise_seed=10_000 + i)
                     for i in range(len(sets[r]))] for r in RENDERERS}
    paired = {'frames': len(a), 'frames_with_identical_metrics': int(sum(
        all(np.isclose(x[k], y[k], equal_nan=True) for k in x) for x, y in zip(*per_frame.values())))}
    for r in RENDERERS:
        m = per_frame[r]
        vis = [f for f in m if f['frames_with_pad']]
        paired[r] = {'depth_rmse_m': float(np.sqrt(np.mean([f['depth_rmse_m'] ** 2 for f in m])))}
        for ax in 'xyz':
            e = np.array([f[f'{ax}_abs_err_median_m'] for f in vis])
            paired[r][f'{ax}_abs_err_median_m'] = float(np.median(e))
            paired[r][f'{ax}_abs_err_p90_m'] = float(np.percentile(e, 90))
    out['paired_per_frame_noise'] = paired
    keys = [k for k in card if k in out['pybullet']]
    print(f'{"metric":32s} {"card":>9s} {"pybullet":>9s} {"analytic":>9s}')
    for k in keys:
        print(f'{k:32s} {card[k]:9.4f} {out["pybullet"][k]:9.4f} {out["analytic"][k]:9.4f}')
    print(json.dumps(out['pixels'], indent=1))
    print(json.dumps(paired, indent=1))
    return out


def actors(args: argparse.Namespace) -> dict:
    """Landings of the shipped actors with the selected renderers (rows kept for `compare`)."""
    from assist_lab.env import LandingAssistEnv
    from assist_lab.evaluate import EvalArgs, make_policy, run_landing
    from assist_perception.latent import make_latent_fn

    torch.set_num_threads(1)
    defaults = EvalArgs()
    out = {'betas': args.betas, 'landings_per_beta': args.landings, 'seed': defaults.seed, 'rows': {}}
    for cond in args.conditions:
        for r in args.renderers:
            env, policy = make_policy(cond, '', '', defaults.max_episode_s, defaults.alpha)
            cfg = dataclasses.replace(env.cfg)
            env.close()
            cfg.world = WorldConfig()
            cfg.world.camera.renderer = r
            latent_fn = make_latent_fn(seed=args.noise_seed)[0] if cond == 'latent' else None
            env = LandingAssistEnv(cfg, latent_fn=latent_fn)
            t0 = time.process_time()
            rows = [run_landing(env, policy, defaults.seed + 1000 * bi + k, float(beta))
                    for bi, beta in enumerate(args.betas) for k in range(args.landings)]
            env.close()
            out['rows'].setdefault(cond, {})[r] = rows
            print(f'{cond} / {r}: {len(rows)} landings in {time.process_time() - t0:.0f} CPU-s', file=sys.stderr)
    if all(len(v) == 2 for v in out['rows'].values()):
        out['paired'] = paired_summary(out['rows'])
    return out


def paired_summary(rows: dict) -> dict:
    """Per condition: evaluate.summarize for each renderer and the paired differences."""
    from assist_lab.evaluate import summarize

    res = {}
    for cond, by_r in rows.items():
        a, b = by_r[RENDERERS[0]], by_r[RENDERERS[1]]
        pairs = list(zip(a, b))
        if any((x['beta'], x['seed']) != (y['beta'], y['seed']) for x, y in pairs):
            raise ValueError(f'{cond}: the two row sets are not the same landings')
        err = np.array([[x['error_m'], y['error_m']] for x, y in pairs])
        res[cond] = {
            'landings': len(pairs),
            'summary': {r: summarize(by_r[r]) for r in RENDERERS},
            'identical_landings': int(sum(x == y for x, y in pairs)),
            'same_outcome': int(sum(x['outcome'] == y['outcome'] for x, y in pairs)),
            'mean_error_m': {r: float(err[:, i].mean()) for i, r in enumerate(RENDERERS)},
            'max_abs_error_diff_m': float(np.abs(err[:, 0] - err[:, 1]).max()),
        }
    print(json.dumps(res, indent=1, default=str))
    return res


def compare(args: argparse.Namespace) -> dict:
    """Merge `actors` outputs run separately per renderer and compare them."""
    rows: dict = {}
    for path in args.files:
        for cond, by_r in json.loads(Path(path).read_text())['rows'].items():
            rows.setdefault(cond, {}).update(by_r)
    return {'rows': rows, 'paired': paired_summary(rows)}


def main(argv: list[str] | None = None) -> int:
    """Command line (see module doc)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest='what', required=True)
    c = sub.add_parser('cmvae', help='CM-VAE held-out metrics with each renderer')
    c.add_argument('--scenes', type=int, default=50, help='held-out scenes to render (card: all 50)')
    a = sub.add_parser('actors', help='paired landings of the shipped actors with each renderer')
    a.add_argument('--betas', type=float, nargs='+', default=[0.0, 0.25, 0.5, 0.75, 1.0])
    a.add_argument('--landings', type=int, default=12, help='landings per beta and renderer')
    a.add_argument('--conditions', nargs='+', default=['latent', 'oracle'])
    a.add_argument('--renderers', nargs='+', default=list(RENDERERS), choices=RENDERERS)
    a.add_argument('--noise-seed', type=int, default=0,
                   help="base seed of the latent env's depth noise (make_latent_fn's default: 0; each landing "
                        "draws its own stream from it and the landing's seed); another base seed with the "
                        'same renderer shows how far landings move from noise alone')
    m = sub.add_parser('compare', help='merge and compare actors outputs run per renderer')
    m.add_argument('files', nargs='+')
    for p in (c, a, m):
        p.add_argument('--out', default='', help='also write the result as JSON here')
    args = ap.parse_args(argv)
    res = {'cmvae': cmvae, 'actors': actors, 'compare': compare}[args.what](args)
    if args.out:
        Path(args.out).write_text(json.dumps(res, indent=1, default=str))
    return 0


if __name__ == '__main__':
    sys.exit(main())
