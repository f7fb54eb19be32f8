"""Floor guard: an independent, non-learned safety layer over the blended command.

Rule: when base_link is lower than ``guard_height_m`` above the floor and the downward depth image
shows the floor (no pad) beneath every leg, a descending V is not passed through: its vertical
component is raised to a small climb (min_climb_mps). The layer acts on V = blend(u, a) whatever the actor did (it
also acts while the actor relinquishes, which is where the learned assistant fails: a pilot who
overshoots the last pad and descends with no pad in view). Its effect is published as the agent
action: the guard replaces a by a' = 2 V' - u, so blend(u, a') = V' and /assist/agent_cmd shows
what the assistant imposed (the simulated pilot then feels it, as it feels any assistance). Only
the vertical part of a is replaced; the actor's horizontal action is kept.

How "floor beneath the legs" is read from the depth image (optical z metres, invalid = 0 or NaN):
the floor's depth below the camera is altitude - camera_offset_m (odometry altitude over the floor,
camera looking straight down, tilt ignored); each leg's floor point projects to a pixel
(optical x = -body y, optical y = -body x); the median of the valid depths in a small window around
it is compared with the floor depth. A leg is over the floor when that median is within
``floor_tolerance_m`` of the floor depth, and over something (a pad) when it is nearer. A window
without valid pixels is unknown; the guard then does not act (it never blocks on missing data).
Pads in this world stand 0.4-1.2 m tall, so a tolerance of 0.2 m separates them from the floor.

Blind range: a camera closer to a surface than its minimum range cannot see it (the D435i returns
holes, which the guard treats as unknown; the simulator's renderer clips the surface at its near
plane and shows the floor behind it). So the guard remembers the last pad it saw beneath the legs
(its top height and the vehicle's x, y then) and does not block while the vehicle is still within
``pad_memory_radius_m`` of that spot and low enough for the camera to be inside ``blind_range_m`` of
that pad top: a vehicle touching down on a pad is never pushed back up. ``reset`` forgets it.

Edge rule (``edge_height_m`` > 0, 0.6 m by default): a descent is also held while the legs straddle a
pad edge (some legs over the floor, some over a pad) with the camera nearer than ``edge_height_m`` to
that pad: a touchdown there tips the vehicle over (the crashes left with the floor rule alone). It
watches up to ``edge_watch_m`` of altitude (pads stand up to 1.2 m tall). It is on by default because
the pad recall (assist_policy.recall) brings vehicles back to pads from beside them: with both on, the
two of 810 held-out landings that tip over without the edge rule become a success and an edge landing,
and nothing changes for the worse on the paper pilot (840 landings;
docs/experiments/2026-11-pad-recall-and-edge-rule.md). Without the pad recall (actor alone, edge height
0.5 m) it avoids as many crashes as it causes (three each).

Wall rule (``wall_radius_m`` > 0, 1.5 m by default; ``assist_policy.walls``): no
horizontal command toward a wall the camera has seen within that distance (surfaces higher than
``wall_height_m``, remembered for the landing).

``guard_height_m`` = 1.0 m: from a 1 m/s descent the velocity controller (kp_z 4 /s, 2.5 m/s^2)
stops within ~0.3 m, well above the judge's crash height (0.2 m), while pilots landing on a pad
are over the pad (not the floor) when they come this low. Pure numpy; no rclpy.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from assist_common.settings import check_named, setting
from .blending import blend
from .settings import node_param
from .stage import COMMAND, Decision, Parts, Rule, Stage, StepContext


@dataclass
class SafetyConfig:
    """Settings of the floor guard (policy_node parameters map onto these)."""

    enabled: bool = node_param(True, 'floor_guard', 'Floor guard (assist_policy.safety, not learned): low over the '
                               'floor with no pad under the legs in /camera/depth/image_raw, a descent is replaced '
                               'by a small climb.')
    # acts below this altitude of base_link over the floor
    guard_height_m: float = node_param(1.0, 'floor_guard_height_m', 'Altitude (odom z over the floor, m) below '
                                       'which the floor guard acts.', min=0.0, max=10.0)
    floor_tolerance_m: float = setting(0.2, ge=0)  # a leg's surface within this of the floor depth is the floor
    # vertical V imposed instead of a descent
    min_climb_mps: float = node_param(0.15, 'floor_guard_climb_mps', 'Vertical velocity the floor guard imposes '
                                      'instead of a descent (m/s; at least blend_threshold / 2 + 0.01 is used).',
                                      min=0.0, max=1.0)
    leg_offset_m: float = setting(0.15, ge=0)  # legs at (+-, +-) this in base_link (VehicleConfig.leg_offset_m)
    window_m: float = setting(0.06, gt=0)  # half-size, on the floor, of the patch checked under each leg
    camera_offset_m: float = setting(0.05, ge=0)  # optical centre below base_link (CameraConfig.offset_below_base_m)
    vertical_fov_deg: float = setting(58.0, gt=0, lt=180)  # depth camera vertical field of view (square pixels)
    blind_range_m: float = setting(0.3, ge=0)  # camera minimum range (D435i ~0.2-0.3 m; sim near plane 0.1 m) + margin
    # a pad seen beneath the legs is assumed still there within this (x, y)
    pad_memory_radius_m: float = setting(0.6, ge=0)
    # hold a descent straddling a pad edge nearer than this to the pad (0: off)
    edge_height_m: float = node_param(0.6, 'floor_guard_edge_height_m', 'Floor guard edge rule: a descent is held '
                                      'while the legs straddle a pad edge with the camera nearer than this to the '
                                      'pad (m; 0 = off).', min=0.0, max=5.0)
    edge_watch_m: float = setting(2.0, ge=0)  # the edge rule watches below this altitude
    # wall rule (assist_policy.walls): no V toward a wall seen within wall_radius_m (0: off)
    # a wall this close horizontally stops the approach to it
    wall_radius_m: float = node_param(1.5, 'floor_guard_wall_radius_m', 'Floor guard wall rule '
                                      '(assist_policy.walls): the part of /cmd_vel heading for a wall seen within '
                                      "this horizontal distance is removed, the pilot's as well as the actor's (m; "
                                      '0 = off).', min=0.0, max=10.0)
    # a surface this high over the floor is a wall (pads stand 0.4-1.2 m)
    wall_height_m: float = node_param(2.0, 'floor_guard_wall_height_m', 'Floor guard wall rule: a surface seen this '
                                      'high over the floor (odom z) is a wall (m; landing pads must stand lower).',
                                      min=0.1, max=50.0)
    wall_min_points: int = setting(4, ge=1)  # fewer such pixels in a frame: noise
    wall_cell_m: float = setting(0.25, gt=0)  # walls are remembered in cells of this size (m)

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self, type(self).__name__)


@dataclass
class GuardResult:
    """Outcome of one guard check: possibly replaced agent action and velocity, and why."""

    agent: np.ndarray | None
    velocity: np.ndarray
    engaged: bool
    floor: bool | None                # floor beneath every leg (None: unknown / not checked)


class FloorGuard:
    """Stateless floor guard (see module docstring); ``apply`` is the one definition of the rule."""

    def __init__(self, cfg: SafetyConfig | None = None):
        self.cfg = cfg or SafetyConfig()
        self._pad: tuple[float, float, float] | None = None   # x, y of the vehicle and top z of the pad seen

    @property
    def watch_height_m(self) -> float:
        """Below this altitude the guard reads the depth image (guard height + blind range; edge rule: edge_watch_m)."""
        base = self.cfg.guard_height_m + self.cfg.blind_range_m
        return max(base, self.cfg.edge_watch_m) if self.cfg.edge_height_m > 0 else base

    def reset(self) -> None:
        """Forget the last pad seen (new episode)."""
        self._pad = None

    def _near_remembered_pad(self, position: np.ndarray) -> bool:
        if self._pad is None:
            return False
        x, y, top = self._pad
        c = self.cfg
        return (math.hypot(position[0] - x, position[1] - y) < c.pad_memory_radius_m
                and position[2] - c.camera_offset_m - top < c.blind_range_m)

    def _remember_pad(self, legs: list[float | None], position: np.ndarray) -> None:
        """Store the top height of the surface under the legs (nearest of the leg depths `legs`) and where it
        was seen."""
        tops = [d for d in legs if d is not None]
        if tops:
            self._pad = (float(position[0]), float(position[1]),
                         float(position[2]) - self.cfg.camera_offset_m - min(tops))

    def _leg_depths(self, depth: np.ndarray, altitude_m: float) -> list[float | None]:
        """Median valid depth around each leg's floor point (None: no valid pixel), [] if not checkable."""
        c = self.cfg
        depth = np.asarray(depth, dtype=np.float32)
        if depth.ndim != 2 or depth.size == 0:
            raise ValueError(f'depth image must be HxW, got shape {depth.shape}')
        d_floor = float(altitude_m) - c.camera_offset_m
        if not math.isfinite(d_floor) or d_floor <= 0:
            return []
        h, w = depth.shape
        f = (h / 2.0) / math.tan(math.radians(c.vertical_fov_deg) / 2.0)
        cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
        half = max(1, int(round(f * c.window_m / d_floor)))
        out: list[float | None] = []
        for bx in (c.leg_offset_m, -c.leg_offset_m):
            for by in (c.leg_offset_m, -c.leg_offset_m):
                col = int(round(min(max(cx + f * (-by) / d_floor, 0), w - 1)))
                row = int(round(min(max(cy + f * (-bx) / d_floor, 0), h - 1)))
                patch = depth[max(0, row - half):row + half + 1, max(0, col - half):col + half + 1]
                valid = patch[np.isfinite(patch) & (patch > 0)]
                out.append(float(np.median(valid)) if valid.size else None)
        return out

    def floor_below(self, depth: np.ndarray, altitude_m: float) -> bool | None:
        """True when every leg's floor point shows the floor, False when any shows something nearer."""
        return self._floor_from(self._leg_depths(depth, altitude_m), altitude_m)

    def surface_below(self, depth: np.ndarray, position: np.ndarray) -> tuple[bool | None, float | None]:
        """(floor_below, base_link's height over the nearest surface under a leg in m; None where unknown).

        Inside the camera's blind range over the pad it last saw beneath the legs (see the module
        docstring) the depth image shows the floor behind that pad: the remembered pad top counts then.
        """
        p = np.asarray(position, dtype=float).reshape(3)
        if self._near_remembered_pad(p):
            return False, float(p[2]) - self._pad[2]
        legs = self._leg_depths(depth, float(p[2]))
        seen = [d for d in legs if d is not None]
        return self._floor_from(legs, float(p[2])), (min(seen) + self.cfg.camera_offset_m if seen else None)

    def _floor_from(self, legs: list[float | None], altitude_m: float) -> bool | None:
        """floor_below from the leg depths `legs` (_leg_depths)."""
        if not legs or any(d is None for d in legs):
            return None
        d_floor = float(altitude_m) - self.cfg.camera_offset_m
        return all(d >= d_floor - self.cfg.floor_tolerance_m for d in legs)

    def legs_on_pad(self, depth: np.ndarray, position: np.ndarray) -> bool | None:
        """True when every leg is over a surface nearer than the floor (a pad, no edge) or the camera is inside its
        blind range over the pad last seen under them, False when a leg is over the floor, None when a leg's
        window holds no valid depth."""
        p = np.asarray(position, dtype=float).reshape(3)
        if self._near_remembered_pad(p):
            return True
        legs = self._leg_depths(depth, float(p[2]))
        if not legs or any(d is None for d in legs):
            return None
        d_floor = float(p[2]) - self.cfg.camera_offset_m
        return all(d < d_floor - self.cfg.floor_tolerance_m for d in legs)

    def straddle_depth(self, depth: np.ndarray, altitude_m: float) -> float | None:
        """Depth of the nearest pad under a leg when other legs are over the floor (a pad edge), else None."""
        return self._straddle_from(self._leg_depths(depth, altitude_m), altitude_m)

    def _straddle_from(self, legs: list[float | None], altitude_m: float) -> float | None:
        """straddle_depth from the leg depths `legs` (_leg_depths)."""
        legs = [d for d in legs if d is not None]
        if not legs:
            return None
        d_floor = float(altitude_m) - self.cfg.camera_offset_m
        pad = [d for d in legs if d < d_floor - self.cfg.floor_tolerance_m]
        floor = [d for d in legs if d >= d_floor - self.cfg.floor_tolerance_m]
        return min(pad) if pad and floor else None

    def apply(self, u: np.ndarray, agent: np.ndarray | None, velocity: np.ndarray,
              depth: np.ndarray | None, position: np.ndarray | None, blend_threshold: float) -> GuardResult:
        """Guard one blended command V (= blend(u, agent)) at odom `position`; unchanged unless a floor descent."""
        v = np.asarray(velocity, dtype=float).reshape(3)
        c = self.cfg
        if (not c.enabled or depth is None or position is None
                or float(position[2]) >= self.watch_height_m):
            return GuardResult(agent, v, False, None)
        position = np.asarray(position, dtype=float).reshape(3)
        legs = self._leg_depths(depth, float(position[2]))     # once per step: the rules below all read them
        floor = self._floor_from(legs, float(position[2]))
        if floor is False:
            self._remember_pad(legs, position)      # watched from above the guard height on, too
        edge = False
        if c.edge_height_m > 0 and v[2] < 0.0 and floor is False:
            pad_d = self._straddle_from(legs, float(position[2]))
            edge = pad_d is not None and pad_d < c.edge_height_m
        if not edge and (v[2] >= 0.0 or float(position[2]) >= c.guard_height_m or not floor
                         or self._near_remembered_pad(position)):
            return GuardResult(agent, v, False, floor)
        u = np.asarray(u, dtype=float).reshape(3)
        # only the vertical part of the assistance changes: a' = (a_xy, 2 climb - u_z), V' = blend(u, a').
        # The actor's horizontal action is kept (zero when it relinquished: V'_xy = u_xy / 2, the pilot
        # is slowed while it is held off the floor). With climb > threshold / 2 a descending pilot
        # (u_z <= 0) always gets |a'| > threshold; where |a'| ends up at or under it, V' = u and then
        # u_z >= 2 climb - threshold > 0: V' never descends while the guard is engaged.
        climb = max(c.min_climb_mps, 0.5 * blend_threshold + 0.01)
        a_in = np.zeros(3) if agent is None else np.asarray(agent, dtype=float).reshape(3)
        a_safe = a_in if float(np.linalg.norm(a_in)) > blend_threshold else np.zeros(3)
        a_safe = a_safe.copy()
        a_safe[2] = 2.0 * climb - u[2]
        return GuardResult(a_safe, blend(u, a_safe, blend_threshold), True, floor)


