"""RGB-D dataset for the CM-VAE: scenes from the sim's generator, a downward camera swept through each.

Per scene (50 frames by default) the camera base pose moves along the row of pads (x sorted
uniform from the start pose to past the last pad), y follows a random smooth curve, and the
altitude is uniform between `min_clearance_m` above whatever is below and `max_altitude_m`.

Labels per frame:
- clean metric depth (the renderer's linearised depth), stored as uint16 millimetres;
- the closest visible pad: a pad is *visible* when at least `min_pad_pixels` pixels of the clean
  depth image back-project onto its top surface (within `surface_tol_m` of its height and inside
  its footprint). Among visible pads the *closest* is the one whose top-surface centre is nearest
  in 3D to the camera's optical centre. Its label is that top-surface centre in the camera optical
  frame (x right, y down, z out of the lens), metres. The centre itself may lie outside the image.
- frames with no visible pad have `visible = False`, `pad_index = -1` and xyz = NaN; they are
  kept (the CM-VAE masks them out of the XYZ loss).

Shards: `shard_00000.npz` ... (compressed), each holding `scenes_per_shard` whole scenes, written
atomically, so a stopped run resumes by skipping complete shards; `meta.json` holds the config.
Scene j uses seeds derived from (seed, j) only, so the set is deterministic and resumable.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple
from collections.abc import Iterator, Sequence

import numpy as np

from assist_common.atomic import atomic_path, remove_stale_temporaries, write_text_atomic

from assist_common.settings import SettingsError, check_settings, exit_error, parse_settings, setting

DATASET_VERSION = 1
_LOG = logging.getLogger(__name__)


@dataclass
class DatasetConfig:
    """Settings of `make_dataset` (every field is a --flag; ranges checked before any work)."""

    out_dir: str = setting('data/cmvae', nonempty=True)       # shard directory
    frames: int = setting(50_000, ge=1, le=100_000_000)       # total frames (the paper's size)
    frames_per_scene: int = setting(50, ge=1, le=100_000)     # paper: 50 frames per generated scene
    scenes_per_shard: int = setting(20, ge=1, le=100_000)     # 1000 frames per shard
    seed: int = setting(0, ge=0, le=2**63 - 1)
    min_pad_pixels: int = setting(12, ge=1)                   # visible: >= this many top-surface pixels (of 64x64)
    surface_tol_m: float = setting(0.03, gt=0.0, le=1.0)      # back-projected point within this of the pad top
    min_clearance_m: float = setting(0.3, gt=0.0)             # base_link above the surface below it
    max_altitude_m: float = setting(4.5, gt=0.0)              # base_link above the floor
    x_before_m: float = setting(1.0, ge=0.0, le=50.0)         # sweep starts this far before the start pose
    x_after_m: float = setting(2.0, ge=0.0, le=50.0)          # ... and ends this far past the last pad
    y_amplitude_m: float = setting(1.5, ge=0.0, le=50.0)      # max amplitude of the lateral sweep curve
    y_offset_m: float = setting(0.8, ge=0.0, le=50.0)         # max constant lateral offset of the curve
    y_jitter_m: float = setting(0.2, ge=0.0, le=50.0)         # per-frame lateral jitter
    yaw_jitter_rad: float = setting(0.0, ge=0.0, le=math.pi)  # heading is held at 0 in the task
    overwrite: bool = False               # discard an existing, different dataset in out_dir

    def check_relations(self) -> None:
        """SettingsError unless the sweep fits the dataset world's camera (its pixels, near and far planes)."""
        from assist_sim.core.config import WorldConfig  # plain dataclasses (no pybullet)

        world = WorldConfig()
        cam = world.camera
        pixels = cam.width * cam.height
        if self.min_pad_pixels > pixels:
            raise SettingsError(f'--min-pad-pixels must be <= {pixels} (the {cam.width}x{cam.height} image), '
                                f'got {self.min_pad_pixels}')
        lowest = cam.near_m + cam.offset_below_base_m       # camera at least at its near plane above a surface
        if self.min_clearance_m < lowest:
            raise SettingsError(f'--min-clearance-m must be >= {lowest:g} (camera {cam.offset_below_base_m:g} m below '
                                f'base_link, near plane {cam.near_m:g} m), got {self.min_clearance_m:g}')
        ceiling = min(cam.far_m, world.scene.wall_height_m)
        if not self.min_clearance_m < self.max_altitude_m <= ceiling:
            raise SettingsError(f'--max-altitude-m must be above --min-clearance-m ({self.min_clearance_m:g}) and '
                                f'<= {ceiling:g} (the room\'s walls and the camera\'s far plane), '
                                f'got {self.max_altitude_m:g}')


