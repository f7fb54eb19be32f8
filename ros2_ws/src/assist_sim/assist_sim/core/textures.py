"""Deterministic procedural materials (the paper used 52 textures on pads, walls and floor)."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from assist_common.cache import scratch_dir

TEXTURE_VERSION = 1
_PATTERNS = ('checker', 'stripes', 'noise', 'bricks', 'wood', 'dots', 'tiles', 'gradient',
             'marble', 'grid', 'plaid', 'speckle', 'hexish')


def _palette(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two contrasting colours drawn in HSV so materials differ in hue and brightness."""
    h = rng.uniform(0, 180)
    s = rng.uniform(40, 230)
    v1, v2 = sorted(rng.uniform(40, 250, size=2))
    if v2 - v1 < 50:
        v2 = min(255.0, v1 + 60)
    hsv = np.array([[[h, s, v1], [(h + rng.uniform(0, 60)) % 180, s * rng.uniform(0.5, 1.0), v2]]],
                   dtype=np.float32)
    rgb = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)[0].astype(np.float32)
    return rgb[0], rgb[1]


def _smooth_noise(rng: np.random.Generator, n: int, cells: int) -> np.ndarray:
    """Value noise in [0,1] at a given cell count, bicubic upsampled (tileable enough)."""
    base = rng.uniform(0, 1, size=(cells, cells)).astype(np.float32)
    return np.clip(cv2.resize(base, (n, n), interpolation=cv2.INTER_CUBIC), 0, 1)


def make_texture(index: int, size: int = 64) -> np.ndarray:
    """Material `index` as an RGB uint8 image (size x size); same index -> same image."""
    rng = np.random.default_rng([TEXTURE_VERSION, index])
    pattern = _PATTERNS[index % len(_PATTERNS)]
    c1, c2 = _palette(rng)
    n = size
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32) / n
    period = rng.integers(2, 9)
    if pattern == 'checker':
        m = ((np.floor(xx * period) + np.floor(yy * period)) % 2).astype(np.float32)
    elif pattern == 'stripes':
        ang = rng.uniform(0, np.pi)
        m = (np.sin(2 * np.pi * period * (xx * np.cos(ang) + yy * np.sin(ang))) > 0).astype(np.float32)
    elif pattern == 'noise':
        m = _smooth_noise(rng, n, int(rng.integers(4, 12)))
    elif pattern == 'bricks':
        rows = period
        row = np.floor(yy * rows)
        shift = (row % 2) * 0.5 / rows * 2
        m = (((yy * rows) % 1 < 0.12) | (((xx + shift) * rows / 2) % 1 < 0.06)).astype(np.float32)
    elif pattern == 'wood':
        m = (np.sin(2 * np.pi * (period * 2 * xx + 3 * _smooth_noise(rng, n, 4))) + 1) / 2
    elif pattern == 'dots':
        cx, cy = (xx * period) % 1 - 0.5, (yy * period) % 1 - 0.5
        m = ((cx ** 2 + cy ** 2) < rng.uniform(0.04, 0.16)).astype(np.float32)
    elif pattern == 'tiles':
        m = ((((xx * period) % 1) < 0.9) & (((yy * period) % 1) < 0.9)).astype(np.float32)
        m *= 0.6 + 0.4 * _smooth_noise(rng, n, period * 2)
    elif pattern == 'gradient':
        m = np.clip(xx * rng.uniform(0.5, 1.0) + yy * rng.uniform(0, 0.5), 0, 1)
        m = m * 0.7 + 0.3 * _smooth_noise(rng, n, 16)
    elif pattern == 'marble':
        m = (np.sin(2 * np.pi * (xx + yy) * period + 6 * _smooth_noise(rng, n, 6)) + 1) / 2
    elif pattern == 'grid':
        m = ((((xx * period) % 1) < 0.08) | (((yy * period) % 1) < 0.08)).astype(np.float32)
    elif pattern == 'plaid':
        m = 0.5 * (np.sin(2 * np.pi * period * xx) > 0.3) + 0.5 * (np.sin(2 * np.pi * period * yy) > 0.3)
    elif pattern == 'speckle':
        m = (rng.uniform(0, 1, size=(n, n)) < rng.uniform(0.1, 0.4)).astype(np.float32)
        m = cv2.GaussianBlur(m, (3, 3), 0)
    else:  # hexish: offset dots
        row = np.floor(yy * period)
        cx = ((xx * period + 0.5 * (row % 2)) % 1) - 0.5
        cy = (yy * period) % 1 - 0.5
        m = ((cx ** 2 + cy ** 2) < 0.12).astype(np.float32)
    grain = rng.uniform(0, 25)
    img = c1[None, None, :] * (1 - m[..., None]) + c2[None, None, :] * m[..., None]
    img += rng.normal(0, grain, size=img.shape).astype(np.float32) * 0.3
    return np.clip(img, 0, 255).astype(np.uint8)


def texture_cache_dir() -> Path:
    """Folder for generated texture PNGs in the user's cache (pybullet loads textures from files)."""
    return scratch_dir(f'textures_v{TEXTURE_VERSION}')


def texture_path(index: int, size: int = 64) -> Path:
    """Path of material `index` as PNG, generating it (atomically) on first use."""
    folder = texture_cache_dir()
    path = folder / f'material_{index:02d}_{size}.png'
    if not path.exists():
        folder.mkdir(parents=True, exist_ok=True)
        img = make_texture(index, size)
        tmp = folder / f'.{path.name}.{os.getpid()}.tmp.png'
        cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        os.replace(tmp, path)
    return path