# ----------------------------------------------------------------------------------------------- stage
class GuardStage(Stage):
    """5. The floor guard on the blended command."""

    key, phase, position = 'floor_guard', COMMAND, 10

    def __init__(self, guard: FloorGuard, threshold: Callable[[], float]):
        self.guard, self._threshold = guard, threshold

    def reset(self) -> None:
        """Forget the last pad seen under the legs."""
        self.guard.reset()

    def apply(self, ctx: StepContext, d: Decision) -> Decision | None:
        """A small climb instead of a descent over bare floor, or None."""
        if (ctx.frame is None or not self.guard.cfg.enabled
                or float(ctx.position[2]) >= self.guard.watch_height_m):
            return None                       # too high to watch: the image is not read
        thr = self._threshold()
        active = d.agent is not None and float(np.linalg.norm(d.agent)) > thr
        g = self.guard.apply(ctx.u, d.agent if active else None, d.velocity, ctx.frame.image, ctx.position, thr)
        if not g.engaged:
            return None
        return Decision(g.agent, g.velocity, self.key, 'floor guard: descent over bare floor blocked')


def _make(cfg: SafetyConfig, parts: Parts, threshold: Callable[[], float]) -> tuple[dict, tuple[Stage, ...]]:
    """The floor guard and the wall rule (one switch and one settings object for both) and their stages."""
    from .walls import WallGuard, WallStage      # walls builds on this module
    guard, walls = FloorGuard(cfg), WallGuard(cfg)
    return {'guard': guard, 'walls': walls}, (GuardStage(guard, threshold), WallStage(walls, threshold))


RULE = Rule('safety', 'floor_guard', 'guard', SafetyConfig, goal_agnostic=False, title='floor guard', make=_make)
