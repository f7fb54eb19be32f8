"""train_cmvae: train the denoising CM-VAE on a make_dataset directory.

The depth noise model G is applied on the fly (new noise every epoch) to the clean depth to make
the network input; the targets are the clean depth and the closest-visible-pad XYZ. Whole scenes
are held out for validation. The run directory gets config.json, metrics.csv (one row per epoch),
checkpoint.pt (latest, for --resume), best.pt and model.pt (weights files for load_model).
Every file is replaced atomically (temporary file, fsync, rename); on --resume the metrics rows of
epochs after the checkpoint are dropped (they are trained again).

Settings are checked before any work (one `error:` line, exit status 2): each field's rule, a run
directory holding a checkpoint needs --resume, and a resumed run must have the settings it was
started with (config.json), except RESUMABLE_CHANGES (epochs, threads, max_minutes,
stop_after_epoch); the error names each setting that differs. A damaged checkpoint, and a run whose
loss turns non-finite (it stops before writing that epoch's files, keeping the last finite model),
end with one `error:` line and exit status 1.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from assist_common.atomic import atomic_path, remove_stale_temporaries, truncate_csv, write_text_atomic
from assist_common.settings import SettingsError, check_settings, exit_error, flag, parse_settings, setting
from assist_perception.model import (CMVAE, CMVAEConfig, LossConfig, cmvae_loss, load_training_state, preprocess,
                                     save_model, training_device)
from assist_perception.noise import NoiseConfig, apply_depth_noise
from .cmvae_dataset import FrameSet, load_frames, split_by_scene
from .curves import plot_curves

_LOG = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    """Settings of one training run (every field is a --flag; ranges checked before any work)."""

    data_dir: str = setting('data/cmvae50k', nonempty=True)       # make_dataset output
    run_dir: str = setting('runs/cmvae', nonempty=True)           # config, metrics.csv, checkpoints
    epochs: int = setting(10, ge=1, le=100_000)
    batch_size: int = setting(128, ge=1, le=65_536)
    lr: float = setting(1e-3, gt=0.0, le=1.0)                     # Adam, cosine decay to lr_min after warm-up
    lr_min: float = setting(2e-5, ge=0.0, le=1.0)                 # <= lr
    warmup_steps: int = setting(100, ge=0)
    weight_decay: float = setting(0.0, ge=0.0, le=1.0)
    val_fraction: float = setting(0.05, ge=0.0, lt=1.0)           # fraction of scenes held out
    max_frames: int = setting(0, ge=0)                            # 0 = the whole dataset
    seed: int = setting(0, ge=0, le=2**31 - 1)
    latent_dim: int = setting(10, ge=1, le=4096)
    depth_scale_m: float = setting(5.0, gt=0.0, le=100.0)
    noise_prob: float = setting(0.9, ge=0.0, le=1.0)              # fraction of training inputs degraded by G
    kl_warmup_epochs: float = setting(1.0, ge=0.0, le=100_000)    # KL weight ramps linearly from 0 over these
    w_depth: float = setting(1.0, ge=0.0, le=1e6)                 # paper weights 1 / 2 / 4
    w_xyz: float = setting(2.0, ge=0.0, le=1e6)
    w_kl: float = setting(4.0, ge=0.0, le=1e6)
    depth_sigma_m: float = setting(0.25, gt=0.0, le=100.0)        # loss units (see LossConfig)
    xyz_sigma_m: float = setting(0.03, gt=0.0, le=100.0)
    threads: int = setting(1, ge=1, le=256)       # torch intra-op threads (1 is fastest on a shared 2-core box)
    device: str = setting('auto', choices=('auto', 'cpu', 'cuda'))   # auto: cuda when torch sees a GPU
    max_minutes: float = setting(0.0, ge=0.0)     # time budget (0 = off): the LR schedule follows whichever of
    #                                               steps or elapsed/budget is further along; stops when spent
    stop_after_epoch: int = setting(0, ge=0)      # end the run after this epoch (0 = off); --resume continues
    resume: bool = False                          # continue from run_dir/checkpoint.pt (same settings)

    def check_relations(self) -> None:
        """SettingsError when fields contradict each other."""
        if self.lr_min > self.lr:
            raise SettingsError(f'--lr-min ({self.lr_min:g}) must not exceed --lr ({self.lr:g})')
        if self.w_depth + self.w_xyz == 0.0:
            raise SettingsError('--w-depth and --w-xyz are both 0: nothing to learn')


def _batch_inputs(frames: FrameSet, idx: np.ndarray, rng: np.random.Generator,
                  noise_cfg: NoiseConfig, noise_prob: float, mcfg: CMVAEConfig) -> torch.Tensor:
    """Network input for rows `idx`: G(clean depth) for a `noise_prob` fraction, clean otherwise."""
    depth = frames.depth[idx]
    rgb = frames.rgb[idx]
    noisy = apply_depth_noise(depth, rng, noise_cfg, rgb=rgb)
    keep_clean = rng.uniform(size=len(idx)) >= noise_prob
    noisy[keep_clean] = depth[keep_clean]
    return preprocess(rgb, noisy, mcfg)


def _targets(frames: FrameSet, idx: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    vis = frames.visible[idx]
    xyz = np.where(vis[:, None], frames.xyz[idx], 0.0).astype(np.float32)
    return (torch.from_numpy(frames.depth[idx]), torch.from_numpy(xyz), torch.from_numpy(vis))


def evaluate_split(model: CMVAE, frames: FrameSet, idx: np.ndarray, loss_cfg: LossConfig,
                   noise_cfg: NoiseConfig, seed: int, batch_size: int = 256) -> dict[str, float]:
    """Losses (z = mu) and metrics on rows `idx` with a fixed noise draw (same every call), on the model's device."""
    model.eval()
    device = next(model.parameters()).device
    rng = np.random.default_rng(seed)
    sums = {'loss': 0.0, 'depth_loss': 0.0, 'xyz_loss': 0.0, 'kl': 0.0}
    se_rec = se_in = se_valid = 0.0
    n_px = n_valid = 0
    err = []
    with torch.no_grad():
        for s in range(0, len(idx), batch_size):
            b = idx[s:s + batch_size]
            x = _batch_inputs(frames, b, rng, noise_cfg, 1.0, model.cfg).to(device)
            d, xyz, vis = (v.to(device) for v in _targets(frames, b))
            out = model(x, sample=False)
            terms = cmvae_loss(out, d, xyz, vis, loss_cfg)
            for k, t in zip(sums, terms):
                sums[k] += float(t) * len(b)
            se_rec += float(((out.depth - d) ** 2).sum())
            d_in = x[:, 3] * model.cfg.depth_scale_m
            se_in += float(((d_in - d) ** 2).sum())
            valid = d_in > 0
            se_valid += float(((d_in - d)[valid] ** 2).sum())
            n_valid += int(valid.sum())
            n_px += d.numel()
            v = vis.cpu().numpy()
            err.append((out.xyz.cpu().numpy() - xyz.cpu().numpy())[v])
    n = max(len(idx), 1)
    e = np.concatenate(err) if err else np.zeros((0, 3))
    res = {k: v / n for k, v in sums.items()}
    res['depth_rmse_m'] = math.sqrt(se_rec / max(n_px, 1))
    res['input_rmse_m'] = math.sqrt(se_in / max(n_px, 1))          # holes count as 0 m
    res['input_rmse_valid_m'] = math.sqrt(se_valid / max(n_valid, 1))   # non-hole pixels only
    res['input_hole_fraction'] = 1.0 - n_valid / max(n_px, 1)
    for i, ax in enumerate('xyz'):
        res[f'{ax}_mae_m'] = float(np.median(np.abs(e[:, i]))) if len(e) else float('nan')
    return res


