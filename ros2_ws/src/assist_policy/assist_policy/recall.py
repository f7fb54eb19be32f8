"""Pad recall: a non-learned memory of the pads the camera has seen, and a rule that steers to them.

Why: the learned assistant knows about a pad only while the encoder sees one (its feature memory
covers a couple of seconds). A pilot who overshoots the last pad, or sets down between pads, descends
over bare floor with no pad in view, and there the actor is almost inactive or points nowhere in
particular (pilots it never trained with fail this way); the floor guard then stops the descent, and the
landing times out hovering over the floor. The nearest-pad reference, which knows the true pad
positions, pulls such a pilot back onto the pad it passed.

Map (``PadMap``): every depth frame is back-projected into odom with the camera's pose (odometry
position and attitude, camera ``camera_offset_m`` below base_link on the body z axis, optical frame as
in ARCHITECTURE.md); pixels standing more than ``min_top_m`` over the floor (odom z = 0) are "raised".
Each 4-connected raised region of at least ``min_pixels`` pixels is one pad sighting: its top surface
(points within ``top_band_m`` of the region's highest decile) gives the centre x, y and the top height.
Not pads: a region reaching ``max_top_m`` (a wall: pads stand 0.4-1.2 m, walls 6 m) and a "top" thinner
than ``min_spread_m`` across (a vertical face seen edge-on: a wall at the image border, a pad's side).
A sighting within ``merge_radius_m`` of a mapped pad updates it. A region cut by the image border is
seen only in part: its centre is biased toward the image centre and, low beside a pad, most of it is
the pad's side face (its "top" reads low). So a part view never replaces a centre seen whole, replaces
another part view only when it is larger, and the top of a pad never seen whole is the highest read.
Frames larger than ``max_image_px`` on their long side are subsampled first (pads span tens of pixels
at 64x64 already). ``reset`` forgets the map.

Rule (``PadRecall.apply``): it acts when the depth image shows the floor beneath every leg (the floor
guard's test), the nearest mapped pad is between ``clear_radius_m`` and ``radius_m`` away horizontally,
and the pilot commands a descent or is lower than ``low_height_m`` over that pad's top (the reference's
trigger). It stays out while the pilot's command, now or its 1 s mean, is faster than
``leave_speed_mps`` away from the pad (a pilot on its way to a pad ahead not yet seen, or back to one
behind), and the caller skips it while the pilot override acts. Acting, the agent's horizontal action
is replaced by the nearest-pad reference's centring action toward the pad (``ScriptedOracle.velocity``:
a_xy = 2 gain (pad - p)_xy - u_xy, clipped); its vertical action is kept, except lower than
``clear_height_m`` over the pad's top, where V_z = max(u_z, climb_mps) takes it over the pad's side
rather than into it. Nearer the centre than ``clear_radius_m`` the actor sees the pad (and a "floor"
there is the camera's blind range). The floor guard still acts after this rule.

Scout (``mode`` 'scout', ``scout_max_m`` > 0): the camera looks straight down and sees only about its
height x 0.55 to each side, so the map holds the pads the vehicle flew over, and a pad ahead may be
nearer than the one behind without ever having been in view. When the recall would steer back to a pad
and some cells (``cell_m``) of ground were never seen (no depth pixel of any frame fell on them) within
45 degrees of the line from that pad through the vehicle and within D - ``scout_margin_m`` of the spot
where the scout began, D being that spot's distance to the pad (a pad there would be the nearer), it
first steers toward the nearest such cell, holding the height (V_z = max(u_z, 0): the lower, the less
the camera sees), until a nearer pad is mapped (the nearest-pad rule then steers to it), every such cell
was seen, or it went ``scout_max_m`` from that spot; then back to the pad, which from then on is
recalled from up to ``radius_m`` + ``scout_max_m``. Not when the pilot commands (now or its 1 s mean) at
more than ``scout_back_mps`` toward the pad behind (it knows the pad is there); a scout interrupted (the
pilot stops descending or leaves, another rule acts) goes on when the rule acts again, from the same
spot within the same distance: one look per pad, except that a recall farther from the pad than the
scout ever steered it by more than ``scout_margin_m`` (the pilot took the vehicle on, e.g. under the
pilot override's long push) starts a new look from there. Why the scout: a pilot who passes the first
pad at transit speed and descends short of the second (its aim misjudged in depth, as the paper's
novices do; the held-out glide family) would be taken back to the first pad (e.g. 2.4 m back, with the
second 1.9 m ahead); the reference, which knows where every pad is, takes it on to the second. The same
signature (a descent past a pad, the floor below) is a pilot who overshot the last pad (the case the
recall exists for): the scout costs that pilot a look of up to ``scout_max_m`` before it goes back. Why
the new look: a look may begin as a pilot first descends past a pad (e.g. 2 m past it); the long push
then lets the pilot fly on toward its aim, and when it descends there the ground within reach of where
the look began has been seen, so without a new look the recall would take it back to that pad, away from
the goal pad it was nearing (a low_flyer pattern); a new look from there finds the goal pad. The look's
start is not moved along while the pilot creeps on away from the pad: the scout's own motion drags a
novice's aim on (the paper's conformance), the pilot creeps after it, and the look would chase it
(on low_flyer that would gain 2 landings and lose 4 to edges and a wrong pad).

Touchdown (``mode`` 'touchdown', ``touchdown_height_m`` > 0): nearer a mapped pad's centre than
``clear_radius_m``, lower than ``touchdown_height_m`` over its top, with the pad seen whole at least once
and a descent under way (u_z + a_z < 0: the blended V descends while the actor acts), the actor's
horizontal action is replaced by the same centring action toward the mapped centre; the vertical action
stays the actor's. Why: below about 1 m over its top a 0.8-1.6 m pad fills the camera's 58 degree view,
so the encoder sees no edge to place the pad by, and the actor's horizontal action there is noise
(0.6-1 m/s sideways pushes in the last 0.3 m, enough to slide a key-confused pilot off the edge with 2 of
4 legs on).
The map's centre comes from the pad seen whole from higher up (within 8 cm in the tests). The leaving
test above applies (a pilot moving off the pad at > ``leave_speed_mps`` is let go).

Pure numpy + OpenCV; no rclpy.
"""
from __future__ import annotations

