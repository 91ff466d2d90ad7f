"""Colour and depth of textured solids by ray casting (numba, single-threaded, no ROS): the simulated "real" camera
(:mod:`gsrmr_sim.world.raycast`) and the server's virtual agents (:mod:`gsrmr_server.mr.content`). One ray per pixel
centre, scaled so that its camera-frame z is 1: the ray parameter at a hit is the depth (camera z, metres; +inf for a
miss). Primitives in ``map``, metres; shading and textures: docs/world.md, "Rendering".
"""

from __future__ import annotations

import math

import numba
import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_shapes.spec import TEXTURES, Lighting, Material, Shape

_EPS = 1e-6
_SHADOW_BIAS = 1e-4

# ----------------------------------------------------------------------------------------------
# packing scene objects into flat arrays for the kernel


class MaterialTable:
    """Materials as an (K, 8) float64 table: texture code, colour rgb, colour2 rgb, scale_m."""

    def __init__(self) -> None:
        self.rows: list[list[float]] = []
        self.index: dict[Material, int] = {}

    def add(self, m: Material) -> int:
        """Index of material ``m`` (added on first use)."""
        if m not in self.index:
            self.index[m] = len(self.rows)
            self.rows.append([float(TEXTURES.index(m.texture)), *m.color, *m.color2, m.scale_m])
        return self.index[m]

    def array(self) -> np.ndarray:
        """The table (at least one row so numba sees a 2-D array)."""
        return np.array(self.rows or [[0.0] * 8], dtype=np.float64).reshape(-1, 8)


def pack_shapes(shapes: tuple[Shape, ...] | list[Shape],
                mats: MaterialTable) -> tuple[np.ndarray, np.ndarray]:
    """(boxes (N, 9): cx cy cz hx hy hz cos sin mat; cylinders (M, 6): cx cy z0 z1 r mat)."""
    boxes, cyls = [], []
    for s in shapes:
        mat = float(mats.add(s.material))
        if s.shape == "box":
            hx, hy, hz = (0.5 * v for v in s.size)
            boxes.append([s.position[0], s.position[1], s.base_z_m + hz, hx, hy, hz,
                          math.cos(s.yaw_rad), math.sin(s.yaw_rad), mat])
        else:
            cyls.append([s.position[0], s.position[1], s.base_z_m, s.base_z_m + s.size[2], s.radius_m, mat])
    return (np.array(boxes, dtype=np.float64).reshape(-1, 9), np.array(cyls, dtype=np.float64).reshape(-1, 6))


