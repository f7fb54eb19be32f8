"""The scene as boxes for /sim/scene (visualization_msgs/MarkerArray): pure Python, no rclpy.

One box per platform in `odom` (ns ``platforms``, id = pad index, centre = box centre, size = box
size, yaw about +z); the goal pad once more in ns ``goal`` (id = pad index). Colours are each
pad's mean texture colour, so a viewer drawing plain boxes (the pilot station, RViz, Foxglove)
looks like the camera images; the goal copy is drawn in GOAL_RGBA.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .scene import SceneSpec
from .textures import make_texture

PLATFORMS_NS = 'platforms'
GOAL_NS = 'goal'
GOAL_RGBA = (0.95, 0.15, 0.1, 0.5)
_COLOUR_SAMPLE_PX = 16   # texture size averaged for a pad's colour (cheap, same mean as 64 px)


@dataclass(frozen=True)
class BoxMarker:
    """One CUBE marker: namespace, id, centre (odom ENU), yaw about +z, size (x, y, z), RGBA."""

    ns: str
    id: int
    center: tuple[float, float, float]
    yaw: float
    size: tuple[float, float, float]
    rgba: tuple[float, float, float, float]

    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        """Orientation (x, y, z, w) of a rotation by `yaw` about +z."""
        return (0.0, 0.0, math.sin(self.yaw / 2.0), math.cos(self.yaw / 2.0))


@lru_cache(maxsize=64)
def material_rgba(material: int) -> tuple[float, float, float, float]:
    """Mean colour of procedural material `material` as opaque RGBA in [0, 1]."""
    tex = make_texture(int(material), _COLOUR_SAMPLE_PX).reshape(-1, 3).astype(float)
    r, g, b = (float(c) / 255.0 for c in tex.mean(axis=0))
    return (r, g, b, 1.0)


def scene_markers(scene: SceneSpec, goal_index: int | None) -> list[BoxMarker]:
    """Boxes of every platform (ns 'platforms') and, when `goal_index` is set, the goal pad (ns 'goal')."""
    boxes = []
    for i, pad in enumerate(scene.pads):
        boxes.append(BoxMarker(ns=PLATFORMS_NS, id=i,
                               center=(float(pad.center[0]), float(pad.center[1]), float(pad.height) / 2.0),
                               yaw=float(pad.yaw), size=(float(pad.length), float(pad.width), float(pad.height)),
                               rgba=material_rgba(pad.material)))
    if goal_index is not None:
        if not 0 <= int(goal_index) < len(boxes):
            raise ValueError(f'goal_index {goal_index} out of range 0..{len(boxes) - 1}')
        g = boxes[int(goal_index)]
        boxes.append(BoxMarker(ns=GOAL_NS, id=g.id, center=g.center, yaw=g.yaw, size=g.size, rgba=GOAL_RGBA))
    if not all(np.isfinite(b.center).all() and np.isfinite(b.size).all() for b in boxes):
        raise ValueError('scene has a non-finite platform')
    return boxes