import logging
import math
from collections.abc import Hashable
from dataclasses import dataclass, field

import cv2
import numpy as np

from assist_common.frames import R_BODY_FROM_OPTICAL, heading, quat_to_matrix, rotate_xy

from assist_common.settings import check_named, setting
from .safety import FloorGuard, SafetyConfig
from .scripted import ScriptedConfig, ScriptedOracle
from .settings import node_param
from .stage import ACTION, Decision, Parts, Rule, Stage, StepContext

log = logging.getLogger(__name__)


@dataclass
class RecallConfig:
    """Settings of the pad map and the recall rule (policy_node parameters pad_recall_* map onto these)."""

    enabled: bool = node_param(True, 'pad_recall', 'Pad recall (assist_policy.recall, not learned): pads seen in '
                               'the depth image are mapped; when the pilot descends (or is low) over bare floor, '
                               "the actor's horizontal action is replaced by a push back to the nearest mapped pad. "
                               'Default false in mode oracle.')
    # steers only to a mapped pad this close (pads stand ~4 m apart)
    radius_m: float = node_param(3.0, 'pad_recall_radius_m', 'The pad recall steers only to a mapped pad this close '
                                 '(horizontal m).', min=0.0, max=50.0)
    gain_xy: float = setting(ScriptedConfig.gain_xy, ge=0)  # 1/s, the reference's centring gain (V = gain (pad - p))
    low_height_m: float = setting(1.2, ge=0)  # also acts without a descent this low over the pad's top (reference: 1.2)
    clear_height_m: float = setting(0.35, ge=0)  # lower than this over the pad's top and off it: climb first (its side)
    # 'over it': nearer its centre than this (pads >= 0.8 m): the rule is off
    clear_radius_m: float = setting(0.4, ge=0)
    climb_mps: float = setting(0.3, ge=0)  # vertical V while climbing to clear the pad's side
    leave_speed_mps: float = setting(0.5, ge=0)  # a command (now or 1 s mean) this fast away from the pad: leaving it
    # lower than this over a pad seen whole and over it: centre on it (0: off)
    touchdown_height_m: float = node_param(1.0, 'pad_recall_touchdown_height_m', 'Lower than this over the top of a '
                                           'mapped pad seen whole (and over it) during a descent, the pad recall '
                                           'centres on it instead of the actor (m; 0: off).', min=0.0, max=5.0)
    min_top_m: float = setting(0.25, ge=0)  # a point this high over the floor is raised (pads 0.4-1.2 m)
    max_top_m: float = setting(2.0, ge=0)  # a raised region reaching this high is a wall (walls stand 6 m)
    top_band_m: float = setting(0.1, ge=0)  # the top surface: raised points within this of the region's top
    min_pixels: int = setting(6, ge=1)  # smaller raised regions are noise
    min_spread_m: float = setting(0.03, ge=0)  # a top thinner than this (std across) is a vertical face, not a pad
    merge_radius_m: float = setting(1.2, ge=0)  # a sighting this close to a mapped pad is that pad (pads <= 1.6 m)
    min_view_m: float = setting(0.5, ge=0)  # the map is not updated with the camera nearer than this to the floor
    # optical centre below base_link (as the guard's)
    camera_offset_m: float = setting(SafetyConfig.camera_offset_m, ge=0)
    # depth camera vertical field of view (square pixels)
    vertical_fov_deg: float = setting(SafetyConfig.vertical_fov_deg, gt=0, lt=180)
    max_image_px: int = setting(128, ge=8)  # a larger depth image is subsampled to this many pixels on its long side
    # scout (module docstring): look beyond before steering back to a pad behind (scout_max_m 0: off)
    # at most this far from where the scout began (then back to the pad)
    scout_max_m: float = node_param(1.5, 'pad_recall_scout_max_m', 'Before steering back to a mapped pad behind, '
                                    'the pad recall looks at the ground beyond not yet seen, where a nearer pad may '
                                    'be, at most this far (horizontal m; 0: off).', min=0.0, max=10.0)
    scout_margin_m: float = setting(0.4, ge=0)  # a pad nearer than the mapped one has its centre this much nearer still
    # a command this fast toward the pad behind: the pilot is coming back (no scout)
    scout_back_mps: float = setting(0.25, ge=0)
    cell_m: float = setting(0.25, gt=0)  # ground seen: cells of this size (m) with a depth pixel on them
    # more cells seen (a long flight): those farther than keep_seen_m are forgotten
    max_seen_cells: int = setting(100_000, ge=1000)
    keep_seen_m: float = setting(20.0, ge=0)  # ... (a landing covers ~2000 cells; a scout looks < 5 m away)

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges, or a pad-top band that holds nothing (ValueError, one
        line)."""
        check_named(self, type(self).__name__)
        if self.max_top_m <= self.min_top_m:
            raise ValueError(f'RecallConfig.max_top_m ({self.max_top_m}) must exceed min_top_m ({self.min_top_m})')


@dataclass
class MappedPad:
    """One pad in the map: top-surface centre in odom (x, y, top z) and whether it was ever seen whole."""

    xyz: np.ndarray
    whole: bool
    area: int                         # pixels of the sighting the centre comes from
    sightings: int = 1


@dataclass
class PadMap:
    """Pads seen in the depth images of this landing, in odom (see module docstring)."""

    cfg: RecallConfig = field(default_factory=RecallConfig)
    pads: list[MappedPad] = field(default_factory=list)
    seen: set[tuple[int, int]] = field(default_factory=set)    # ground cells (cell_m) a depth pixel fell on

    def reset(self) -> None:
        """Forget every pad and the ground seen (new landing)."""
        self.pads.clear()
        self.seen.clear()

    def unseen_near(self, xy: np.ndarray, radius_m: float, away_from: np.ndarray,
                    nearest_to: np.ndarray | None = None) -> np.ndarray | None:
        """Centre of a cell not yet seen within `radius_m` of `xy` on its far side from `away_from`, or None.

        The far side: within 45 degrees of the line from `away_from` (a pad behind) through `xy`. Of those
        cells, the one nearest to `nearest_to` (default `xy`). None: all of them seen.
        """
        c = self.cfg.cell_m
        xy = np.asarray(xy, dtype=float)[:2]
        near = xy if nearest_to is None else np.asarray(nearest_to, dtype=float)[:2]
        d = xy - np.asarray(away_from, dtype=float)[:2]
        d = d / max(float(np.hypot(d[0], d[1])), 1e-9)
        n = int(math.ceil(radius_m / c))
        i0, j0 = int(math.floor(xy[0] / c)), int(math.floor(xy[1] / c))
        ij = np.stack(np.meshgrid(np.arange(i0 - n, i0 + n + 1), np.arange(j0 - n, j0 + n + 1)), -1).reshape(-1, 2)
        off = (ij + 0.5) * c - xy
        r = np.hypot(off[:, 0], off[:, 1])
        keep = (r < radius_m) & (off @ d > _COS_45 * r)
        keep &= np.array([(int(i), int(j)) not in self.seen for i, j in ij])
        if not keep.any():
            return None
        cand = xy + off[keep]
        return cand[int(np.argmin(np.hypot(*(cand - near).T)))]

    def points(self, depth: np.ndarray, position: np.ndarray, quaternion: np.ndarray | None) -> np.ndarray:
        """HxWx3 odom points of the depth pixels (NaN where the depth is a hole)."""
        return depth_points(depth, position, quaternion, self.cfg.camera_offset_m, self.cfg.vertical_fov_deg)

    def update(self, depth: np.ndarray, position: np.ndarray, quaternion: np.ndarray | None = None) -> int:
        """Add this frame's pad sightings to the map; returns how many regions were seen."""
        c = self.cfg
        if float(position[2]) - c.camera_offset_m < c.min_view_m:
            return 0
        depth = subsample(depth, c.max_image_px)   # a RealSense frame (848x480): ~14 ms -> ~1 ms, same pads
        pts = self.points(depth, position, quaternion)
        xy = pts[..., :2].reshape(-1, 2)
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if len(xy):
            self.seen.update(_distinct_cells(np.floor(xy / c.cell_m).astype(np.int64)))
            if len(self.seen) > c.max_seen_cells:
                self._forget_far(np.asarray(position, dtype=float)[:2])
        zw = pts[..., 2]
        raised = (np.isfinite(zw) & (zw > c.min_top_m)).astype(np.uint8)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(raised, connectivity=4)
        h, w = raised.shape
        seen = 0
        for k in range(1, n):
            x0, y0, ww, hh, area = (int(v) for v in stats[k])
            if area < c.min_pixels:
                continue
            region = pts[labels == k]
            if float(region[:, 2].max()) >= c.max_top_m:
                continue                         # reaches higher than any pad: a wall
            top = float(np.percentile(region[:, 2], 90))
            surface = region[region[:, 2] > top - c.top_band_m]
            if len(surface) < c.min_pixels or _thinnest_spread(surface[:, :2]) < c.min_spread_m:
                continue                         # no level top (a wall face seen edge-on, a side face)
            xyz = np.array([float(np.median(surface[:, 0])), float(np.median(surface[:, 1])), top])
            whole = x0 > 0 and y0 > 0 and x0 + ww < w and y0 + hh < h
            self._add(xyz, whole, area)
            seen += 1
        return seen

    def _forget_far(self, xy: np.ndarray) -> None:
        """Forget the ground seen farther than keep_seen_m from `xy` (bounds the memory of a long flight)."""
        c = self.cfg
        self.seen = cells_within(self.seen, xy, c.cell_m, c.keep_seen_m)
        log.info('pad map: %d ground cells seen within %.0f m kept, farther ones forgotten', len(self.seen),
                 c.keep_seen_m)

    def _add(self, xyz: np.ndarray, whole: bool, area: int) -> None:
        for pad in self.pads:
            if math.hypot(pad.xyz[0] - xyz[0], pad.xyz[1] - xyz[1]) < self.cfg.merge_radius_m:
                pad.sightings += 1
                if whole:                        # seen whole: its centre and top, as measured
                    pad.xyz, pad.whole, pad.area = xyz, True, area
                elif not pad.whole and area >= pad.area:
                    # seen in part: the larger view has the less biased centre; a side face in view reads
                    # lower than the top, never higher, so the top is the highest seen
                    pad.xyz, pad.area = np.array([xyz[0], xyz[1], max(xyz[2], pad.xyz[2])]), area
                return
        self.pads.append(MappedPad(xyz, whole, area))

    def nearest(self, xy: np.ndarray) -> MappedPad | None:
        """The mapped pad nearest (horizontally) to `xy`, or None when the map is empty."""
        if not self.pads:
            return None
        d = [math.hypot(p.xyz[0] - xy[0], p.xyz[1] - xy[1]) for p in self.pads]
        return self.pads[int(np.argmin(d))]


