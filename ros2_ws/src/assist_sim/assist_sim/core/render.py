"""Analytic RGB-D renderer of the landing scene: per-pixel ray casting in numpy (no rclpy, no pybullet).

The scene is a floor, four inward-facing walls and five textured boxes, so every pixel's depth
and colour can be computed in closed form: intersect the pixel's ray with the boxes' faces that
face the camera, the walls and the floor, keep the nearest hit and shade it. The result reproduces pybullet's
TinyRenderer (the renderer the shipped models were trained with) pixel for pixel, quirks included:

- TinyRenderer samples pixel (col, row) at the ray through (col - W/2, row - (H/2 - 1)) in units
  of the focal length (viewport without the half-pixel offset, then a vertical flip);
- a GEOM_BOX visual is bullet's textured unit cube scaled to the box: flat face normals, each
  face textured affinely from a quarter-size square of the texture (`_CUBE_FACES`); a face's
  texel is lit with ambient 0.6 + diffuse 0.35 + specular 0.05 (exponent 2, reflection z in
  world) from the default light direction (-50, 30, 100), int(0.6 c + direct c) clamped;
- texel (u, v) -> image[H - 1 - int(frac(v) * H), int(frac(u) * W)] of the texture PNG;
- the floor keeps the world's analytic-floor convention (rays through the pixel centres of K, one
  shading factor), exactly as `LandingWorld` drew it before this module existed.

The camera may have any pose (position + R_world_from_optical), so a tilting airframe renders
correctly too. The renderer is selected by `CameraConfig.renderer` ('analytic' by default;
'pybullet' keeps TinyRenderer as the baseline).
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .scene import SceneSpec
from .textures import make_texture

# TinyRenderer's default lighting (bullet3 TinyRendererVisualShapeConverter / TinyRenderer.cpp).
LIGHT_DIR = np.array([-50.0, 30.0, 100.0]) / np.linalg.norm([-50.0, 30.0, 100.0])
AMBIENT, DIFFUSE, SPECULAR = 0.6, 0.35, 0.05


@functools.lru_cache(maxsize=128)
def _texture(index: int, px: int) -> np.ndarray:
    """Material texture (read-only, cached: scenes reuse the 52 materials)."""
    tex = make_texture(index, px)
    tex.setflags(write=False)
    return tex


def tiny_shading(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TinyRenderer's per-fragment light for unit world normals (n, 3): (ambient, direct) float32."""
    n = normals.astype(np.float32)
    light = LIGHT_DIR.astype(np.float32)
    ndl = n @ light
    refl = 2.0 * ndl[:, None] * n - light
    refl /= np.linalg.norm(refl, axis=1, keepdims=True)
    spec = np.maximum(refl[:, 2], 0.0) ** 2
    direct = np.float32(DIFFUSE) * np.maximum(ndl, 0.0) + np.float32(SPECULAR) * spec
    return np.float32(AMBIENT), direct.astype(np.float32)


def _shade(texels: np.ndarray, direct: np.ndarray | float) -> np.ndarray:
    """int(0.6 c + direct c) clamped to 255, in float32 as TinyRenderer computes it."""
    c = texels.astype(np.float32)
    out = np.float32(AMBIENT) * c + (np.asarray(direct, np.float32)[..., None] if np.ndim(direct) else
                                     np.float32(direct)) * c
    return np.minimum(out, 255.0).astype(np.uint8)


def _packed(rgb: np.ndarray) -> np.ndarray:
    """uint8 RGB (..., 3) -> one uint32 per texel (bytes R, G, B, 0 in memory): 1-D gathers are fast."""
    rgba = np.zeros(rgb.shape[:-1] + (4,), np.uint8)
    rgba[..., :3] = rgb
    return rgba.view(np.uint32)[..., 0]