def pack_lights(state: Lighting) -> tuple[np.ndarray, np.ndarray]:
    """(lights (L, 9): type vx vy vz r g b range shadows; regions (R, 9): min3 max3 gain3)."""
    lights = [[0.0 if lt.type == "directional" else 1.0, *lt.vector, *(c * lt.intensity for c in lt.color),
               lt.range_m, 1.0 if lt.shadows else 0.0] for lt in state.lights]
    regions = [[*lo, *hi, *gain] for lo, hi, gain in state.regions]
    return (np.array(lights, dtype=np.float64).reshape(-1, 9),
            np.array(regions, dtype=np.float64).reshape(-1, 9))


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """(N, 8, 3) world corners of packed boxes."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    local = signs[None] * boxes[:, None, 3:6]
    c, s = boxes[:, None, 6], boxes[:, None, 7]
    x = c * local[..., 0] - s * local[..., 1] + boxes[:, None, 0]
    y = s * local[..., 0] + c * local[..., 1] + boxes[:, None, 1]
    z = local[..., 2] + boxes[:, None, 2]
    return np.stack([x, y, z], axis=-1)


def cylinder_corners(cyls: np.ndarray) -> np.ndarray:
    """(M, 8, 3) corners of the axis-aligned boxes around packed cylinders."""
    signs = np.array([[sx, sy] for sx in (-1, 1) for sy in (-1, 1)], np.float64)
    xy = cyls[:, None, 0:2] + signs[None] * cyls[:, None, 4:5]
    bottom = np.concatenate([xy, np.broadcast_to(cyls[:, None, 2:3], (len(cyls), 4, 1))], axis=-1)
    top = np.concatenate([xy, np.broadcast_to(cyls[:, None, 3:4], (len(cyls), 4, 1))], axis=-1)
    return np.concatenate([bottom, top], axis=1)


def screen_rects(camera: Camera, corners: np.ndarray, near_m: float = 1e-3) -> np.ndarray:
    """(N, 4) int64 pixel rectangles x0 x1 y0 y1 (inclusive) that contain each convex solid's image.

    The image of a convex solid entirely in front of the camera lies in the convex hull of its
    projected corners; a solid reaching behind ``near_m`` gets the whole image. Rectangles are
    widened by one pixel, so the culling never drops a pixel centre the solid covers.
    """
    n = corners.shape[0]
    out = np.empty((n, 4), np.int64)
    out[:] = (0, camera.width - 1, 0, camera.height - 1)
    if n == 0:
        return out
    cam = camera.to_camera(corners.reshape(-1, 3)).reshape(n, 8, 3)
    k = camera.intrinsics
    for i in range(n):
        z = cam[i, :, 2]
        if np.any(z <= near_m):
            continue
        u = k.fx * cam[i, :, 0] / z + k.cx
        v = k.fy * cam[i, :, 1] / z + k.cy
        x0, x1 = int(np.floor(u.min())) - 1, int(np.ceil(u.max())) + 1
        y0, y1 = int(np.floor(v.min())) - 1, int(np.ceil(v.max())) + 1
        out[i] = (max(x0, 0), min(x1, camera.width - 1), max(y0, 0), min(y1, camera.height - 1))
        if x0 > camera.width - 1 or x1 < 0 or y0 > camera.height - 1 or y1 < 0:
            out[i] = (1, 0, 1, 0)  # empty: off screen
    return out


def world_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), H×W×3 world ray directions whose camera-frame z is 1) — ray t equals depth."""
    c2w = camera.camera_to_world
    dirs = camera.ray_directions_camera() @ c2w[:3, :3].T
    return np.ascontiguousarray(c2w[:3, 3]), np.ascontiguousarray(dirs)


# ----------------------------------------------------------------------------------------------
# numba kernel


@numba.njit(cache=True, inline="always")
def _hash01(i: int, j: int, seed: int) -> float:
    h = (i * 374761393 + j * 668265263 + seed * 1442695041) & 0xFFFFFFFF
    h = ((h ^ (h >> 13)) * 1274126177) & 0xFFFFFFFF
    h = h ^ (h >> 16)
    return h / 4294967296.0


@numba.njit(cache=True)
def _value_noise(u: float, v: float, seed: int) -> float:
    i0 = math.floor(u)
    j0 = math.floor(v)
    fu = u - i0
    fv = v - j0
    su = fu * fu * (3.0 - 2.0 * fu)
    sv = fv * fv * (3.0 - 2.0 * fv)
    a = _hash01(int(i0), int(j0), seed)
    b = _hash01(int(i0) + 1, int(j0), seed)
    c = _hash01(int(i0), int(j0) + 1, seed)
    d = _hash01(int(i0) + 1, int(j0) + 1, seed)
    return (a * (1 - su) + b * su) * (1 - sv) + (c * (1 - su) + d * su) * sv


@numba.njit(cache=True, inline="always")
def _filtered_square(x: float, w: float) -> float:
    """Box-filtered square wave of period 2 (+1 on [0, 1), −1 on [1, 2)) over a window of width w."""
    a = (x - 0.5 * w) * 0.5
    b = (x + 0.5 * w) * 0.5
    return 2.0 * (abs(a - math.floor(a) - 0.5) - abs(b - math.floor(b) - 0.5)) / w


