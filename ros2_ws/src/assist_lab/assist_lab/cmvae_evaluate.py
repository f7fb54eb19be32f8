"""evaluate_cmvae: held-out metrics of a trained CM-VAE and a latent interpolation figure.

Metrics (on frames the model never saw, with a fixed draw of the noise model G):
- depth RMSE of the reconstruction p_D(mu) against the clean depth, and, for comparison, of the
  noisy input itself (holes counted as 0 m, and over valid pixels only);
- closest-visible-pad XYZ absolute error per axis (median and 90th percentile) on frames with a
  visible pad.
The figure follows the paper's Fig. 3: two inputs, and the depth decoded from
mu_i = mu_1 + delta (mu_2 - mu_1) for delta from 0 to 1.
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from assist_common.settings import check_settings, exit_error, parse_settings, setting
from .cmvae_dataset import FrameSet, load_frames, split_by_scene
from assist_perception.model import CMVAE, latent_interpolation, load_model, preprocess
from assist_perception.noise import NoiseConfig, apply_depth_noise

_LOG = logging.getLogger(__name__)


@dataclass
class EvalConfig:
    """Settings of `evaluate_cmvae` (every field is a --flag; ranges checked before any work)."""

    model_path: str = setting('models/cmvae.pt', nonempty=True)
    data_dir: str = setting('data/cmvae50k', nonempty=True)
    split: str = setting('val', choices=('val', 'all'))   # val: training's held-out scenes; all: a fresh dataset
    val_fraction: float = setting(0.05, gt=0.0, lt=1.0)   # must match training (scene split)
    split_seed: int = setting(0, ge=0, le=2**63 - 1)      # training seed (scene split)
    max_frames: int = setting(0, ge=0)                    # 0 = all frames of data_dir
    noise_seed: int = setting(1, ge=0, le=2**63 - 1)
    out_dir: str = setting('runs/cmvae_eval', nonempty=True)
    pairs: int = setting(4, ge=1, le=64)                  # rows of the interpolation figure
    steps: int = setting(8, ge=2, le=64)                  # interpolation steps per row
    batch_size: int = setting(256, ge=1, le=65_536)


def compute_metrics(model: CMVAE, frames: FrameSet, idx: np.ndarray, noise_seed: int = 1,
                    noise_cfg: NoiseConfig | None = None, batch_size: int = 256) -> dict[str, float]:
    """Held-out metrics of `model` on rows `idx` of `frames` (see module doc)."""
    noise_cfg = noise_cfg or NoiseConfig()
    rng = np.random.default_rng(noise_seed)
    model.eval()
    se_rec = se_rec_clean = se_in = se_valid = 0.0
    n_px = n_valid = 0
    errs = []
    with torch.no_grad():
        for s in range(0, len(idx), batch_size):
            b = idx[s:s + batch_size]
            clean = frames.depth[b]
            noisy = apply_depth_noise(clean, rng, noise_cfg, rgb=frames.rgb[b])
            out = model(preprocess(frames.rgb[b], noisy, model.cfg), sample=False)
            rec = out.depth.numpy()
            se_rec += float(((rec - clean) ** 2).sum())
            out_clean = model(preprocess(frames.rgb[b], clean, model.cfg), sample=False)
            se_rec_clean += float(((out_clean.depth.numpy() - clean) ** 2).sum())
            se_in += float(((noisy - clean) ** 2).sum())
            valid = noisy > 0
            se_valid += float(((noisy - clean)[valid] ** 2).sum())
            n_valid += int(valid.sum())
            n_px += clean.size
            vis = frames.visible[b]
            errs.append(np.abs(out.xyz.numpy()[vis] - frames.xyz[b][vis]))
    e = np.concatenate(errs) if errs else np.zeros((0, 3))
    res = {
        'frames': int(len(idx)),
        'frames_with_pad': int(len(e)),
        'depth_rmse_m': math.sqrt(se_rec / max(n_px, 1)),
        'depth_rmse_clean_input_m': math.sqrt(se_rec_clean / max(n_px, 1)),
        'noisy_input_rmse_m': math.sqrt(se_in / max(n_px, 1)),
        'noisy_input_rmse_valid_m': math.sqrt(se_valid / max(n_valid, 1)),
        'noisy_input_hole_fraction': 1.0 - n_valid / max(n_px, 1),
    }
    for i, ax in enumerate('xyz'):
        col = e[:, i] if len(e) else np.array([np.nan])
        res[f'{ax}_abs_err_median_m'] = float(np.median(col))
        res[f'{ax}_abs_err_p90_m'] = float(np.percentile(col, 90))
    return res


def interpolation_figure(model: CMVAE, frames: FrameSet, idx: np.ndarray, path: str | Path,
                         pairs: int = 4, steps: int = 8, seed: int = 0,
                         noise_cfg: NoiseConfig | None = None) -> Path:
    """PNG like the paper's Fig. 3: per row input 1, decoded interpolation, input 2."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(seed)
    cand = idx[frames.visible[idx]] if frames.visible[idx].sum() >= 2 * pairs else idx
    chosen = rng.choice(cand, size=(pairs, 2), replace=False)
    noise_cfg = noise_cfg or NoiseConfig()
    vmax = float(np.percentile(frames.depth[chosen.ravel()], 99))
    cols = steps + 4
    fig, axes = plt.subplots(pairs, cols, figsize=(1.3 * cols, 1.4 * pairs + 0.4), squeeze=False)
    for r, (i1, i2) in enumerate(chosen):
        noisy = apply_depth_noise(frames.depth[[i1, i2]], rng, noise_cfg, rgb=frames.rgb[[i1, i2]])
        x = preprocess(frames.rgb[[i1, i2]], noisy, model.cfg)
        seq = latent_interpolation(model, x[0], x[1], steps).numpy()
        panels = [(frames.rgb[i1], 'RGB 1'), (noisy[0], 'depth 1')]
        panels += [(seq[k], f'd={k / (steps - 1):.2f}') for k in range(steps)]
        panels += [(noisy[1], 'depth 2'), (frames.rgb[i2], 'RGB 2')]
        for c, (img, title) in enumerate(panels):
            ax = axes[r, c]
            if img.ndim == 3:
                ax.imshow(img)
            else:
                ax.imshow(img, cmap='viridis', vmin=0.0, vmax=vmax)
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=7)
    fig.suptitle('CM-VAE latent interpolation: depth decoded from mu1 + d (mu2 - mu1)', fontsize=9)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def evaluate(cfg: EvalConfig) -> dict:
    """Run the evaluation described by `cfg`; writes metrics.json and interpolation.png."""
    check_settings(cfg)
    model = load_model(cfg.model_path)
    frames = load_frames(cfg.data_dir, cfg.max_frames or None)
    if cfg.split == 'val':
        _, idx = split_by_scene(frames, cfg.val_fraction, cfg.split_seed)
    elif cfg.split == 'all':
        idx = np.arange(len(frames))
    else:
        raise ValueError(f"split must be 'val' or 'all', got {cfg.split!r}")
    metrics = compute_metrics(model, frames, idx, cfg.noise_seed, batch_size=cfg.batch_size)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig = interpolation_figure(model, frames, idx, out / 'interpolation.png', cfg.pairs, cfg.steps,
                               seed=cfg.noise_seed)
    metrics.update({'model_path': cfg.model_path, 'data_dir': cfg.data_dir, 'split': cfg.split,
                    'figure': str(fig)})
    (out / 'metrics.json').write_text(json.dumps(metrics, indent=1))
    return metrics


def main(argv: list[str] | None = None) -> int:
    """Console entry point `evaluate_cmvae`."""
    logging.basicConfig(level=logging.INFO, format='[%(levelname)s] %(name)s: %(message)s')
    cfg, _ = parse_settings(EvalConfig, 'Evaluate a trained CM-VAE on held-out frames.', argv, prog='evaluate_cmvae')
    try:
        metrics = evaluate(cfg)
    except (ValueError, OSError) as exc:       # bad model file, no dataset, unwritable --out-dir
        _LOG.debug('evaluate_cmvae failed', exc_info=True)
        exit_error('evaluate_cmvae', exc, 1)
    width = max(len(k) for k in metrics)
    for k, v in metrics.items():
        print(f'{k:<{width}}  {v:.4f}' if isinstance(v, float) else f'{k:<{width}}  {v}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