def _lookup(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Model::diffuse: wrap uv into [0,1), truncate to texel indices, flipped rows."""
    h, w = tex.shape[:2]
    u = u - np.floor(u)
    v = v - np.floor(v)
    iu = np.minimum((u * w).astype(np.int64), w - 1)
    iv = np.minimum((v * h).astype(np.int64), h - 1)
    return tex[h - 1 - iv, iu]


@dataclass(frozen=True)
class PinholeRays:
    """Unit-z ray directions (H, W, 3) in the optical frame for a pixel-centre convention."""

    rays: np.ndarray

    @classmethod
    def make(cls, width: int, height: int, f: float, cx: float, cy: float) -> PinholeRays:
        """Rays through pixel (col, row) = ((col - cx) / f, (row - cy) / f, 1)."""
        uu, vv = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
        return cls(np.stack([(uu - cx) / f, (vv - cy) / f, np.ones_like(uu)], axis=-1))


# pybullet's GEOM_BOX visual (bullet3 ShapeData.h `cube_vertices_textured`): 24 vertices, flat
# face normals, each face mapped onto a quarter-size square of the texture. Rows: corner (unit
# cube, x y z) and its uv.
_CUBE_FACES = {
    (2, +1): [((-1, -1, 1), (0.75, 0.25)), ((1, -1, 1), (1.0, 0.25)), ((1, 1, 1), (1.0, 0.0)),
              ((-1, 1, 1), (0.75, 0.0))],
    (2, -1): [((-1, -1, -1), (0.5, 0.25)), ((1, -1, -1), (0.25, 0.25)), ((1, 1, -1), (0.25, 0.0)),
              ((-1, 1, -1), (0.5, 0.0))],
    (0, -1): [((-1, -1, -1), (0.5, 0.0)), ((-1, 1, -1), (0.75, 0.0)), ((-1, 1, 1), (0.75, 0.25)),
              ((-1, -1, 1), (0.5, 0.25))],
    (0, +1): [((1, -1, -1), (0.25, 0.5)), ((1, 1, -1), (0.25, 0.25)), ((1, 1, 1), (0.0, 0.25)),
              ((1, -1, 1), (0.0, 0.5))],
    (1, -1): [((-1, -1, -1), (0.25, 0.5)), ((-1, -1, 1), (0.25, 0.25)), ((1, -1, 1), (0.5, 0.25)),
              ((1, -1, -1), (0.5, 0.5))],
    (1, +1): [((-1, 1, -1), (0.0, 0.0)), ((-1, 1, 1), (0.0, 0.25)), ((1, 1, 1), (0.25, 0.25)),
              ((1, 1, -1), (0.25, 0.0))],
}


def _face_uv_maps() -> dict[tuple[int, int], np.ndarray]:
    """Per face: 3x2 matrix M with uv = [1, a, b] @ M (a, b = the other two unit-cube coordinates).

    Built from sums of the table's exact binary fractions (no least squares), so texel edges
    land exactly where bullet's interpolation puts them."""
    maps = {}
    for (axis, sign), rows in _CUBE_FACES.items():
        others = [k for k in range(3) if k != axis]
        x = np.array([[1.0, c[others[0]], c[others[1]]] for c, _ in rows])
        y = np.array([uv for _, uv in rows])
        m = (x.T @ y) / 4.0                               # the corners are +-1: x.T @ x = 4 I
        if not np.array_equal(x @ m, y):
            raise RuntimeError(f'face {(axis, sign)} is not affinely textured')
        maps[(axis, sign)] = m
    return maps


FACE_UV = _face_uv_maps()
FACE_KEYS = tuple(FACE_UV)


def _windows_overlap(windows: dict[int, list[int]]) -> bool:
    """Whether any two [c0, c1, r0, r1) pixel windows intersect."""
    ws = list(windows.values())
    return any(a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]
               for k, a in enumerate(ws) for b in ws[k + 1:])


