"""Depth noise model G (x_D = G(y_D)) imitating an Intel RealSense D435i stereo depth camera.

Clean metric depth from the simulator is degraded in this order (every effect has a parameter
in `NoiseConfig`, and each can be switched off by setting its probability/coefficient to 0):

1. range limits: depth below `min_range_m` or above `max_range_m` becomes a hole (0);
2. axial noise: Gaussian with standard deviation `sigma_z2 * z**2` (stereo error grows with the
   square of distance);
3. disparity quantisation: disparity d = f*b/z is rounded to `disparity_step_px` sub-pixel steps,
   so the depth step also grows with z**2; then depth is rounded to `depth_unit_m` (16UC1 mm);
4. depth discontinuities: pixels within `edge_band_px` of a jump larger than `edge_threshold_m`
   become holes with probability `edge_hole_prob`; of the rest of that band a fraction
   `flying_pixel_prob` become "flying pixels" with a depth uniformly between the near and far
   side of the jump;
5. surface-dependent holes: dark (IR-absorbing) surfaces, RGB luminance below `dark_threshold`,
   lose depth with probability `dark_hole_prob`;
6. isolated dropouts: any pixel is a hole with probability `base_hole_prob`;
7. dropout blobs: a Poisson(`blob_rate`) number of elliptical holes per frame, semi-axes uniform
   in `blob_radius_frac` times the image width.

Holes are 0 (as in the RealSense driver). Input holes (0 or NaN) stay holes.

`frame_rng(seed, stamp_ns)` is the generator encoder_node draws one frame's noise from: a function of
the node's `noise_seed` and the frame's header stamp only (not of the frames before it, nor of which
frames the node dropped), so a replay of a recorded flight re-applies the very noise the encoder saw.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from assist_common.settings import check_named, setting


@dataclass
class NoiseConfig:
    """Parameters of the D435i-like depth noise model (defaults are for 64x64 images)."""

    min_range_m: float = setting(0.28, ge=0)  # D435i minimum depth at 848x480
    max_range_m: float = 10.0            # usable range
    sigma_z2: float = setting(0.01, ge=0)  # axial std = sigma_z2 * z^2 (2 % at 2 m, the D435i spec)
    focal_baseline_px_m: float = setting(21.0, gt=0)  # f (px, 848x480) * baseline (0.05 m)
    disparity_step_px: float = setting(0.08, ge=0)  # sub-pixel disparity resolution; 0 disables
    depth_unit_m: float = setting(0.001, ge=0)  # output rounding (16UC1 millimetres); 0 disables
    edge_threshold_m: float = setting(0.1, ge=0)  # neighbour depth jump that counts as a discontinuity
    edge_band_px: int = setting(1, ge=0)  # half-width of the band around a discontinuity
    edge_hole_prob: float = setting(0.5, ge=0, le=1)  # band pixel -> hole
    flying_pixel_prob: float = setting(0.3, ge=0, le=1)  # remaining band pixel -> flying pixel
    dark_threshold: float = 0.12         # luminance (0..1) below which a surface is "dark"
    dark_hole_prob: float = setting(0.5, ge=0, le=1)  # dark pixel -> hole
    base_hole_prob: float = setting(0.01, ge=0, le=1)  # any pixel -> hole
    blob_rate: float = setting(1.0, ge=0)  # mean number of dropout blobs per frame
    blob_radius_frac: tuple[float, float] = (0.03, 0.12)   # blob semi-axes / image width

    def __post_init__(self) -> None:
        """Validate ranges so a bad config fails loudly at construction (SettingsError, one line)."""
        check_named(self, type(self).__name__)
        if self.max_range_m <= self.min_range_m:
            raise ValueError('NoiseConfig.max_range_m must exceed min_range_m')
        lo, hi = self.blob_radius_frac
        if not 0 < lo <= hi:
            raise ValueError('NoiseConfig.blob_radius_frac must satisfy 0 < lo <= hi')


def frame_rng(seed: int, stamp_ns: int) -> np.random.Generator:
    """Noise generator of one frame: seeded by (seed, the frame's header stamp in ns) alone; ValueError if negative."""
    seed, stamp_ns = int(seed), int(stamp_ns)
    if seed < 0 or stamp_ns < 0:
        raise ValueError(f'frame_rng: seed {seed} and stamp {stamp_ns} ns must be >= 0')
    return np.random.default_rng([seed, stamp_ns])


def _neighbour_extremum(z: np.ndarray, radius: int, op) -> np.ndarray:
    """cv2.erode (min) or cv2.dilate (max) of z over a (2r+1)^2 window (edge-replicated), batched over (N,H,W)."""
    zf = np.ascontiguousarray(z, dtype=np.float32)
    if radius == 0:
        return zf.copy()
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    out = np.empty_like(zf)
    for i in range(zf.shape[0]):
        out[i] = op(zf[i], kernel, borderType=cv2.BORDER_REPLICATE)
    return out


def _neighbour_extrema(z: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Min and max of z over a (2r+1)^2 window per pixel (edge-replicated), batched over (N,H,W)."""
    return _neighbour_extremum(z, radius, cv2.erode), _neighbour_extremum(z, radius, cv2.dilate)


def discontinuity_band(depth: np.ndarray, threshold_m: float, band_px: int) -> np.ndarray:
    """Boolean mask of pixels within `band_px` of a 4-neighbour depth jump above `threshold_m`."""
    z = np.asarray(depth, dtype=np.float32)
    squeeze = z.ndim == 2
    if squeeze:
        z = z[None]
    jump = np.zeros(z.shape, dtype=bool)
    dy = np.abs(np.diff(z, axis=1)) > threshold_m
    dx = np.abs(np.diff(z, axis=2)) > threshold_m
    jump[:, 1:, :] |= dy
    jump[:, :-1, :] |= dy
    jump[:, :, 1:] |= dx
    jump[:, :, :-1] |= dx
    if band_px > 1:
        jump = _neighbour_extremum(jump.astype(np.float32), band_px - 1, cv2.dilate) > 0.5
    return jump[0] if squeeze else jump


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 601 luminance in [0,1] of uint8 RGB images (..., H, W, 3)."""
    rgb = np.asarray(rgb, dtype=np.float32) / 255.0
    return rgb[..., 0] * 0.299 + rgb[..., 1] * 0.587 + rgb[..., 2] * 0.114


_GRIDS: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}


def _pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """(yy, xx) float32 pixel coordinates of an h x w image, built once per size (read-only)."""
    grid = _GRIDS.get((h, w))
    if grid is None:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        yy.flags.writeable = xx.flags.writeable = False
        grid = _GRIDS[(h, w)] = (yy, xx)
    return grid


def _blob_mask(rng: np.random.Generator, n: int, h: int, w: int,
               rate: float, radius_frac: tuple[float, float]) -> np.ndarray:
    """Elliptical dropout blobs: a Poisson(rate) count per frame, random centre/axes/angle."""
    mask = np.zeros((n, h, w), dtype=bool)
    if rate <= 0:
        return mask
    counts = rng.poisson(rate, size=n)
    if not counts.any():
        return mask
    yy, xx = _pixel_grid(h, w)
    for i in np.nonzero(counts)[0]:
        for _ in range(int(counts[i])):
            cy, cx = rng.uniform(0, h), rng.uniform(0, w)
            a, b = rng.uniform(radius_frac[0], radius_frac[1], size=2) * w
            th = rng.uniform(0, np.pi)
            c, s = np.cos(th), np.sin(th)
            u = (xx - cx) * c + (yy - cy) * s
            v = -(xx - cx) * s + (yy - cy) * c
            mask[i] |= (u / a) ** 2 + (v / b) ** 2 <= 1.0
    return mask


def apply_depth_noise(depth: np.ndarray, rng: np.random.Generator,
                      cfg: NoiseConfig | None = None, rgb: np.ndarray | None = None) -> np.ndarray:
    """G: clean metric depth (H,W) or (N,H,W) -> noisy float32 depth, holes = 0.

    `rgb` (same leading shape + 3 channels, uint8) enables dark-surface holes; the input is
    never modified.
    """
    cfg = cfg or NoiseConfig()
    z = np.array(depth, dtype=np.float32, copy=True)
    squeeze = z.ndim == 2
    if squeeze:
        z = z[None]
    if z.ndim != 3:
        raise ValueError(f'depth must be (H,W) or (N,H,W), got shape {np.shape(depth)}')
    n, h, w = z.shape
    invalid = ~np.isfinite(z) | (z <= 0)
    z[invalid] = 0.0
    invalid |= (z < cfg.min_range_m) | (z > cfg.max_range_m)

    # discontinuities are a property of the clean scene
    band = discontinuity_band(np.where(invalid, 0.0, z), cfg.edge_threshold_m, cfg.edge_band_px)
    win = max(cfg.edge_band_px, 1)
    near = _neighbour_extremum(np.where(invalid, np.inf, z), win, cv2.erode)
    far = _neighbour_extremum(np.where(invalid, -np.inf, z), win, cv2.dilate)

    # axial noise growing with z^2
    noisy = z + rng.standard_normal(z.shape, dtype=np.float32) * (cfg.sigma_z2 * z * z)

    # flying pixels: a depth between the two sides of the jump
    u_band = rng.random(z.shape, dtype=np.float32)
    edge_hole = band & (u_band < cfg.edge_hole_prob)
    fly = band & ~edge_hole & (rng.random(z.shape, dtype=np.float32) < cfg.flying_pixel_prob)
    fly &= np.isfinite(near) & np.isfinite(far)
    if fly.any():
        t = rng.uniform(size=int(fly.sum())).astype(np.float32)
        noisy[fly] = near[fly] + t * (far[fly] - near[fly])

    # disparity quantisation and output units
    valid = noisy > 0
    if cfg.disparity_step_px > 0:
        d = cfg.focal_baseline_px_m / np.where(valid, noisy, 1.0)
        d = np.maximum(np.round(d / cfg.disparity_step_px), 1.0) * cfg.disparity_step_px
        noisy = np.where(valid, cfg.focal_baseline_px_m / d, 0.0).astype(np.float32)
    if cfg.depth_unit_m > 0:
        noisy = (np.round(noisy / cfg.depth_unit_m) * cfg.depth_unit_m).astype(np.float32)

    holes = invalid | edge_hole | ~(noisy > 0)
    if rgb is not None and cfg.dark_hole_prob > 0:
        lum = luminance(rgb)
        lum = lum[None] if lum.ndim == 2 else lum
        if lum.shape != z.shape:
            raise ValueError(f'rgb shape {np.shape(rgb)} does not match depth {np.shape(depth)}')
        holes |= (lum < cfg.dark_threshold) & (rng.random(z.shape, dtype=np.float32) < cfg.dark_hole_prob)
    if cfg.base_hole_prob > 0:
        holes |= rng.random(z.shape, dtype=np.float32) < cfg.base_hole_prob
    holes |= _blob_mask(rng, n, h, w, cfg.blob_rate, cfg.blob_radius_frac)
    noisy[holes] = 0.0
    noisy = noisy.astype(np.float32)
    return noisy[0] if squeeze else noisy