def _lr_at(step: int, total: int, cfg: TrainConfig, elapsed_s: float = 0.0) -> float:
    """Linear warm-up, then cosine decay to lr_min over the steps (or the time budget)."""
    if step < cfg.warmup_steps:
        return cfg.lr * (step + 1) / cfg.warmup_steps
    t = min(1.0, (step - cfg.warmup_steps) / max(1, total - cfg.warmup_steps))
    if cfg.max_minutes > 0:
        t = max(t, min(1.0, elapsed_s / (60.0 * cfg.max_minutes)))
    return cfg.lr_min + 0.5 * (cfg.lr - cfg.lr_min) * (1 + math.cos(math.pi * t))


RESUMABLE_CHANGES = ('epochs', 'threads', 'max_minutes', 'stop_after_epoch', 'device', 'resume')
CHECKPOINT_KEYS = ('model', 'optimizer', 'epoch', 'step', 'best', 'elapsed_s')


def check_run_dir(cfg: TrainConfig) -> None:
    """SettingsError unless `cfg` may train in its run directory (nothing is written).

    A directory holding a checkpoint needs --resume, and a resumed run keeps the settings it was
    started with (config.json): only RESUMABLE_CHANGES may differ; the error names the others.
    """
    run = Path(cfg.run_dir)
    if run.exists() and not run.is_dir():
        raise SettingsError(f'--run-dir {run} exists and is not a directory')
    ckpt_path = run / 'checkpoint.pt'
    if not ckpt_path.exists():
        return
    if not cfg.resume:
        raise SettingsError(f'--run-dir {run} holds a checkpoint: pass --resume to continue it, or use a new '
                            '--run-dir')
    try:
        saved = json.loads((run / 'config.json').read_text(encoding='utf-8'))
        if not isinstance(saved, dict):
            raise ValueError('not a mapping')
    except (OSError, ValueError) as exc:
        raise SettingsError(f'--resume: {run / "config.json"} is missing or unreadable ({exc}), so the run\'s '
                            'settings are unknown') from None
    now = dataclasses.asdict(cfg)
    changed = [f'{flag(k)} (run: {saved[k]!r}, now: {now[k]!r})' for k in now
               if k in saved and k not in RESUMABLE_CHANGES and saved[k] != now[k]]
    if changed:
        raise SettingsError(f'--resume: the run in {run} was started with other settings: {"; ".join(changed)}; '
                            'resume with its settings (only ' + ', '.join(flag(k) for k in RESUMABLE_CHANGES[:-1])
                            + ' may change) or use a new --run-dir')