class PadRecall:
    """The pad map and the recall rule (see module docstring); ``reset`` at each new landing."""

    def __init__(self, cfg: RecallConfig | None = None, floor_guard: FloorGuard | None = None):
        self.cfg = cfg or RecallConfig()
        self.map = PadMap(self.cfg)
        self.floor = floor_guard or FloorGuard()          # its floor_below test (its settings: legs, tolerance)
        self._centre = ScriptedOracle(ScriptedConfig(gain_xy=self.cfg.gain_xy))
        self.mode: str | None = None                       # the rule that acted in the last apply (or None)
        self._scouts: list[Scout] = []                     # one per pad scouted beyond (this landing)

    def reset(self) -> None:
        """Forget the map and the scouting (new landing)."""
        self.map.reset()
        self._scouts.clear()

    def observe(self, depth: np.ndarray, position: np.ndarray, quaternion: np.ndarray | None = None) -> None:
        """Map this frame's pads (call with every depth frame, whether or not the rule then acts)."""
        if self.cfg.enabled:
            self.map.update(depth, position, quaternion)

    def apply(self, u: np.ndarray, mean_u: np.ndarray, agent: np.ndarray, depth: np.ndarray, position: np.ndarray,
              quaternion: np.ndarray | None, max_speed: np.ndarray | tuple[float, float, float]) -> np.ndarray | None:
        """The agent action (m/s, base_link) steering to the remembered pad, or None (neither rule acts).

        ``mode`` tells which rule acted: 'recall' (back to a pad from beside it) or 'touchdown' (centring
        on the pad below during the last of a descent); None when neither did.
        """
        c = self.cfg
        self.mode = None
        u = np.asarray(u, dtype=float).reshape(3)
        p = np.asarray(position, dtype=float).reshape(3)
        a = np.asarray(agent, dtype=float).reshape(3).copy()
        if not c.enabled or not (np.all(np.isfinite(u)) and np.all(np.isfinite(p))):
            return None
        pad = self.map.nearest(p[:2])
        if pad is None:
            return None
        horiz, height = math.hypot(pad.xyz[0] - p[0], pad.xyz[1] - p[1]), float(p[2] - pad.xyz[2])
        scout = next((s for s in self._scouts if s.pad is pad), None)
        if scout is not None and (scout.done or math.hypot(*(p[:2] - scout.start)) < c.scout_max_m):
            radius = c.radius_m + c.scout_max_m         # the scout takes it (took it) this much farther
        else:
            radius = c.radius_m
        if horiz < c.clear_radius_m:        # over it: only the touchdown rule (a 'floor' here is the blind range)
            if not (pad.whole and height < c.touchdown_height_m and u[2] + a[2] < 0.0):
                return None
            mode = 'touchdown'
        elif horiz > radius or not (u[2] < 0.0 or height < c.low_height_m):
            return None                     # too far, or idle
        else:
            mode = 'recall'
        yaw = 0.0 if quaternion is None else heading(quaternion)
        to_pad = pad.xyz[:2] - p[:2]
        for cmd in (np.asarray(mean_u, dtype=float).reshape(3), u):
            if (np.all(np.isfinite(cmd)) and float(np.hypot(cmd[0], cmd[1])) > c.leave_speed_mps
                    and rotate_xy(cmd[:2], yaw) @ to_pad < 0.0):
                return None                 # heading away from it (to a pad ahead not yet seen, or back to another)
        if mode == 'recall' and self.floor.floor_below(depth, float(p[2])) is not True:
            return None
        u_odom = np.array([*rotate_xy(u[:2], yaw), u[2]])
        target = pad.xyz
        if mode == 'recall' and scout is not None and horiz > scout.far + c.scout_margin_m:
            # the pilot took it on beyond the last look: a look from here
            self._scouts = [s for s in self._scouts if s is not scout]
            scout = None
        if mode == 'recall' and not (scout is not None and scout.done):
            spot = self._scout_spot(pad, scout, p, horiz, to_pad,
                                    (u_odom, rotate_xy(np.asarray(mean_u, dtype=float)[:2], yaw)))
            if spot is not None:
                target, mode = np.array([spot[0], spot[1], pad.xyz[2]]), 'scout'
        v = self._centre.velocity(target, p, u_odom)           # odom; only its horizontal part is used
        a[:2] = rotate_xy(v[:2], -yaw)                            # back into base_link
        if mode != 'touchdown' and height < c.clear_height_m:
            a[2] = 2.0 * max(float(u[2]), c.climb_mps) - u[2]     # V_z = max(u_z, climb): over its side first
        elif mode == 'scout':
            a[2] = 2.0 * max(float(u[2]), 0.0) - u[2]            # V_z = max(u_z, 0): no lower while it looks
        ms = np.asarray(max_speed, dtype=float).reshape(3)
        self.mode = mode
        return np.clip(a, -ms, ms)


    def _scout_spot(self, pad: MappedPad, scout: Scout | None, p: np.ndarray, horiz: float, to_pad: np.ndarray,
                    commands: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
        """Where to look before steering back to `pad` (ground not yet seen beyond), or None: go back now."""
        c = self.cfg
        if c.scout_max_m <= 0:
            return None
        unit = to_pad / max(horiz, 1e-9)
        if any(np.all(np.isfinite(cmd[:2])) and float(cmd[:2] @ unit) > c.scout_back_mps for cmd in commands):
            return None                 # the pilot is coming back to it: it knows the pad is behind
        new = scout is None
        if new:
            scout = Scout(pad, p[:2].copy(), horiz - c.scout_margin_m, horiz)
        spot = None
        if math.hypot(*(p[:2] - scout.start)) < c.scout_max_m:
            spot = self.map.unseen_near(scout.start, scout.reach, pad.xyz[:2], nearest_to=p[:2])
        if spot is not None:
            scout.far = max(scout.far, horiz)    # how far from the pad the look has steered it
            if new:
                self._scouts.append(scout)
        elif not new:
            scout.done = True           # looked (or went as far as it may): back to the pad from now on
        return spot


@dataclass(eq=False)
class Scout:
    """A look beyond a pad: from where it began, how far a nearer pad's centre would be, whether it is over.

    ``far``: the farthest from the pad it has steered the vehicle (m); a recall farther still than that
    by ``scout_margin_m`` (the pilot took the vehicle on) starts a new look from there.
    """

    pad: MappedPad
    start: np.ndarray
    reach: float
    far: float
    done: bool = False


_COS_45 = math.cos(math.radians(45.0))


def subsample(depth: np.ndarray, max_px: int) -> np.ndarray:
    """`depth` (as an array) taking every k-th pixel so that its long side has at most `max_px` pixels."""
    depth = np.asarray(depth)
    stride = math.ceil(max(depth.shape) / max_px) if depth.ndim == 2 else 1
    return depth[::stride, ::stride] if stride > 1 else depth


def cells_within(cells: set[tuple[int, int]], xy: np.ndarray, cell_m: float, keep_m: float) -> set[tuple[int, int]]:
    """The grid cells (size `cell_m`) of `cells` whose centres lie within `keep_m` of `xy`."""
    keep = (keep_m / cell_m) ** 2
    i0, j0 = xy[0] / cell_m - 0.5, xy[1] / cell_m - 0.5
    return {(i, j) for i, j in cells if (i - i0) ** 2 + (j - j0) ** 2 <= keep}


def depth_points(depth: np.ndarray, position: np.ndarray, quaternion: np.ndarray | None, camera_offset_m: float,
                 vertical_fov_deg: float) -> np.ndarray:
    """HxWx3 odom points of a downward depth image's pixels (NaN where the depth is a hole); ValueError if not HxW.

    The camera's optical centre is `camera_offset_m` below base_link on the body z axis, the optical frame as
    in ARCHITECTURE.md, square pixels with `vertical_fov_deg`; the pose is odometry's (no quaternion: level).
    """
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2 or depth.size == 0:
        raise ValueError(f'depth image must be HxW, got shape {depth.shape}')
    h, w = depth.shape
    f = (h / 2.0) / math.tan(math.radians(vertical_fov_deg) / 2.0)
    cols, rows = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan)
    optical = np.stack([(cols - (w - 1) / 2.0) / f * z, (rows - (h - 1) / 2.0) / f * z, z], axis=-1)
    r_wb = np.eye(3) if quaternion is None else quat_to_matrix(quaternion)
    r_wo = r_wb @ R_BODY_FROM_OPTICAL
    cam = np.asarray(position, dtype=float).reshape(3) + r_wb @ np.array([0.0, 0.0, -camera_offset_m])
    return optical @ r_wo.T + cam


