"""The display rasterizer: forward-only float32 compositing for :func:`~gsrmr_splat.render.render`, with the rules of
the float64 training kernel :func:`~gsrmr_splat.rasterize.forward_kernel`. A Gaussian is blended into a whole 16-pixel
tile row at a time, branch-free, with :func:`~gsrmr_splat.fastexp.exp_neg` and float32 state (half the bytes) in one
flat array indexed by unsigned integers, so that LLVM vectorises the row; tiles are dealt to threads interleaved, and
the output does not depend on the thread count. Why each: docs/splatting.md, "How the fast path works", step 4.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from gsrmr_splat.fastexp import exp_neg
from gsrmr_splat.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN, bin_kernel

TILE = 16  # pixels; one tile row is one (or two) SIMD registers of float32
N_CHUNKS = 64  # interleaved work units for prange (≫ threads, so a static split still balances)
_PLANE = TILE * TILE  # one state plane: T, then r, g, b, z (weighted), then "still compositing"
_U_TILE = np.uint64(TILE)
_U_PLANE = np.uint64(_PLANE)
_U_R, _U_G, _U_B = np.uint64(_PLANE), np.uint64(2 * _PLANE), np.uint64(3 * _PLANE)
_U_Z, _U_LIVE = np.uint64(4 * _PLANE), np.uint64(5 * _PLANE)
_F1, _F0, _FH = np.float32(1.0), np.float32(0.0), np.float32(0.5)
_AMAX, _AMIN, _TMIN = np.float32(ALPHA_MAX), np.float32(ALPHA_MIN), np.float32(T_MIN)
_TINY = np.float32(1e-8)


@nb.njit(inline="always", fastmath=True, cache=True)
def _blend_row(state, base, du, mx, half_a, half_c_dy2, b_dy, opacity, radius, red, green, blue, depth):
    """Blend one Gaussian into the 16 pixels of one tile row; returns how many pixels finished."""
    n_end = 0
    for i in range(_U_TILE):
        p = base + i
        dx = du[i] - mx
        sigma = (half_a * dx + b_dy) * dx + half_c_dy2
        alpha = min(_AMAX, opacity * exp_neg(-sigma))
        # σ < 0 only by rounding of a near-singular conic: skipped, as 3DGS does ("power > 0")
        ok = (alpha >= _AMIN) & (sigma >= _F0) & (abs(dx) <= radius) & (state[p + _U_LIVE] > _F0)
        t_p = state[p]
        t_next = t_p * (_F1 - alpha)
        end = ok & (t_next < _TMIN)
        blend = ok & (t_next >= _TMIN)
        w = alpha * t_p if blend else _F0
        state[p + _U_R] += w * red
        state[p + _U_G] += w * green
        state[p + _U_B] += w * blue
        state[p + _U_Z] += w * depth
        state[p] = t_next if blend else t_p
        state[p + _U_LIVE] = _F0 if end else state[p + _U_LIVE]
        n_end += 1 if end else 0
    return n_end


@nb.njit(parallel=True, fastmath=True, cache=True)
def display_kernel(packed, box, offsets, lst, width, height, tiles_x, bg, out_rgb, out_alpha, out_depth):
    """Composite every pixel into ``out_rgb`` (H×W×3), ``out_alpha`` and ``out_depth`` (H×W), float32.

    ``packed`` float32 rows in depth order (layout of :func:`~gsrmr_splat.rasterize.pack`),
    ``box`` their pixel boxes, ``offsets``/``lst`` from :func:`~gsrmr_splat.rasterize.bin_kernel`
    with :data:`TILE`.
    """
    n_tiles = offsets.shape[0] - 1
    for chunk in nb.prange(N_CHUNKS):
        state = np.empty(6 * _PLANE, np.float32)
        row_live = np.empty(TILE, np.int64)
        du = np.empty(TILE, np.float32)
        for t in range(chunk, n_tiles, N_CHUNKS):
            x0, y0 = (t % tiles_x) * TILE, (t // tiles_x) * TILE
            x1, y1 = min(x0 + TILE, width), min(y0 + TILE, height)
            n_live = 0
            for r in range(TILE):
                row_live[r] = 0
                for i in range(TILE):
                    p = r * TILE + i
                    inside = y0 + r < height and x0 + i < width  # edge tiles: outside pixels start done
                    state[p] = _F1
                    for c in range(1, 5):
                        state[p + c * _PLANE] = _F0
                    state[p + 5 * _PLANE] = _F1 if inside else _F0
                    row_live[r] += 1 if inside else 0
                n_live += row_live[r]
            for i in range(TILE):
                du[i] = np.float32(x0 + i) + _FH
            for j in range(offsets[t], offsets[t + 1]):
                k = lst[j]
                mx, my = packed[k, 0], packed[k, 1]
                half_a, cb, half_c = _FH * packed[k, 2], packed[k, 3], _FH * packed[k, 4]
                opacity, radius = packed[k, 5], packed[k, 10]
                for v in range(max(box[k, 2], y0), min(box[k, 3] + 1, y1)):
                    r = v - y0
                    if row_live[r] == 0:
                        continue
                    dy = np.float32(v) + _FH - my
                    if abs(dy) > radius:
                        continue
                    n_end = _blend_row(state, np.uint64(r) * _U_TILE, du, mx, half_a, half_c * dy * dy, cb * dy,
                                       opacity, radius, packed[k, 6], packed[k, 7], packed[k, 8], packed[k, 9])
                    row_live[r] -= n_end
                    n_live -= n_end
                if n_live == 0:
                    break
            for v in range(y0, y1):
                for u in range(x0, x1):
                    p = (v - y0) * TILE + (u - x0)
                    t_p = state[p]
                    out_rgb[v, u, 0] = state[p + _PLANE] + t_p * bg[0]
                    out_rgb[v, u, 1] = state[p + 2 * _PLANE] + t_p * bg[1]
                    out_rgb[v, u, 2] = state[p + 3 * _PLANE] + t_p * bg[2]
                    a = _F1 - t_p
                    out_alpha[v, u] = a
                    out_depth[v, u] = state[p + 4 * _PLANE] / a if a > _TINY else _F0


def rasterize_display(packed: np.ndarray, box: np.ndarray, width: int, height: int,
                      background: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rgb H×W×3, alpha H×W, depth H×W), float32, from depth-ordered float32 ``packed`` rows."""
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    offsets, lst = bin_kernel(np.ascontiguousarray(box), TILE, tiles_x, tiles_y)
    rgb = np.empty((height, width, 3), np.float32)
    alpha = np.empty((height, width), np.float32)
    depth = np.empty((height, width), np.float32)
    display_kernel(np.ascontiguousarray(packed, np.float32), box, offsets, lst, width, height, tiles_x,
                   np.asarray(background, np.float32), rgb, alpha, depth)
    return rgb, alpha, depth