@numba.njit(cache=True)
def _albedo(mats: np.ndarray, m: int, u: float, v: float, footprint_m: float, out: np.ndarray) -> None:
    """Albedo of material m at texture coordinates (u, v) metres, pre-filtered over ``footprint_m``.

    The filter (a pixel's footprint on the surface) keeps the textures from aliasing: the checker
    is box-filtered analytically, stripes and noise octaves fade as their period approaches it.
    """
    tex = int(mats[m, 0])
    s = mats[m, 7]
    w = 0.0
    fw = max(footprint_m / s, 1e-4)  # footprint in pattern periods
    if tex == 1:
        w = 0.5 - 0.5 * _filtered_square(u / s, fw) * _filtered_square(v / s, fw)
    elif tex == 2:
        a1 = max(0.0, 1.0 - 0.5 * fw)
        a2 = max(0.0, 1.0 - fw)
        w = 0.5 + a1 * 0.65 * (_value_noise(u / s, v / s, m) - 0.5) \
            + a2 * 0.35 * (_value_noise(2.0 * u / s, 2.0 * v / s, m + 101) - 0.5)
        w = min(1.0, max(0.0, 1.5 * (w - 0.5) + 0.5))
    elif tex == 3:
        w = 0.5 + 0.5 * max(0.0, 1.0 - fw) * math.sin(2.0 * math.pi * u / s)
    for k in range(3):
        out[k] = mats[m, 1 + k] * (1.0 - w) + mats[m, 4 + k] * w


@numba.njit(cache=True)
def _hit_box(b: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
             tmax: float, res: np.ndarray) -> bool:
    """Nearest hit in (eps, tmax); res = t, nx, ny, nz, u, v."""
    c, s = b[6], b[7]
    px = c * (ox - b[0]) + s * (oy - b[1])
    py = -s * (ox - b[0]) + c * (oy - b[1])
    pz = oz - b[2]
    lx = c * dx + s * dy
    ly = -s * dx + c * dy
    lz = dz
    p = (px, py, pz)
    d = (lx, ly, lz)
    h = (b[3], b[4], b[5])
    tnear = -1e30
    tfar = 1e30
    axis = 0
    sign = 1.0
    for k in range(3):
        if abs(d[k]) < 1e-12:
            if abs(p[k]) > h[k]:
                return False
            continue
        t1 = (-h[k] - p[k]) / d[k]
        t2 = (h[k] - p[k]) / d[k]
        if t1 > t2:
            t1, t2 = t2, t1
        if t1 > tnear:
            tnear = t1
            axis = k
            sign = -1.0 if d[k] > 0 else 1.0
        if t2 < tfar:
            tfar = t2
    if tnear > tfar or tnear <= _EPS or tnear >= tmax:
        return False
    hx = p[0] + tnear * d[0] + h[0]
    hy = p[1] + tnear * d[1] + h[1]
    hz = p[2] + tnear * d[2] + h[2]
    nlx = sign if axis == 0 else 0.0
    nly = sign if axis == 1 else 0.0
    res[0] = tnear
    res[1] = c * nlx - s * nly
    res[2] = s * nlx + c * nly
    res[3] = sign if axis == 2 else 0.0
    if axis == 0:
        res[4] = hy
        res[5] = hz
    elif axis == 1:
        res[4] = hx
        res[5] = hz
    else:
        res[4] = hx
        res[5] = hy
    return True


@numba.njit(cache=True)
def _hit_cyl(cy: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float, dz: float,
             tmax: float, res: np.ndarray) -> bool:
    px = ox - cy[0]
    py = oy - cy[1]
    r = cy[4]
    best = tmax
    found = False
    a = dx * dx + dy * dy
    if a > 1e-18:
        bq = 2.0 * (px * dx + py * dy)
        cq = px * px + py * py - r * r
        disc = bq * bq - 4.0 * a * cq
        if disc >= 0.0:
            t = (-bq - math.sqrt(disc)) / (2.0 * a)
            if _EPS < t < best:
                z = oz + t * dz
                if cy[2] <= z <= cy[3]:
                    best = t
                    found = True
                    hx = px + t * dx
                    hy = py + t * dy
                    res[0] = t
                    res[1] = hx / r
                    res[2] = hy / r
                    res[3] = 0.0
                    res[4] = (math.atan2(hy, hx) + math.pi) * r
                    res[5] = z - cy[2]
    if abs(dz) > 1e-12:
        for cap in range(2):
            zc = cy[3] if cap == 0 else cy[2]
            t = (zc - oz) / dz
            if _EPS < t < best:
                hx = px + t * dx
                hy = py + t * dy
                if hx * hx + hy * hy <= r * r:
                    best = t
                    found = True
                    res[0] = t
                    res[1] = 0.0
                    res[2] = 0.0
                    res[3] = 1.0 if cap == 0 else -1.0
                    res[4] = hx + r
                    res[5] = hy + r
    return found