def load_checkpoint(path: Path) -> dict:
    """The training state in checkpoint.pt (weights_only); ValueError (one line) when it is damaged."""
    return load_training_state(path, CHECKPOINT_KEYS)


def train(cfg: TrainConfig, frames: FrameSet | None = None, progress: bool = True) -> dict:
    """Run (or resume) training; returns the last epoch's metrics plus timing.

    SettingsError (before anything is written) for bad settings or a run directory they do not fit;
    ValueError for a damaged checkpoint or a diverged run (non-finite loss: the last good model.pt
    and checkpoint are kept).
    """
    from tqdm import tqdm

    check_settings(cfg)
    check_run_dir(cfg)
    device = torch.device(training_device(cfg.device))
    torch.set_num_threads(cfg.threads)
    run = Path(cfg.run_dir)
    ckpt_path = run / 'checkpoint.pt'
    ck = load_checkpoint(ckpt_path) if cfg.resume and ckpt_path.exists() else None
    run.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(run)
    write_text_atomic(run / 'config.json', json.dumps(dataclasses.asdict(cfg), indent=1))

    if frames is None:
        frames = load_frames(cfg.data_dir, cfg.max_frames or None)
    train_idx, val_idx = split_by_scene(frames, cfg.val_fraction, cfg.seed)
    if len(train_idx) == 0:
        raise ValueError('no training frames after the held-out split')
    noise_cfg = NoiseConfig()
    loss_cfg = LossConfig(cfg.w_depth, cfg.w_xyz, cfg.w_kl, cfg.depth_sigma_m, cfg.xyz_sigma_m)

    torch.manual_seed(cfg.seed)
    model = CMVAE(CMVAEConfig(latent_dim=cfg.latent_dim, depth_scale_m=cfg.depth_scale_m))
    model = model.to(device=device, memory_format=torch.channels_last)   # ~1.5x faster convolutions on CPU
    vis_train = train_idx[frames.visible[train_idx]]
    if len(vis_train):
        model.set_xyz_stats(frames.xyz[vis_train].mean(0), frames.xyz[vis_train].std(0))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = math.ceil(len(train_idx) / cfg.batch_size)
    total_steps = steps_per_epoch * cfg.epochs
    start_epoch, step, best, elapsed = 0, 0, math.inf, 0.0
    if ck is not None:
        try:
            model.load_state_dict(ck['model'])
            model.set_xyz_stats(model.xyz_mean.cpu().numpy(), model.xyz_std.cpu().numpy())
            opt.load_state_dict(ck['optimizer'])
            start_epoch, step = int(ck['epoch']) + 1, int(ck['step'])
            best, elapsed = float(ck['best']), float(ck['elapsed_s'])
        except (RuntimeError, ValueError, KeyError, TypeError) as exc:
            first = (str(exc).strip().splitlines() or [''])[0][:200]
            raise ValueError(f'damaged checkpoint {ckpt_path}: {type(exc).__name__}: {first}') from None
        _LOG.info('resumed from %s at epoch %d', ckpt_path, start_epoch)

    metrics_file = run / 'metrics.csv'
    # rows of epochs after the checkpoint (killed before it was written) are trained again: drop them
    dropped = truncate_csv(metrics_file, lambda row: int(row['epoch']) <= start_epoch)
    if dropped:
        _LOG.info('metrics.csv: dropped %d rows logged after the checkpoint', dropped)
    last: dict = {}
    t_start = time.perf_counter() - elapsed
    for epoch in range(start_epoch, cfg.epochs):
        model.train()
        rng = np.random.default_rng([cfg.seed, epoch])      # per-epoch streams: resumable
        torch.manual_seed(cfg.seed * 100_003 + epoch)
        order = rng.permutation(train_idx)
        acc = np.zeros(4)
        done = 0
        bar = tqdm(range(steps_per_epoch), desc=f'epoch {epoch + 1}/{cfg.epochs}', disable=not progress,
                   leave=False)
        for i in bar:
            b = order[i * cfg.batch_size:(i + 1) * cfg.batch_size]
            x = _batch_inputs(frames, b, rng, noise_cfg, cfg.noise_prob, model.cfg).to(device)
            d, xyz, vis = (v.to(device) for v in _targets(frames, b))
            kl_scale = min(1.0, (step + 1) / max(1.0, cfg.kl_warmup_epochs * steps_per_epoch))
            lr = _lr_at(step, total_steps, cfg, time.perf_counter() - t_start)
            for g in opt.param_groups:
                g['lr'] = lr
            x = x.contiguous(memory_format=torch.channels_last)
            terms = cmvae_loss(model(x), d, xyz, vis, loss_cfg, kl_scale)
            opt.zero_grad(set_to_none=True)
            terms.total.backward()
            opt.step()
            step += 1
            done += 1
            values = [float(t.detach()) for t in terms]
            if not all(math.isfinite(v) for v in values):
                raise ValueError(f'training diverged at epoch {epoch + 1}, step {step}: the loss is {values[0]} '
                                 f'(try a lower --lr); {run} keeps the last finite model')
            acc += values
            bar.set_postfix(loss=f'{acc[0] / done:.1f}', kl=f'{acc[3] / done:.1f}')
            if cfg.max_minutes > 0 and time.perf_counter() - t_start >= 60.0 * cfg.max_minutes:
                break   # budget spent: validate and save what we have (counts as the last epoch)
        bar.close()
        train_means = acc / max(done, 1)
        val = evaluate_split(model, frames, val_idx, loss_cfg, noise_cfg, seed=cfg.seed + 1) \
            if len(val_idx) else {}
        elapsed = time.perf_counter() - t_start
        row = {'epoch': epoch + 1, 'step': step, 'elapsed_s': round(elapsed, 1),
               'lr': lr,
               'train_loss': train_means[0], 'train_depth_loss': train_means[1],
               'train_xyz_loss': train_means[2], 'train_kl': train_means[3],
               **{f'val_{k}': v for k, v in val.items()}}
        new_file = not metrics_file.exists()
        with open(metrics_file, 'a', newline='', encoding='utf-8') as fh:
            w = csv.DictWriter(fh, fieldnames=list(row))
            if new_file:
                w.writeheader()
            w.writerow(row)
            fh.flush()
            os.fsync(fh.fileno())       # durable before the checkpoint that counts it
        plot_curves(metrics_file, run / 'learning_curve.png', 'epoch',
                    [['train_loss', 'val_loss'], ['train_depth_loss', 'val_depth_loss'],
                     ['train_xyz_loss', 'val_xyz_loss']], title=f'train_cmvae {run.name}')
        meta = {'epoch': epoch + 1, 'train_frames': int(len(train_idx)), 'val_frames': int(len(val_idx)),
                'data_dir': cfg.data_dir, 'train_seconds': round(elapsed, 1),
                **{k: float(v) for k, v in val.items()}}
        score = val.get('loss', train_means[0])
        if score < best:
            best = score
            save_model(run / 'best.pt', model, meta)
        save_model(run / 'model.pt', model, meta)
        with atomic_path(ckpt_path) as tmp:   # an interrupted save keeps the old checkpoint
            torch.save({'model': model.state_dict(), 'optimizer': opt.state_dict(), 'epoch': epoch,
                        'step': step, 'best': best, 'elapsed_s': elapsed}, tmp)
        _LOG.info('epoch %d: %s', epoch + 1,
                  ', '.join(f'{k}={v:.4g}' for k, v in row.items() if isinstance(v, float)))
        last = row
        if cfg.stop_after_epoch and epoch + 1 >= cfg.stop_after_epoch:
            break
        if cfg.max_minutes > 0 and elapsed >= cfg.max_minutes * 60:
            _LOG.info('time budget of %.1f min reached after epoch %d', cfg.max_minutes, epoch + 1)
            break
    return last


def main(argv: list[str] | None = None) -> int:
    """Console entry point `train_cmvae`."""
    logging.basicConfig(level=logging.INFO, format='[%(levelname)s] %(name)s: %(message)s')
    cfg, args = parse_settings(TrainConfig, 'Train the denoising CM-VAE (see TrainConfig).', argv,
                               {'--no-progress': {'action': 'store_true', 'help': 'hide progress bars'}},
                               prog='train_cmvae')
    try:
        check_run_dir(cfg)
        training_device(cfg.device)         # --device cuda without a GPU: refused before any work
    except SettingsError as exc:
        exit_error('train_cmvae', str(exc), 2)
    try:
        last = train(cfg, progress=not args.no_progress)
    except (ValueError, OSError) as exc:       # damaged checkpoint or dataset, diverged run, disk full
        _LOG.debug('train_cmvae failed', exc_info=True)
        exit_error('train_cmvae', exc, 1)
    print(json.dumps(last, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
