"""Link section of `make bench`: what image_relay sends over the radio, what compressing and restoring a pair costs,
and what JPEG quality does to the CM-VAE's pad estimate (on held-out sim frames with true pad positions)."""
from __future__ import annotations

import tempfile
import time

import numpy as np

QUALITIES = (30, 50, 75, 90, 95)
FRAMES = 400            # 20 scenes of 20 frames, rendered like the CM-VAE's data (seed 7: not its training scenes)
RATE_HZ = 20.0


def run() -> list[dict]:
    """Measure and return rows (name, value, unit, target)."""
    import torch

    from assist_bridge.image_link import COLOR_FORMAT, DEPTH_FORMAT, LinkConfig, decode_color, decode_depth, pack_pair
    from assist_lab.cmvae_dataset import DatasetConfig, load_frames, make_dataset
    from assist_perception.encoder_core import LatentEncoder

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        make_dataset(DatasetConfig(out_dir=tmp, frames=FRAMES, frames_per_scene=20, scenes_per_shard=20, seed=7),
                     progress=False)
        frames = load_frames(tmp)
    encoder = LatentEncoder()
    rows = []
    vis = np.flatnonzero(frames.visible)

    def pad_error(rgbs: np.ndarray, depths: np.ndarray) -> float:
        errs = [np.linalg.norm(encoder.encode(rgbs[i], depths[i]).pad_xyz - frames.xyz[i]) for i in vis]
        return float(np.median(errs))

    base = pad_error(frames.rgb, frames.depth)
    rows.append({'name': f'pad estimate error, raw frames ({len(vis)} with a pad in view)', 'value': base,
                 'unit': 'm (median)'})
    for q in QUALITIES:
        cfg = LinkConfig(jpeg_quality=q)
        sizes, enc_s, dec_s, rgbs, depths = [], [], [], [], []
        for rgb, depth in zip(frames.rgb, frames.depth):
            t0 = time.perf_counter()
            jpeg, png = pack_pair(rgb, depth, cfg)
            t1 = time.perf_counter()
            rgbs.append(decode_color(jpeg, COLOR_FORMAT))
            depths.append(decode_depth(png, DEPTH_FORMAT).astype(np.float32) * np.float32(0.001))
            dec_s.append(time.perf_counter() - t1)
            enc_s.append(t1 - t0)
            sizes.append(len(jpeg) + len(png))
        err = pad_error(np.stack(rgbs), np.stack(depths))
        rows.append({'name': f'JPEG {q}: link payload at {RATE_HZ:g} Hz (64x64 pair)',
                     'value': np.mean(sizes) * RATE_HZ / 1000, 'unit': 'kB/s'})
        rows.append({'name': f'JPEG {q}: pad estimate error through the link', 'value': err, 'unit': 'm (median)',
                     'target': f'raw {base:.3f}'})
        if q == LinkConfig().jpeg_quality:
            rows.append({'name': f'JPEG {q}: compress + restore one pair (CPU, relay + decoder)',
                         'value': 1e3 * (np.median(enc_s) + np.median(dec_s)), 'unit': 'ms (median)'})
    raw = frames.rgb[0].nbytes + frames.depth[0].nbytes
    rows.append({'name': f'raw 64x64 pair (rgb8 + 32FC1) at {RATE_HZ:g} Hz, for comparison',
                 'value': raw * RATE_HZ / 1000, 'unit': 'kB/s'})
    return rows