@numba.njit(cache=True)
def _occluded(boxes: np.ndarray, cyls: np.ndarray, ox: float, oy: float, oz: float, dx: float, dy: float,
              dz: float, tmax: float, scratch: np.ndarray) -> bool:
    for i in range(boxes.shape[0]):
        if _hit_box(boxes[i], ox, oy, oz, dx, dy, dz, tmax, scratch):
            return True
    for i in range(cyls.shape[0]):  # noqa: SIM110 - numba cannot compile any() over a generator
        if _hit_cyl(cyls[i], ox, oy, oz, dx, dy, dz, tmax, scratch):
            return True
    return False


@numba.njit(cache=True, nogil=True)  # the server casts the virtual view beside its GS render (compose.py)
def render_kernel(origin: np.ndarray, dirs: np.ndarray, boxes: np.ndarray, cyls: np.ndarray,
                  box_rects: np.ndarray, cyl_rects: np.ndarray,
                  room: np.ndarray, has_room: bool, mats: np.ndarray, lights: np.ndarray,
                  regions: np.ndarray, ambient: float, background: np.ndarray, pixel_angle: float,
                  out_rgb: np.ndarray, out_depth: np.ndarray) -> None:
    """Ray cast every pixel: writes out_rgb (H×W×3 float32 in [0, 1]) and out_depth (H×W, +inf on miss).

    ``pixel_angle`` (rad, ≈ 1/fx) sets the texture pre-filter footprint.
    """
    H, W = dirs.shape[0], dirs.shape[1]
    ox, oy, oz = origin[0], origin[1], origin[2]
    res = np.empty(6)
    best = np.empty(6)
    scratch = np.empty(6)
    alb = np.empty(3)
    for y in range(H):
        for x in range(W):
            dx, dy, dz = dirs[y, x, 0], dirs[y, x, 1], dirs[y, x, 2]
            tbest = np.inf
            mat = -1
            for i in range(boxes.shape[0]):
                r = box_rects[i]
                if x < r[0] or x > r[1] or y < r[2] or y > r[3]:
                    continue
                if _hit_box(boxes[i], ox, oy, oz, dx, dy, dz, tbest, res):
                    tbest = res[0]
                    mat = int(boxes[i, 8])
                    best[:] = res
            for i in range(cyls.shape[0]):
                r = cyl_rects[i]
                if x < r[0] or x > r[1] or y < r[2] or y > r[3]:
                    continue
                if _hit_cyl(cyls[i], ox, oy, oz, dx, dy, dz, tbest, res):
                    tbest = res[0]
                    mat = int(cyls[i, 5])
                    best[:] = res
            if has_room:
                # exit point of the room box (camera inside)
                texit = np.inf
                axis = -1
                upper = False
                for k in range(3):
                    dk = dx if k == 0 else (dy if k == 1 else dz)
                    ok = ox if k == 0 else (oy if k == 1 else oz)
                    if dk > 1e-12:
                        t = (room[3 + k] - ok) / dk
                        if t < texit:
                            texit, axis, upper = t, k, True
                    elif dk < -1e-12:
                        t = (room[k] - ok) / dk
                        if t < texit:
                            texit, axis, upper = t, k, False
                if axis >= 0 and _EPS < texit < tbest:
                    tbest = texit
                    hx, hy, hz = ox + texit * dx, oy + texit * dy, oz + texit * dz
                    best[0] = texit
                    best[1] = 0.0
                    best[2] = 0.0
                    best[3] = 0.0
                    best[1 + axis] = -1.0 if upper else 1.0
                    if axis == 2:
                        mat = int(room[6]) if not upper else int(room[8])
                        best[4] = hx
                        best[5] = hy
                    else:
                        mat = int(room[7])
                        best[4] = hy if axis == 0 else hx
                        best[5] = hz
            if mat < 0:
                out_depth[y, x] = np.inf
                for k in range(3):
                    out_rgb[y, x, k] = background[k]
                continue
            out_depth[y, x] = tbest
            nx, ny, nz = best[1], best[2], best[3]
            # pixel footprint on the surface (m): ray length per pixel over the incidence cosine
            dlen = math.sqrt(dx * dx + dy * dy + dz * dz)
            cos_i = abs(nx * dx + ny * dy + nz * dz) / dlen
            _albedo(mats, mat, best[4], best[5], tbest * dlen * pixel_angle / max(cos_i, 0.25), alb)
            px, py, pz = ox + tbest * dx, oy + tbest * dy, oz + tbest * dz
            lr = ambient
            lg = ambient
            lb = ambient
            for li in range(lights.shape[0]):
                if lights[li, 0] == 0.0:
                    lx, ly, lz = -lights[li, 1], -lights[li, 2], -lights[li, 3]
                    dist = np.inf
                    att = 1.0
                else:
                    lx, ly, lz = lights[li, 1] - px, lights[li, 2] - py, lights[li, 3] - pz
                    dist = math.sqrt(lx * lx + ly * ly + lz * lz)
                    if dist < 1e-9:
                        continue
                    lx, ly, lz = lx / dist, ly / dist, lz / dist
                    q = dist / lights[li, 7]
                    att = 1.0 / (1.0 + q * q)
                ndl = nx * lx + ny * ly + nz * lz
                if ndl <= 0.0:
                    continue
                if lights[li, 8] > 0.0:
                    sx = px + _SHADOW_BIAS * nx
                    sy = py + _SHADOW_BIAS * ny
                    sz = pz + _SHADOW_BIAS * nz
                    if _occluded(boxes, cyls, sx, sy, sz, lx, ly, lz, dist, scratch):
                        continue
                w = ndl * att
                lr += lights[li, 4] * w
                lg += lights[li, 5] * w
                lb += lights[li, 6] * w
            gr = 1.0
            gg = 1.0
            gb = 1.0
            for ri in range(regions.shape[0]):
                if (regions[ri, 0] <= px <= regions[ri, 3] and regions[ri, 1] <= py <= regions[ri, 4]
                        and regions[ri, 2] <= pz <= regions[ri, 5]):
                    gr *= regions[ri, 6]
                    gg *= regions[ri, 7]
                    gb *= regions[ri, 8]
            out_rgb[y, x, 0] = min(1.0, alb[0] * lr * gr)
            out_rgb[y, x, 1] = min(1.0, alb[1] * lg * gg)
            out_rgb[y, x, 2] = min(1.0, alb[2] * lb * gb)


# ----------------------------------------------------------------------------------------------
# public API


def render_shapes(camera: Camera, shapes: tuple[Shape, ...] | list[Shape], state: Lighting,
                  room: np.ndarray | None = None, mats: MaterialTable | None = None,
                  background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Ray cast ``shapes`` (plus an optional packed room) lit by ``state``: (rgb H×W×3 f32, depth H×W f32)."""
    mats = mats or MaterialTable()
    boxes, cyls = pack_shapes(shapes, mats)
    lights, regions = pack_lights(state)
    origin, dirs = world_rays(camera)
    rgb = np.empty((camera.height, camera.width, 3), np.float32)
    depth = np.empty((camera.height, camera.width), np.float32)
    box_rects = screen_rects(camera, box_corners(boxes))
    cyl_rects = screen_rects(camera, cylinder_corners(cyls))
    render_kernel(origin, dirs, boxes, cyls, box_rects, cyl_rects,
                  room if room is not None else np.zeros(9), room is not None,
                  mats.array(), lights, regions, float(state.ambient), np.asarray(background, np.float64),
                  1.0 / camera.intrinsics.fx, rgb, depth)
    return rgb, depth
