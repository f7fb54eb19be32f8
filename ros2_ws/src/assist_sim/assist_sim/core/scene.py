"""Scene generator: five textured landing pads in a row, walls and floor (paper, CM-VAE section)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import SceneConfig


@dataclass(frozen=True)
class PadSpec:
    """One landing platform: a yawed box standing on the floor."""

    center: tuple[float, float]   # (x, y) of the box centre, odom ENU
    length: float                 # extent along the pad's own x axis (m)
    width: float                  # extent along the pad's own y axis (m)
    height: float                 # top surface height above the floor (m)
    yaw: float                    # rad, about +z
    material: int                 # texture index

    @property
    def top_center(self) -> np.ndarray:
        """Centre of the top surface, odom ENU (the goal point of the contract)."""
        return np.array([self.center[0], self.center[1], self.height], dtype=float)

    def contains_xy(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether world points (..., 2) lie over the top surface (shrunk by `margin`)."""
        xy = np.asarray(xy, dtype=float)
        d = xy - np.asarray(self.center)
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        lx = c * d[..., 0] + s * d[..., 1]
        ly = -s * d[..., 0] + c * d[..., 1]
        return (np.abs(lx) <= self.length / 2 - margin) & (np.abs(ly) <= self.width / 2 - margin)


@dataclass(frozen=True)
class SceneSpec:
    """A whole generated scene; everything needed to build it again."""

    seed: int
    pads: tuple[PadSpec, ...]
    floor_material: int
    wall_material: int
    start_position: tuple[float, float, float]
    room_min: tuple[float, float] = field(default=(-6.0, -6.0))
    room_max: tuple[float, float] = field(default=(30.0, 6.0))
    wall_height: float = 6.0

    @property
    def pad_top_centers(self) -> np.ndarray:
        """(n_pads, 3) top-surface centres."""
        return np.stack([p.top_center for p in self.pads])


def generate_scene(seed: int | np.random.Generator, cfg: SceneConfig | None = None) -> SceneSpec:
    """Draw a scene: pads along +x with random spacing, size, height, shift, yaw and textures."""
    cfg = cfg or SceneConfig()
    if isinstance(seed, np.random.Generator):
        rng = seed
        seed_value = int(rng.integers(0, 2**31 - 1))
        rng = np.random.default_rng(seed_value)
    else:
        seed_value = int(seed)
        rng = np.random.default_rng(seed_value)
    materials = rng.permutation(cfg.n_materials)
    x = rng.uniform(*cfg.first_pad_x_m)
    pads = []
    for i in range(cfg.n_pads):
        if i > 0:
            x += rng.uniform(*cfg.gap_m)
        pads.append(PadSpec(
            center=(float(x + rng.uniform(-cfg.longitudinal_jitter_m, cfg.longitudinal_jitter_m)),
                    float(rng.uniform(-cfg.lateral_shift_m, cfg.lateral_shift_m))),
            length=float(rng.uniform(*cfg.length_m)),
            width=float(rng.uniform(*cfg.width_m)),
            height=float(rng.uniform(*cfg.height_m)),
            yaw=float(rng.uniform(-cfg.max_yaw_rad, cfg.max_yaw_rad)),
            material=int(materials[i]),
        ))
    start = (float(rng.uniform(*cfg.start_x_m)), float(rng.uniform(*cfg.start_y_m)),
             float(rng.uniform(*cfg.start_altitude_m)))
    xs = [p.center[0] for p in pads]
    room_min = (min(start[0], xs[0]) - cfg.wall_margin_m, -cfg.room_half_width_m)
    room_max = (xs[-1] + cfg.wall_margin_m, cfg.room_half_width_m)
    return SceneSpec(seed=seed_value, pads=tuple(pads), floor_material=int(materials[cfg.n_pads]),
                     wall_material=int(materials[cfg.n_pads + 1]), start_position=start,
                     room_min=room_min, room_max=room_max, wall_height=cfg.wall_height_m)