def _distinct_cells(ij: np.ndarray) -> list[tuple[int, int]]:
    """The distinct (i, j) rows of an Nx2 int64 array, as tuples: each row packed into one int64 (i in the high
    half, j's low 32 bits in the low half) so that one 1-D sort finds them (np.unique(axis=0) sorts rows as
    bytes, ~10x slower, and this runs on every depth frame)."""
    keys = np.unique((ij[:, 0] << 32) | (ij[:, 1] & 0xFFFFFFFF))
    i = keys >> 32
    j = ((keys & 0xFFFFFFFF) ^ 0x80000000) - 0x80000000        # the low half back to a signed 32-bit value
    return list(zip(i.tolist(), j.tolist()))


def _thinnest_spread(xy: np.ndarray) -> float:
    """Standard deviation of points `xy` (Nx2) across their narrowest direction (m)."""
    return float(math.sqrt(max(np.linalg.eigvalsh(np.cov(xy.T))[0], 0.0))) if len(xy) > 2 else 0.0


# ----------------------------------------------------------------------------------------------- stage
_RECALL_REASONS = {'recall': 'pad recall: steering back to a pad seen',
                   'touchdown': 'pad recall: centring on the pad below for touchdown',
                   'scout': 'pad recall: looking beyond for a nearer pad before steering back'}


