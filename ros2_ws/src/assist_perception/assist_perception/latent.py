"""Latent feature for the latent condition: RGB-D frame -> CM-VAE encoder mean mu.

Uses the perception package's own inference pipeline (assist_perception.encoder_core.LatentEncoder,
the one encoder_node runs); nothing of it is copied here. In simulation the depth is first passed
through the perception package's D435i-like noise model G (the encoder was trained on noisy input
and the real camera is noisy) unless depth_noise=False; measured on 40 sim frames the noise moves
mu by 0.04-0.2 (rms per dimension) against a 0.5-2.0 spread across frames.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def default_encoder_path() -> Path:
    """The shipped CM-VAE weights (perception package's default: models/cmvae.pt); ValueError if missing."""
    try:
        from assist_perception.encoder_core import default_model_path
    except ImportError as exc:
        raise ValueError(f'latent condition needs assist_perception: {exc}') from exc
    path = default_model_path()
    if not path.is_file():
        raise ValueError(f'no shipped CM-VAE weights at {path}')
    return path


class LatentFn:
    """fn(rgb uint8 HxWx3, depth m HxW) -> mu (latent_dim,) through the CM-VAE, with the sim's depth noise.

    `reset(episode_seed)` starts a landing: the depth noise is re-seeded from (seed, episode_seed) and the
    repeated latent goes back to zeros, so a landing depends on its own seed only, not on the landings
    flown before it with the same env. A frame the encoder rejects (e.g. no valid depth) repeats the
    previous mu (zeros at first) and is logged. Called with a frame's header stamp (`stamp_ns`), the frame's
    noise comes from (seed, stamp) instead (`assist_perception.noise.frame_rng`), as encoder_node draws it:
    replay_assist re-encodes a graph's recording that way.
    """

    def __init__(self, encoder, depth_noise: bool, seed: int):
        from assist_perception.encoder_core import BadFrame
        from assist_perception.level import DEFAULT_MIN_TILT_DEG, level_frame, level_rotation, tilt_deg
        from assist_perception.noise import apply_depth_noise, frame_rng
        self._encoder, self._apply_noise, self._frame_rng = encoder, apply_depth_noise, frame_rng
        self._level_frame, self._level_rotation, self._tilt_deg = level_frame, level_rotation, tilt_deg
        self.level_min_tilt_deg = DEFAULT_MIN_TILT_DEG     # encoder_node's level_camera default
        self.levelled = 0
        self._bad_frame = BadFrame
        self.depth_noise = bool(depth_noise)
        self.seed = int(seed)
        self.latent_dim = int(encoder.latent_dim)
        self.rejected = 0
        self.last_input: tuple[np.ndarray, np.ndarray] | None = None   # the frame as the encoder saw it
        self.reset(None)

    def reset(self, episode_seed: int | None) -> None:
        """New landing: depth noise from (seed, episode_seed) (seed alone for None); no previous latent."""
        key = [self.seed] if episode_seed is None else [self.seed, int(episode_seed)]
        self._rng = np.random.default_rng(key)
        self._mu = np.zeros(self.latent_dim)

    def __call__(self, rgb: np.ndarray, depth: np.ndarray, stamp_ns: int | None = None,
                 level: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """The encoder mean of this frame (the previous one if the encoder rejects the frame); `stamp_ns`: the
        frame's noise from (seed, stamp) as encoder_node draws it, else from the landing's generator;
        `level` = (K, base_link quaternion): re-render a tilted frame as a level camera would see it, after the
        noise, as encoder_node's level_camera does (an airframe that leans, e.g. the ArduCopter plant)."""
        if self.depth_noise:
            rng = self._rng if stamp_ns is None else self._frame_rng(self.seed, stamp_ns)
            d = self._apply_noise(depth, rng, rgb=rgb if np.shape(rgb)[:2] == np.shape(depth) else None)
        else:
            d = depth
        if level is not None:
            r = self._level_rotation(level[1])
            if self._tilt_deg(r) >= self.level_min_tilt_deg:
                rgb, d = self._level_frame(rgb, d, level[0], r)
                self.levelled += 1
        self.last_input = (rgb, d)      # evaluate --record-dir saves it
        try:
            self._mu = np.asarray(self._encoder.encode(rgb, d, want_xyz=False).mu, dtype=float)
        except self._bad_frame as exc:
            # expected on the pad: the camera is inside the depth sensor's minimum range
            self.rejected += 1
            level = logging.INFO if self.rejected == 1 else logging.DEBUG
            log.log(level, 'encoder rejected a frame (%s); repeating the previous latent (%d so far; '
                    'further rejections are logged at debug level)', exc, self.rejected)
        return self._mu.copy()


def make_latent_fn(model_path: str | Path | None = None, depth_noise: bool = True, seed: int = 0,
                   ) -> tuple[LatentFn, int]:
    """Load the CM-VAE; returns (LatentFn, latent_dim). `seed` is the depth noise's base seed.

    Raises ValueError with a clear message when the package or weights are unavailable.
    """
    try:
        from assist_perception.encoder_core import LatentEncoder
        from assist_perception.model import ModelLoadError
    except ImportError as exc:
        raise ValueError(f'latent condition needs assist_perception (CM-VAE): {exc}') from exc
    path = Path(model_path) if model_path else default_encoder_path()
    try:
        encoder = LatentEncoder(path, threads=0)
    except (ModelLoadError, ValueError) as exc:
        raise ValueError(str(exc)) from exc
    fn = LatentFn(encoder, depth_noise, seed)
    return fn, fn.latent_dim