class _Box:
    """One pad as the renderer sees it: pose, half extents and one pre-lit texture per face."""

    def __init__(self, pad, texture: np.ndarray):
        c, s = math.cos(pad.yaw), math.sin(pad.yaw)
        self.rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])   # world <- box
        self.center = np.array([pad.center[0], pad.center[1], pad.height / 2.0])
        self.half = np.array([pad.length / 2.0, pad.width / 2.0, pad.height / 2.0])
        self.lit = {}                                     # (axis, sign) -> texture lit as that face
        for axis, sign in FACE_UV:
            n = np.zeros(3)
            n[axis] = sign
            self.lit[(axis, sign)] = _shade(texture, tiny_shading((self.rot @ n)[None])[1][0])
        self.inv_half = 1.0 / self.half
        self.other_axes = {k: [a for a in range(3) if a != k] for k in range(3)}
        faces = []                                        # (6, 4, 3) world corners, FACE_KEYS order
        for axis, sign in FACE_KEYS:
            a1, a2 = self.other_axes[axis]
            for s1, s2 in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                unit = np.zeros(3)
                unit[axis], unit[a1], unit[a2] = sign, s1, s2
                faces.append(self.center + self.rot @ (self.half * unit))
        self.face_corners = np.array(faces).reshape(6, 4, 3)


