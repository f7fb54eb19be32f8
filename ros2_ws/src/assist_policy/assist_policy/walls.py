"""Wall guard: the floor guard's second rule, not learned: no command carries the vehicle into a wall it has seen.

Why: a novice whose aim lies beyond the last pad can fly on toward the room's end wall at 4-5 m (the
held-out ``cautious`` family climbs to look before setting off), and there the learned actor, with no pad
in view, may push at full speed (a = (1, 1) m/s) the same way into the wall: a crash the assistant
causes (alone, the pilot hovers short of the wall until the time runs out; 2 of 110 cautious landings
without this rule). The downward camera sees a wall at the edge of its view, as a surface standing
higher than any landing pad.

Map: every depth frame is back-projected into odom (``recall.depth_points``: odometry position and
attitude, the camera ``camera_offset_m`` below base_link); a frame with at least ``wall_min_points``
pixels higher than ``wall_height_m`` over the floor (odom z = 0; pads stand 0.4-1.2 m, the pad map calls
such a region a wall too: ``RecallConfig.max_top_m``) marks the ``wall_cell_m`` cells those pixels fall
in as wall. The cells are remembered for the landing (a wall leaves the view as the vehicle descends);
past ``WALL_MAX_CELLS`` those farther than ``WALL_KEEP_M`` are forgotten. Frames larger than
``WALL_IMAGE_PX`` on their long side are subsampled first.

Rule (``WallGuard.apply``): for every wall cell within ``wall_radius_m`` horizontally of base_link,
nearest first, the part of the blended command's horizontal velocity V_xy that points at it is removed
(two passes), the pilot's as well as the actor's: like ArduPilot's simple avoidance, it stops the
approach. Moving away from a wall, climbing and descending are untouched; moving along one within reach
is slowed and turned away from it (the cells ahead along the wall are approached too). As the floor guard
does, it publishes what it imposed as the agent action a' = 2 V' - u. How near the wall it stops depends
on the height: the camera sees a point h over the floor at most (z_cam - h) tan(29 deg) to the side
(0.55 (z_cam - h) along an image axis), so a wall is marked 1.4 m away at 4.5 m and 0.8 m away at 3.5 m;
from 1 m/s the velocity controller stops within ~0.2 m. Below about 2.5 m the camera sees no wall point
higher than ``wall_height_m`` before it is within 0.3 m: low flight near walls is not covered, except
where the wall was marked from higher up. Pure numpy; no rclpy.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Hashable

import numpy as np

from assist_common.frames import heading, yaw_rotation

from .recall import cells_within, depth_points, subsample
from .safety import GuardResult, SafetyConfig
from .stage import COMMAND, Decision, Stage, StepContext

WALL_IMAGE_PX = 48          # frames larger than this on their long side are subsampled (walls span many pixels)
WALL_MAX_CELLS = 20_000     # more wall cells (a long flight): those farther than WALL_KEEP_M are forgotten
WALL_KEEP_M = 20.0


class WallGuard:
    """Walls seen in this landing's depth frames and the rule that keeps V off them (module docstring)."""

    def __init__(self, cfg: SafetyConfig | None = None):
        self.cfg = cfg or SafetyConfig()
        self.cells: set[tuple[int, int]] = set()

    @property
    def active(self) -> bool:
        """Whether the rule is on (the floor guard on and a positive wall radius)."""
        return bool(self.cfg.enabled and self.cfg.wall_radius_m > 0)

    def reset(self) -> None:
        """Forget the walls (new landing)."""
        self.cells.clear()

    def observe(self, depth: np.ndarray, position: np.ndarray, quaternion: np.ndarray | None = None) -> int:
        """Mark the wall cells this depth frame shows; returns how many wall pixels it had (0 when off)."""
        c = self.cfg
        if not self.active:
            return 0
        pts = depth_points(subsample(depth, WALL_IMAGE_PX), position, quaternion, c.camera_offset_m,
                           c.vertical_fov_deg).reshape(-1, 3)
        high = pts[np.isfinite(pts[:, 2]) & (pts[:, 2] >= c.wall_height_m)]
        if len(high) < c.wall_min_points:
            return 0
        cells = np.unique(np.floor(high[:, :2] / c.wall_cell_m).astype(np.int64), axis=0)
        self.cells.update(map(tuple, cells.tolist()))
        if len(self.cells) > WALL_MAX_CELLS:
            self.cells = cells_within(self.cells, np.asarray(position, dtype=float)[:2], c.wall_cell_m, WALL_KEEP_M)
        return len(high)

    def near(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distances, unit vectors in odom) from `xy` to the wall cell centres within wall_radius_m, nearest first."""
        c = self.cfg
        none = np.zeros(0), np.zeros((0, 2))
        if not self.cells:
            return none
        xy = np.asarray(xy, dtype=float)[:2]
        n = int(math.ceil(c.wall_radius_m / c.wall_cell_m)) + 1
        i0, j0 = int(math.floor(xy[0] / c.wall_cell_m)), int(math.floor(xy[1] / c.wall_cell_m))
        near = [(i, j) for i in range(i0 - n, i0 + n + 1) for j in range(j0 - n, j0 + n + 1) if (i, j) in self.cells]
        if not near:
            return none
        off = (np.array(near, dtype=float) + 0.5) * c.wall_cell_m - xy
        r = np.hypot(off[:, 0], off[:, 1])
        keep = np.argsort(r)[:int(np.sum(r <= c.wall_radius_m))]
        return r[keep], off[keep] / np.maximum(r[keep], 1e-9)[:, None]

    def apply(self, u: np.ndarray, agent: np.ndarray | None, velocity: np.ndarray, position: np.ndarray | None,
              quaternion: np.ndarray | None) -> GuardResult:
        """The command V (base_link) with its horizontal part toward the nearest wall within reach removed."""
        v = np.asarray(velocity, dtype=float).reshape(3)
        if not self.active or position is None:
            return GuardResult(agent, v, False, None)
        p = np.asarray(position, dtype=float).reshape(3)
        if not np.all(np.isfinite(p)):
            return GuardResult(agent, v, False, None)
        _, units = self.near(p[:2])
        if not len(units):
            return GuardResult(agent, v, False, None)
        yaw = 0.0 if quaternion is None else heading(quaternion)
        units = units @ yaw_rotation(-yaw)[:2, :2].T          # toward each wall cell, in base_link
        v_xy = v[:2].copy()
        for _ in range(2):                                     # a second pass: what one projection re-opened
            for n in units:
                toward = float(v_xy @ n)
                if toward > 0.0:
                    v_xy -= toward * n
        if np.allclose(v_xy, v[:2]):
            return GuardResult(agent, v, False, None)
        v_safe = np.array([v_xy[0], v_xy[1], v[2]])
        u = np.asarray(u, dtype=float).reshape(3)
        return GuardResult(2.0 * v_safe - u, v_safe, True, None)


# ----------------------------------------------------------------------------------------------- stage
class WallStage(Stage):
    """6. The wall rule: no command toward a wall seen within reach (the floor guard's switch and settings)."""

    key, phase, position = 'wall_guard', COMMAND, 20

    def __init__(self, walls: WallGuard, threshold: Callable[[], float]):
        self.walls, self._threshold = walls, threshold
        self._mapped: Hashable = None

    def reset(self) -> None:
        """Forget the wall map."""
        self.walls.reset()
        self._mapped = None

    def apply(self, ctx: StepContext, d: Decision) -> Decision | None:
        """V without its part toward the nearest walls, or None."""
        if ctx.frame is None or not self.walls.active:
            return None
        if self._mapped != ctx.frame.key:
            self.walls.observe(ctx.frame.image, *ctx.frame.pose)
            self._mapped = ctx.frame.key
        active = d.agent is not None and float(np.linalg.norm(d.agent)) > self._threshold()
        w = self.walls.apply(ctx.u, d.agent if active else None, d.velocity, ctx.position, ctx.quaternion)
        return Decision(w.agent, w.velocity, self.key, 'floor guard: approach to a wall stopped') if w.engaged else None