class PadLabel(NamedTuple):
    """Closest-visible-pad label of one frame."""

    visible: bool
    index: int                   # pad index in the scene, -1 when none is visible
    xyz: np.ndarray              # (3,) optical frame metres, NaN when none is visible
    pixels: np.ndarray           # (n_pads,) top-surface pixel count of every pad


def backproject(depth: np.ndarray, K: np.ndarray, cam_pos: np.ndarray,
                r_world_from_optical: np.ndarray) -> np.ndarray:
    """Metric depth image (H,W) -> world points (H,W,3) (pinhole, depth along the optical axis)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x = (u - K[0, 2]) / K[0, 0] * depth
    y = (v - K[1, 2]) / K[1, 1] * depth
    pts = np.stack([x, y, depth.astype(np.float64)], axis=-1)
    return pts @ np.asarray(r_world_from_optical).T + np.asarray(cam_pos)


def pad_label(depth: np.ndarray, K: np.ndarray, cam_pos: np.ndarray,
              r_world_from_optical: np.ndarray, pads: Sequence, min_pixels: int,
              surface_tol_m: float) -> PadLabel:
    """Label a clean depth frame with the closest visible pad (definition in the module doc)."""
    pts = backproject(depth, K, cam_pos, r_world_from_optical)
    counts = np.zeros(len(pads), dtype=np.int32)
    for i, pad in enumerate(pads):
        on_top = np.abs(pts[..., 2] - pad.height) <= surface_tol_m
        counts[i] = int((on_top & pad.contains_xy(pts[..., :2])).sum())
    visible = np.nonzero(counts >= min_pixels)[0]
    if visible.size == 0:
        return PadLabel(False, -1, np.full(3, np.nan, np.float32), counts)
    tops = np.stack([pads[i].top_center for i in visible])
    best = int(visible[np.argmin(np.linalg.norm(tops - cam_pos, axis=1))])
    xyz = np.asarray(r_world_from_optical).T @ (pads[best].top_center - np.asarray(cam_pos))
    return PadLabel(True, best, xyz.astype(np.float32), counts)


def surface_height(pads: Sequence, xy: np.ndarray, margin: float) -> float:
    """Highest pad top under point xy (footprint grown by `margin`), else the floor (0)."""
    h = 0.0
    for pad in pads:
        if bool(pad.contains_xy(np.asarray(xy), margin=-margin)):
            h = max(h, pad.height)
    return h


def sweep_positions(scene, cfg: DatasetConfig, rng: np.random.Generator) -> np.ndarray:
    """(frames_per_scene, 3) base_link positions sweeping the downward camera through the scene."""
    n = cfg.frames_per_scene
    x0 = scene.start_position[0] - cfg.x_before_m
    x1 = scene.pads[-1].center[0] + cfg.x_after_m
    xs = np.sort(rng.uniform(x0, x1, size=n))
    amp = rng.uniform(0.0, cfg.y_amplitude_m)
    period = rng.uniform(4.0, 12.0)
    phase = rng.uniform(0.0, 2 * np.pi)
    offset = rng.uniform(-cfg.y_offset_m, cfg.y_offset_m)
    ys = offset + amp * np.sin(2 * np.pi * xs / period + phase) + rng.uniform(-1, 1, n) * cfg.y_jitter_m
    pos = np.zeros((n, 3))
    for k in range(n):
        floor = surface_height(scene.pads, np.array([xs[k], ys[k]]), margin=0.25)
        lo = floor + cfg.min_clearance_m
        pos[k] = (xs[k], ys[k], rng.uniform(lo, max(lo, cfg.max_altitude_m)))
    return pos


def scene_rngs(seed: int, scene_index: int) -> tuple[int, np.random.Generator]:
    """(scene seed, sweep rng) for scene `scene_index` of a dataset: depends on nothing else."""
    ss = np.random.SeedSequence([int(seed), int(scene_index)])
    scene_seed = int(ss.generate_state(1)[0] & 0x7FFFFFFF)
    return scene_seed, np.random.default_rng(ss.spawn(1)[0])


def render_scene(world, scene_index: int, cfg: DatasetConfig, n_frames: int) -> dict[str, np.ndarray]:
    """Render and label `n_frames` of scene `scene_index` in `world` (a LandingWorld)."""
    from assist_sim.core.scene import generate_scene  # sim core (no rclpy)
    scene_seed, rng = scene_rngs(cfg.seed, scene_index)
    scene = generate_scene(scene_seed, world.cfg.scene)
    world.reset(scene=scene, goal_index=0)
    positions = sweep_positions(scene, cfg, rng)[:n_frames]
    out = {k: [] for k in ('rgb', 'depth_mm', 'xyz', 'visible', 'pad_index', 'pad_pixels',
                           'base_position', 'yaw')}
    for pos in positions:
        yaw = float(rng.uniform(-cfg.yaw_jitter_rad, cfg.yaw_jitter_rad)) if cfg.yaw_jitter_rad else 0.0
        frame = world.render_from(pos, yaw)
        cam, r_wo = world.camera_pose(pos, yaw)
        lab = pad_label(frame.depth, frame.K, cam, r_wo, scene.pads, cfg.min_pad_pixels,
                        cfg.surface_tol_m)
        out['rgb'].append(frame.rgb)
        out['depth_mm'].append(np.clip(np.round(frame.depth * 1000.0), 0, 65535).astype(np.uint16))
        out['xyz'].append(lab.xyz)
        out['visible'].append(lab.visible)
        out['pad_index'].append(lab.index)
        out['pad_pixels'].append(lab.pixels)
        out['base_position'].append(pos.astype(np.float32))
        out['yaw'].append(yaw)
    arrays = {k: np.asarray(v) for k, v in out.items()}
    arrays['pad_index'] = arrays['pad_index'].astype(np.int8)
    arrays['pad_pixels'] = arrays['pad_pixels'].astype(np.int16)
    arrays['yaw'] = arrays['yaw'].astype(np.float32)
    arrays['scene'] = np.full(len(positions), scene_index, np.int32)
    arrays['scene_seed'] = np.full(len(positions), scene_seed, np.int64)
    return arrays


def _meta(cfg: DatasetConfig, world) -> dict:
    keep = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ('out_dir', 'overwrite')}
    return {'version': DATASET_VERSION, 'config': keep, 'K': world.camera_intrinsics.tolist(),
            'camera': dataclasses.asdict(world.cfg.camera), 'scene': dataclasses.asdict(world.cfg.scene)}


def shard_path(out_dir: Path, index: int) -> Path:
    """Path of shard `index`."""
    return Path(out_dir) / f'shard_{index:05d}.npz'


def _shard_ok(path: Path, n_expected: int) -> bool:
    try:
        with np.load(path) as z:
            return len(z['visible']) == n_expected
    except (OSError, ValueError, KeyError, EOFError) as exc:
        _LOG.warning('shard %s is unreadable (%s); regenerating it', path, exc)
        return False


def make_dataset(cfg: DatasetConfig, progress: bool = True) -> dict:
    """Generate (or complete) the dataset described by `cfg`; returns a summary with frames/s."""
    from tqdm import tqdm

    from assist_sim.core.config import WorldConfig
    from assist_sim.core.world import LandingWorld

    check_settings(cfg)
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for stale in remove_stale_temporaries(out):
        _LOG.info('removed %s (left by an interrupted run)', stale)
    world = LandingWorld(WorldConfig(), seed=cfg.seed)
    try:
        meta = json.loads(json.dumps(_meta(cfg, world)))   # tuples -> lists, as stored
        meta_file = out / 'meta.json'
        if meta_file.exists():
            old = json.loads(meta_file.read_text())
            if old != meta:
                if not cfg.overwrite:
                    raise ValueError(f'{out} holds a different dataset (meta.json differs); '
                                     'use another --out-dir or --overwrite')
                for f in out.glob('shard_*.npz'):
                    f.unlink()
        write_text_atomic(meta_file, json.dumps(meta, indent=1))
        n_scenes = -(-cfg.frames // cfg.frames_per_scene)
        n_shards = -(-n_scenes // cfg.scenes_per_shard)
        done_frames, new_frames, t0 = 0, 0, time.perf_counter()
        bar = tqdm(total=cfg.frames, unit='frame', disable=not progress, desc='make_dataset')
        for s in range(n_shards):
            first = s * cfg.scenes_per_shard * cfg.frames_per_scene
            n_in_shard = min(cfg.frames - first, cfg.scenes_per_shard * cfg.frames_per_scene)
            path = shard_path(out, s)
            if path.exists() and _shard_ok(path, n_in_shard):
                done_frames += n_in_shard
                bar.update(n_in_shard)
                continue
            parts, left = [], n_in_shard
            scene = s * cfg.scenes_per_shard
            while left > 0:
                k = min(left, cfg.frames_per_scene)
                parts.append(render_scene(world, scene, cfg, k))
                left -= k
                scene += 1
                bar.update(k)
            arrays = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
            with atomic_path(path) as tmp:
                np.savez_compressed(tmp, **arrays)
            new_frames += n_in_shard
        bar.close()
        dt = time.perf_counter() - t0
    finally:
        world.close()
    return {'out_dir': str(out), 'frames': cfg.frames, 'generated': new_frames,
            'reused': done_frames, 'seconds': dt,
            'frames_per_s': new_frames / dt if new_frames and dt > 0 else float('nan')}


@dataclass
class FrameSet:
    """A dataset loaded into memory (all arrays share the first axis)."""

    rgb: np.ndarray           # (N,64,64,3) uint8
    depth: np.ndarray         # (N,64,64) float32 metres (clean)
    xyz: np.ndarray           # (N,3) float32, NaN where not visible
    visible: np.ndarray       # (N,) bool
    scene: np.ndarray         # (N,) int32 scene index
    pad_index: np.ndarray     # (N,) int8
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.visible)

    def subset(self, idx: np.ndarray) -> FrameSet:
        """Rows `idx` as a new FrameSet."""
        return FrameSet(self.rgb[idx], self.depth[idx], self.xyz[idx], self.visible[idx],
                        self.scene[idx], self.pad_index[idx], self.meta)


def iter_shards(data_dir: str | Path) -> Iterator[Path]:
    """Shard files of a dataset directory in order."""
    return iter(sorted(Path(data_dir).glob('shard_[0-9]*[0-9].npz')))


def load_frames(data_dir: str | Path, max_frames: int | None = None) -> FrameSet:
    """Load every shard of `data_dir` (or the first `max_frames` frames) into memory."""
    data_dir = Path(data_dir)
    shards = list(iter_shards(data_dir))
    if not shards:
        raise FileNotFoundError(f'no dataset shards in {data_dir} (run make_dataset first)')
    cols = {k: [] for k in ('rgb', 'depth_mm', 'xyz', 'visible', 'scene', 'pad_index')}
    n = 0
    for path in shards:
        with np.load(path) as z:
            for k in cols:
                cols[k].append(z[k])
            n += len(z['visible'])
        if max_frames is not None and n >= max_frames:
            break
    a = {k: np.concatenate(v)[:max_frames] for k, v in cols.items()}
    meta_file = data_dir / 'meta.json'
    meta = json.loads(meta_file.read_text()) if meta_file.exists() else {}
    return FrameSet(a['rgb'], a['depth_mm'].astype(np.float32) / 1000.0, a['xyz'].astype(np.float32),
                    a['visible'].astype(bool), a['scene'], a['pad_index'], meta)


def split_by_scene(frames: FrameSet, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(train_idx, val_idx): whole scenes go to validation so held-out frames are unseen scenes."""
    scenes = np.unique(frames.scene)
    rng = np.random.default_rng(seed)
    n_val = max(1, int(round(val_fraction * len(scenes)))) if val_fraction > 0 else 0
    val_scenes = rng.choice(scenes, size=n_val, replace=False) if n_val else np.array([], int)
    is_val = np.isin(frames.scene, val_scenes)
    return np.nonzero(~is_val)[0], np.nonzero(is_val)[0]


def main(argv: list[str] | None = None) -> int:
    """Console entry point `make_dataset`."""
    logging.basicConfig(level=logging.INFO, format='[%(levelname)s] %(name)s: %(message)s')
    cfg, args = parse_settings(DatasetConfig, 'Generate the CM-VAE RGB-D dataset (compressed shards).',
                               argv, {'--no-progress': {'action': 'store_true', 'help': 'hide the progress bar'}},
                               prog='make_dataset')
    try:
        summary = make_dataset(cfg, progress=not args.no_progress)
        frames = load_frames(cfg.out_dir)
    except (ValueError, OSError) as exc:       # a different dataset in --out-dir, disk full, unwritable
        _LOG.debug('make_dataset failed', exc_info=True)
        exit_error('make_dataset', exc, 1)
    print(json.dumps({**summary, 'visible_fraction': float(frames.visible.mean())}, indent=1))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