class SceneRenderer:
    """Analytic renderer of one generated scene; `render(cam, R_world_from_optical)` -> (rgb, depth)."""

    def __init__(self, scene: SceneSpec, *, width: int, height: int, vertical_fov_deg: float,
                 near_m: float, far_m: float, floor_tile_m: float, floor_shading: float,
                 wall_tile_m: float = 1.5, texture_px: int = 64):
        self.width, self.height = int(width), int(height)
        self.near, self.far = float(near_m), float(far_m)
        f = (self.height / 2.0) / math.tan(math.radians(vertical_fov_deg) / 2.0)
        self.f = f
        # TinyRenderer's sampling (objects) and the world's K convention (analytic floor)
        self._cx_tr, self._cy_tr = self.width / 2.0, self.height / 2.0 - 1.0
        self._rays_tr = PinholeRays.make(self.width, self.height, f, self._cx_tr, self._cy_tr).rays.reshape(-1, 3)
        self._rays_k = PinholeRays.make(self.width, self.height, f, (self.width - 1) / 2.0,
                                        (self.height - 1) / 2.0).rays.reshape(-1, 3)
        self._corner_idx = np.array([0, self.width - 1, (self.height - 1) * self.width, self.height * self.width - 1])
        self.scene = scene
        (x0, y0), (x1, y1) = scene.room_min, scene.room_max
        self.room = (float(x0), float(y0), float(x1), float(y1))
        self.wall_h = float(scene.wall_height)
        self.floor_tile = float(floor_tile_m)
        self.wall_tile = float(wall_tile_m)
        floor_tex = _texture(scene.floor_material, texture_px)
        # the world's analytic floor: texel * floor_shading, truncated (float64), black where no floor
        self._floor_px = floor_tex.shape[0]
        self._floor_lit = _packed((floor_tex * float(floor_shading)).astype(np.uint8)[::-1]).reshape(-1)
        wall_tex = _texture(scene.wall_material, texture_px)
        self.boxes = [_Box(p, _texture(p.material, texture_px)) for p in scene.pads]
        self._box_rot = np.array([b.rot for b in self.boxes]).reshape(-1, 3, 3)
        self._box_center = np.array([b.center for b in self.boxes]).reshape(-1, 3)
        self._box_half = np.array([b.half for b in self.boxes]).reshape(-1, 3)
        self._face_axis = np.array([k[0] for k in FACE_KEYS])
        self._face_sign = np.array([k[1] for k in FACE_KEYS], float)
        self._pixel_index = np.arange(self.width * self.height).reshape(self.height, self.width)
        self._tex_px = int(texture_px)
        # every face's lit texture in one array (box-major, FACE_KEYS order) and its uv map
        self._lit_faces = (_packed(np.stack([b.lit[key] for b in self.boxes for key in FACE_KEYS])).reshape(-1)
                           if self.boxes else np.zeros(0, np.uint32))
        self._face_uv = np.array([FACE_UV[key] for _ in self.boxes for key in FACE_KEYS]).reshape(-1, 3, 2)
        self._face_corners = (np.concatenate([b.face_corners for b in self.boxes]).reshape(-1, 3)
                              if self.boxes else np.zeros((0, 3)))
        # walls as the world builds them: corner 0 is the uv origin, u along c1-c0, v along c3-c0
        h = self.wall_h
        self.walls = []
        for corners, normal in [
                ([[x0, y1, 0], [x1, y1, 0], [x1, y1, h], [x0, y1, h]], (0, -1, 0)),
                ([[x1, y0, 0], [x0, y0, 0], [x0, y0, h], [x1, y0, h]], (0, 1, 0)),
                ([[x0, y0, 0], [x0, y1, 0], [x0, y1, h], [x0, y0, h]], (1, 0, 0)),
                ([[x1, y1, 0], [x1, y0, 0], [x1, y0, h], [x1, y1, h]], (-1, 0, 0))]:
            c = np.array(corners, float)
            e1, e2 = c[1] - c[0], c[3] - c[0]
            n = np.array(normal, float)
            lit = _packed(_shade(wall_tex, tiny_shading(n[None])[1][0]))
            self.walls.append((c[0], e1 / np.dot(e1, e1), e2 / np.dot(e2, e2), np.linalg.norm(e1),
                               np.linalg.norm(e2), n, lit))

    # ------------------------------------------------------------------ public
    def render(self, cam: np.ndarray, r_wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """RGB (H,W,3 uint8) and optical z-depth (H,W float32, metres) seen from a camera pose.

        `cam` is the optical centre in the world, `r_wo` the rotation world <- optical frame
        (z out of the lens, x right, y down). Pixels that see nothing are black at the far plane.
        """
        cam = np.asarray(cam, float)
        r_wo = np.asarray(r_wo, float)
        rgb, depth = self._floor(cam, r_wo)
        obj_depth = np.full(depth.shape, np.inf)
        self._draw_walls(cam, r_wo, obj_depth, depth, rgb)
        self._draw_boxes(cam, r_wo, obj_depth, depth, rgb)
        rgb = np.ascontiguousarray(rgb.view(np.uint8).reshape(self.height, self.width, 4)[..., :3])
        return rgb, depth.astype(np.float32).reshape(self.height, self.width)

    # ------------------------------------------------------------------ floor
    def _floor(self, cam: np.ndarray, r_wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The world's analytic floor everywhere: z = 0 plane, tiled texture (K's pixel centres)."""
        dirs = self._rays_k @ r_wo.T
        dz = dirs[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = -cam[2] / dz
        ok = (dz < -1e-9) & (t <= self.far)
        all_ok = bool(ok.all())
        if not all_ok:
            t = np.where(ok, t, 0.0)
        px = self._floor_px
        scale = px / self.floor_tile
        tu = np.floor((cam[0] - self.room[0] + t * dirs[:, 0]) * scale).astype(np.int64) % px
        tv = np.floor((cam[1] - self.room[1] + t * dirs[:, 1]) * scale).astype(np.int64) % px
        rgb = self._floor_lit[tv * px + tu]              # packed uint32 colours
        if not all_ok:
            rgb[~ok] = 0
            t = np.where(ok, t, self.far)
        return rgb, t

    # ------------------------------------------------------------------ walls
    def _draw_walls(self, cam: np.ndarray, r_wo: np.ndarray, obj_depth: np.ndarray, depth: np.ndarray,
                    rgb: np.ndarray) -> None:
        x0, y0, x1, y1 = self.room
        inside = (x0 < cam[0] < x1) and (y0 < cam[1] < y1) and (0.0 < cam[2] < self.wall_h)
        if inside:
            # the floor footprint of the view is the quad of the corner rays' floor points (when all
            # four point down); inside the (convex) room it leaves no pixel for a wall
            cd = self._rays_tr[self._corner_idx] @ r_wo.T
            if np.all(cd[:, 2] < 0):
                t = -cam[2] / cd[:, 2]
                fx, fy = cam[0] + t * cd[:, 0], cam[1] + t * cd[:, 1]
                if np.all((fx > x0) & (fx < x1) & (fy > y0) & (fy < y1)):
                    return
        dirs = self._rays_tr @ r_wo.T
        if inside:
            # a ray from inside the room meets a wall only if its floor point lies outside the room
            dz = dirs[:, 2]
            with np.errstate(divide='ignore', invalid='ignore'):
                tf = np.where(dz < 0, -cam[2] / dz, np.inf)
                fx, fy = cam[0] + tf * dirs[:, 0], cam[1] + tf * dirs[:, 1]
            cand = np.nonzero(~((fx >= x0) & (fx <= x1) & (fy >= y0) & (fy <= y1)))[0]
        else:
            cand = np.arange(dirs.shape[0])
        if cand.size == 0:
            return
        d = dirs[cand]
        for origin, g1, g2, len1, len2, normal, lit in self.walls:
            denom = d @ normal
            front = denom < -1e-12                            # walls are one-sided (back faces culled)
            if not front.any():
                continue
            t = np.full(cand.size, np.inf)
            t[front] = ((origin - cam) @ normal) / denom[front]
            with np.errstate(invalid='ignore'):
                rel = cam - origin + t[:, None] * d
                s, q = rel @ g1, rel @ g2                     # in [0,1] on the wall
                ok = front & (t > self.near) & (t <= self.far) & (s >= 0) & (s <= 1) & (q >= 0) & (q <= 1)
            ok &= t < obj_depth[cand]
            if not ok.any():
                continue
            flat = cand[ok]
            rgb[flat] = _lookup(lit, s[ok] * len1 / self.wall_tile, q[ok] * len2 / self.wall_tile)
            depth[flat] = obj_depth[flat] = t[ok]

    # ------------------------------------------------------------------ boxes
    def _face_windows(self, cam: np.ndarray, r_wo: np.ndarray) -> np.ndarray:
        """(n_boxes * 6, 4) pixel windows [col0, col1, row0, row1] of every box face (may exceed the image)."""
        p = (self._face_corners - cam) @ r_wo            # (n_boxes * 6 * 4, 3) optical frame
        z = p[:, 2].reshape(-1, 4)
        with np.errstate(divide='ignore', invalid='ignore'):
            u = (p[:, 0] / p[:, 2] * self.f + self._cx_tr).reshape(-1, 4)
            v = (p[:, 1] / p[:, 2] * self.f + self._cy_tr).reshape(-1, 4)
        # pixel samples sit at integer (u, v): those inside the convex quad lie within its corners'
        # extremes (a 1e-3 px margin covers rounding between this projection and the ray test)
        win = np.stack([np.ceil(u.min(axis=1) - 1e-3), np.floor(u.max(axis=1) + 1e-3),
                        np.ceil(v.min(axis=1) - 1e-3), np.floor(v.max(axis=1) + 1e-3)], axis=1)
        win = np.clip(win, -1e6, 1e6)
        win[(z <= 1e-6).any(axis=1)] = (0, self.width - 1, 0, self.height - 1)   # corner behind the lens
        return win

    def _draw_boxes(self, cam: np.ndarray, r_wo: np.ndarray, obj_depth: np.ndarray, depth: np.ndarray,
                    rgb: np.ndarray) -> None:
        """Every box face the camera is in front of: ray-plane intersection over the face's image
        window, all faces in one vectorised pass; where faces of different boxes cover the same
        pixel the nearest wins (the front faces of one convex box never overlap)."""
        if not self.boxes:
            return
        w, h = self.width, self.height
        windows = self._face_windows(cam, r_wo)
        # camera in every box frame; face (axis, sign) faces the camera when sign * o[axis] > half
        o_all = np.einsum('bji,bj->bi', self._box_rot, cam - self._box_center)
        front = (o_all[:, self._face_axis] * self._face_sign) > self._box_half[:, self._face_axis]
        win = windows.reshape(front.shape + (4,))
        vis = front & (win[..., 1] >= 0) & (win[..., 0] < w) & (win[..., 3] >= 0) & (win[..., 2] < h)
        if not vis.any():
            return
        rays_grid = self._rays_tr.reshape(h, w, 3)
        idx_parts, d_parts, sizes, consts, faces = [], [], [], [], []
        boxes_in_view: dict[int, list[int]] = {}          # box -> its window (union of its faces')
        for i, j in zip(*np.nonzero(vis)):
            box = self.boxes[i]
            axis, sign = FACE_KEYS[j]
            a1, a2 = box.other_axes[axis]
            o = o_all[i]
            c0, c1, r0, r1 = win[i, j]
            c0, c1 = max(int(c0), 0), min(int(c1), w - 1) + 1
            r0, r1 = max(int(r0), 0), min(int(r1), h - 1) + 1
            bw = boxes_in_view.setdefault(int(i), [c0, c1, r0, r1])
            bw[:] = [min(bw[0], c0), max(bw[1], c1), min(bw[2], r0), max(bw[3], r1)]
            idx_parts.append(self._pixel_index[r0:r1, c0:c1].reshape(-1))
            # ray directions in the box frame along (face normal, face axis 1, face axis 2)
            d_parts.append((rays_grid[r0:r1, c0:c1] @ (r_wo.T @ box.rot)[:, (axis, a1, a2)]).reshape(-1, 3))
            sizes.append(idx_parts[-1].size)
            consts.append((sign * box.half[axis] - o[axis], o[a1], o[a2], box.inv_half[a1], box.inv_half[a2]))
            faces.append(6 * i + j)
        idx = np.concatenate(idx_parts)
        d = np.concatenate(d_parts)
        sizes = np.array(sizes)
        k, o1, o2, ih1, ih2 = np.repeat(np.array(consts), sizes, axis=0).T
        with np.errstate(divide='ignore', invalid='ignore'):
            t = k / d[:, 0]
            p1 = (o1 + t * d[:, 1]) * ih1                  # face coordinates in [-1, 1]
            p2 = (o2 + t * d[:, 2]) * ih2
            ok = (np.abs(p1) <= 1.0) & (np.abs(p2) <= 1.0) & (t > self.near) & (t <= self.far) & (t < obj_depth[idx])
        if not ok.any():
            return
        face = np.repeat(np.array(faces), sizes)[ok]
        idx, t, p1, p2 = idx[ok], t[ok], p1[ok], p2[ok]
        if len(boxes_in_view) > 1 and _windows_overlap(boxes_in_view):
            order = np.lexsort((t, idx))                    # per pixel, nearest first
            first = np.ones(order.size, bool)
            first[1:] = idx[order[1:]] != idx[order[:-1]]
            keep = order[first]
            face, idx, t, p1, p2 = face[keep], idx[keep], t[keep], p1[keep], p2[keep]
        m = self._face_uv[face]                             # (n, 3, 2)
        uv = (m[:, 0] + p1[:, None] * m[:, 1] + p2[:, None] * m[:, 2]).astype(np.float32)
        px = self._tex_px
        u = uv[:, 0] - np.floor(uv[:, 0])
        v = uv[:, 1] - np.floor(uv[:, 1])
        iu = np.minimum((u * px).astype(np.int64), px - 1)
        iv = np.minimum((v * px).astype(np.int64), px - 1)
        rgb[idx] = self._lit_faces[(face * px + (px - 1 - iv)) * px + iu]
        depth[idx] = t
        obj_depth[idx] = t