class RecallStage(Stage):
    """3. The pad recall: maps every depth frame; steers back to a mapped pad (not after the override)."""

    key, phase, position = 'pad_recall', ACTION, 30

    def __init__(self, recall: PadRecall):
        self.recall = recall
        self._mapped: Hashable = None         # key of the depth frame last added to the map

    def reset(self) -> None:
        """Forget the map and the scouting."""
        self.recall.reset()
        self._mapped = None

    def apply(self, ctx: StepContext, d: Decision) -> Decision | None:
        """The push back to a mapped pad, or None."""
        if ctx.frame is None or not self.recall.cfg.enabled:
            return None
        if self._mapped != ctx.frame.key:
            self.recall.observe(ctx.frame.image, *ctx.frame.pose)
            self._mapped = ctx.frame.key
        if d.final:
            return None                       # the pilot's correction wins
        a = self.recall.apply(ctx.u, ctx.mean_u, d.agent, ctx.frame.image, ctx.position, ctx.quaternion,
                              ctx.max_speed)
        if a is None:
            return None
        return Decision(a, None, self.key, _RECALL_REASONS.get(self.recall.mode, _RECALL_REASONS['recall']))

    def modes(self, acted: bool, ran: bool) -> tuple[str, ...]:
        """The recall's mode (recall, scout, touchdown) when it acted."""
        return (self.recall.mode,) if acted and self.recall.mode else ()

    def diagnostics(self, modes) -> dict[str, int]:
        """Steps it centred on the pad below or scouted, and the pads mapped in this flight."""
        return {'pad_recall_touchdown': modes[f'{self.key}:touchdown'], 'pad_recall_scout': modes[f'{self.key}:scout'],
                'pad_recall_pads': len(self.recall.map.pads)}


def _make(cfg: RecallConfig, parts: Parts, threshold) -> tuple[dict, tuple[Stage, ...]]:
    """The recall and its stage (the floor guard's legs-over-floor test)."""
    recall = PadRecall(cfg, parts['guard'])
    return {'recall': recall}, (RecallStage(recall),)


RULE = Rule('recall', 'pad_recall', 'recall', RecallConfig, goal_agnostic=True, title='pad recall', make=_make)
