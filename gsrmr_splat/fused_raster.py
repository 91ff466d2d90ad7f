"""The fused engine's rasterizer: float32 forward and backward over whole 16-pixel tile rows, vectorised as
:mod:`~gsrmr_splat.display_raster`, with the rules of :func:`~gsrmr_splat.rasterize.forward_kernel` and
:func:`~gsrmr_splat.rasterize.backward_kernel`. The forward keeps per pixel the final transmittance and the list
position after its last blend; the backward walks each tile's list back to front, undoing T_i = T_{i+1} / (1 − α_i), and
computes α with the forward's code (:func:`_alpha`), so it blends exactly the Gaussians the forward blended.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from gsrmr_splat.fastexp import exp_neg
from gsrmr_splat.rasterize import ALPHA_MAX, ALPHA_MIN, T_MIN

TILE = 16
N_CHUNKS = 64  # interleaved work units of the forward prange
_PLANE = TILE * TILE
_U_TILE = np.uint64(TILE)
# forward state planes: T, r, g, b, live, last (list position after the last blend, tile-local, as float32)
_U_R, _U_G, _U_B = np.uint64(_PLANE), np.uint64(2 * _PLANE), np.uint64(3 * _PLANE)
_U_LIVE, _U_LAST = np.uint64(4 * _PLANE), np.uint64(5 * _PLANE)
# backward state planes: T, acc r, g, b, dL/dC r, g, b, last
_U_AR, _U_AG, _U_AB = np.uint64(_PLANE), np.uint64(2 * _PLANE), np.uint64(3 * _PLANE)
_U_DR, _U_DG, _U_DB = np.uint64(4 * _PLANE), np.uint64(5 * _PLANE), np.uint64(6 * _PLANE)
_U_BLAST = np.uint64(7 * _PLANE)
# per-lane gradient accumulator planes of the backward: d/d mx, my, conic a, b, c, opacity, r, g, b
_A_MY, _A_CA, _A_CB, _A_CC = np.uint64(TILE), np.uint64(2 * TILE), np.uint64(3 * TILE), np.uint64(4 * TILE)
_A_O, _A_R, _A_G, _A_B = np.uint64(5 * TILE), np.uint64(6 * TILE), np.uint64(7 * TILE), np.uint64(8 * TILE)
_F1, _F0, _FH = np.float32(1.0), np.float32(0.0), np.float32(0.5)
_AMAX, _AMIN, _TMIN = np.float32(ALPHA_MAX), np.float32(ALPHA_MIN), np.float32(T_MIN)


@nb.njit(inline="always", fastmath=True, cache=True)
def _alpha(du_i, u_lo, u_hi, mx, half_a, half_c_dy2, b_dy, opacity, radius):
    """(dx, exp(−σ), raw α = o·exp(−σ), α, mask) of the pixel centred at column ``du_i``: the one definition both
    passes use. The mask: α ≥ 1/255, σ ≥ 0, abs(dx) ≤ radius and the column inside the Gaussian's box
    [u_lo, u_hi] (centres), as the float64 kernels."""
    dx = du_i - mx
    sigma = (half_a * dx + b_dy) * dx + half_c_dy2
    gauss = exp_neg(-sigma)
    raw = opacity * gauss
    alpha = min(_AMAX, raw)
    ok = (alpha >= _AMIN) & (sigma >= _F0) & (abs(dx) <= radius) & (du_i >= u_lo) & (du_i <= u_hi)
    return dx, gauss, raw, alpha, ok


@nb.njit(inline="always", fastmath=True, cache=True)
def _blend_row(state, base, du, u_lo, u_hi, jl, mx, half_a, half_c_dy2, b_dy, opacity, radius, red, green, blue):
    """Blend one Gaussian (tile-local list position + 1: ``jl``; box columns [u_lo, u_hi]) into one tile row;
    returns pixels finished."""
    n_end = 0
    for i in range(_U_TILE):
        p = base + i
        _, _, _, alpha, ok = _alpha(du[i], u_lo, u_hi, mx, half_a, half_c_dy2, b_dy, opacity, radius)
        ok = ok & (state[p + _U_LIVE] > _F0)
        t_p = state[p]
        t_next = t_p * (_F1 - alpha)
        end = ok & (t_next < _TMIN)
        blend = ok & (t_next >= _TMIN)
        w = alpha * t_p if blend else _F0
        state[p + _U_R] += w * red
        state[p + _U_G] += w * green
        state[p + _U_B] += w * blue
        state[p] = t_next if blend else t_p
        state[p + _U_LAST] = jl if blend else state[p + _U_LAST]
        state[p + _U_LIVE] = _F0 if end else state[p + _U_LIVE]
        n_end += 1 if end else 0
    return n_end


@nb.njit(parallel=True, fastmath=True, cache=True)
def forward_kernel32(packed, box, offsets, lst, width, height, tiles_x, bg, out_rgb, out_t, out_last):
    """Composite every pixel: ``out_rgb`` (H×W×3 float32), final transmittance ``out_t`` (H×W float32) and
    ``out_last`` (H×W int64: list position after the last Gaussian blended, the tile's start if none)."""
    n_tiles = offsets.shape[0] - 1
    for chunk in nb.prange(N_CHUNKS):
        state = np.empty(6 * _PLANE, np.float32)
        row_live = np.empty(TILE, np.int64)
        du = np.empty(TILE, np.float32)
        for t in range(chunk, n_tiles, N_CHUNKS):
            x0, y0 = (t % tiles_x) * TILE, (t // tiles_x) * TILE
            x1, y1 = min(x0 + TILE, width), min(y0 + TILE, height)
            start = offsets[t]
            n_live = 0
            for r in range(TILE):
                row_live[r] = 0
                for i in range(TILE):
                    p = r * TILE + i
                    inside = y0 + r < height and x0 + i < width
                    state[p] = _F1
                    for c in range(1, 4):
                        state[p + c * _PLANE] = _F0
                    state[p + 4 * _PLANE] = _F1 if inside else _F0
                    state[p + 5 * _PLANE] = _F0
                    row_live[r] += 1 if inside else 0
                n_live += row_live[r]
            for i in range(TILE):
                du[i] = np.float32(x0 + i) + _FH
            for j in range(start, offsets[t + 1]):
                k = lst[j]
                mx, my = packed[k, 0], packed[k, 1]
                half_a, cb, half_c = _FH * packed[k, 2], packed[k, 3], _FH * packed[k, 4]
                opacity, radius = packed[k, 5], packed[k, 10]
                red, green, blue = packed[k, 6], packed[k, 7], packed[k, 8]
                jl = np.float32(j - start + 1)
                u_lo, u_hi = np.float32(box[k, 0]) + _FH, np.float32(box[k, 1]) + _FH
                for v in range(max(box[k, 2], y0), min(box[k, 3] + 1, y1)):
                    r = v - y0
                    if row_live[r] == 0:
                        continue
                    dy = np.float32(v) + _FH - my
                    if abs(dy) > radius:
                        continue
                    n_end = _blend_row(state, np.uint64(r) * _U_TILE, du, u_lo, u_hi, jl, mx, half_a, half_c * dy * dy,
                                       cb * dy, opacity, radius, red, green, blue)
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
                    out_t[v, u] = t_p
                    out_last[v, u] = start + int(state[p + 5 * _PLANE])


@nb.njit(inline="always", fastmath=True, cache=True)
def _grad_row(state, base, du, u_lo, u_hi, jl, mx, half_a, half_c_dy2, b_dy, dy, ca, cb, cc, opacity, radius, red,
              green, blue, acc):
    """One Gaussian's gradient terms over one tile row, added per lane to ``acc`` (9 planes of TILE: d/d mx, my,
    a, b, c, opacity, r, g, b), undoing its blend in the row's state (back to front)."""
    for i in range(_U_TILE):
        p = base + i
        dx, gauss, raw, alpha, ok = _alpha(du[i], u_lo, u_hi, mx, half_a, half_c_dy2, b_dy, opacity, radius)
        ok = ok & (jl <= state[p + _U_BLAST])
        inv = _F1 / (_F1 - alpha)
        t_p = state[p]
        t_i = t_p * inv
        w = t_i * alpha
        d0, d1, d2 = state[p + _U_DR], state[p + _U_DG], state[p + _U_DB]
        a0, a1, a2 = state[p + _U_AR], state[p + _U_AG], state[p + _U_AB]
        d_alpha = d0 * (t_i * red - a0 * inv) + d1 * (t_i * green - a1 * inv) + d2 * (t_i * blue - a2 * inv)
        acc[i + _A_R] += w * d0 if ok else _F0
        acc[i + _A_G] += w * d1 if ok else _F0
        acc[i + _A_B] += w * d2 if ok else _F0
        state[p + _U_AR] = a0 + w * red if ok else a0
        state[p + _U_AG] = a1 + w * green if ok else a1
        state[p + _U_AB] = a2 + w * blue if ok else a2
        state[p] = t_i if ok else t_p
        ok2 = ok & (raw < _AMAX)
        d_sig = -alpha * d_alpha if ok2 else _F0
        acc[i + _A_O] += gauss * d_alpha if ok2 else _F0
        acc[i] -= d_sig * (ca * dx + cb * dy)
        acc[i + _A_MY] -= d_sig * (cb * dx + cc * dy)
        acc[i + _A_CA] += d_sig * _FH * dx * dx
        acc[i + _A_CB] += d_sig * dx * dy
        acc[i + _A_CC] += d_sig * _FH * dy * dy


@nb.njit(cache=True)
def bin_entries_kernel(box, tiles_x, tiles_y, perm):
    """Tile lists of depth-ordered rows (:func:`~gsrmr_splat.rasterize.bin_kernel`, :data:`TILE`) and
    where each list entry's gradient goes: returns (offsets, lst, entry_start, entry_of). Row j (depth order) is
    Gaussian number ``perm[j]`` in index order (``order = visible[perm]``); the gradients of the entries of the
    Gaussian q-th in index order are rows entry_start[q] … entry_start[q + 1] − 1 (its tiles in row-major order),
    and list position p writes row entry_of[p]. So the chain rule reads them in memory order, and summing a
    Gaussian's rows in that fixed order makes its gradient independent of the thread count."""
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, np.int64)
    m = box.shape[0]
    entry_start = np.zeros(m + 1, np.int64)
    for k in range(m):
        n_k = 0
        for ty in range(box[k, 2] // TILE, box[k, 3] // TILE + 1):
            for tx in range(box[k, 0] // TILE, box[k, 1] // TILE + 1):
                counts[ty * tiles_x + tx + 1] += 1
                n_k += 1
        entry_start[perm[k] + 1] = n_k
    for q in range(m):
        entry_start[q + 1] += entry_start[q]
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    lst = np.empty(offsets[-1], np.int32)
    entry_of = np.empty(offsets[-1], np.int64)
    for k in range(m):
        e = entry_start[perm[k]]
        for ty in range(box[k, 2] // TILE, box[k, 3] // TILE + 1):
            for tx in range(box[k, 0] // TILE, box[k, 1] // TILE + 1):
                t = ty * tiles_x + tx
                lst[fill[t]] = k
                entry_of[fill[t]] = e
                e += 1
                fill[t] += 1
    return offsets, lst, entry_start, entry_of


@nb.njit(parallel=True, fastmath=True, cache=True)
def backward_kernel32(packed, box, offsets, lst, width, height, tiles_x, bg, final_t, last_pos, g_rgb,
                      entry_of, entry_grads):
    """Gradients given dL/d rgb (H×W×3): row entry_of[p] of ``entry_grads`` (≥ list length, 9; float32) receives,
    for tile-list position p (one Gaussian in one tile), d/d (mx, my, conic a, b, c, opacity, r, g, b) summed over
    that tile's pixels (zero for the entries behind the tile's last blend). Each tile is written by one thread."""
    n_tiles = offsets.shape[0] - 1
    for ch in nb.prange(N_CHUNKS):
        state = np.empty(8 * _PLANE, np.float32)
        row_max = np.empty(TILE, np.float32)  # per tile row: the largest 'last' (rows past it are skipped)
        du = np.empty(TILE, np.float32)
        acc = np.empty(9 * TILE, np.float32)
        for t in range(ch, n_tiles, N_CHUNKS):
            x0, y0 = (t % tiles_x) * TILE, (t // tiles_x) * TILE
            y1 = min(y0 + TILE, height)
            start = offsets[t]
            jmax = 0
            for r in range(TILE):
                row_max[r] = _F0
                for i in range(TILE):
                    p = r * TILE + i
                    v, u = y0 + r, x0 + i
                    if v < height and u < width:
                        tf = np.float32(final_t[v, u])
                        ll = last_pos[v, u] - start
                        state[p] = tf
                        state[p + 1 * _PLANE] = tf * bg[0]
                        state[p + 2 * _PLANE] = tf * bg[1]
                        state[p + 3 * _PLANE] = tf * bg[2]
                        state[p + 4 * _PLANE] = g_rgb[v, u, 0]
                        state[p + 5 * _PLANE] = g_rgb[v, u, 1]
                        state[p + 6 * _PLANE] = g_rgb[v, u, 2]
                        state[p + 7 * _PLANE] = np.float32(ll)
                        jmax = max(jmax, ll)
                        row_max[r] = max(row_max[r], np.float32(ll))
                    else:
                        state[p] = _F1
                        for c in range(1, 8):
                            state[p + c * _PLANE] = _F0
            for i in range(TILE):
                du[i] = np.float32(x0 + i) + _FH
            for j in range(start + jmax, offsets[t + 1]):
                e = entry_of[j]
                for c in range(9):
                    entry_grads[e, c] = _F0
            for j in range(start + jmax - 1, start - 1, -1):
                k = lst[j]
                mx, my = packed[k, 0], packed[k, 1]
                ca, cb, cc = packed[k, 2], packed[k, 3], packed[k, 4]
                half_a, half_c = _FH * ca, _FH * cc
                opacity, radius = packed[k, 5], packed[k, 10]
                red, green, blue = packed[k, 6], packed[k, 7], packed[k, 8]
                jl = np.float32(j - start + 1)
                u_lo, u_hi = np.float32(box[k, 0]) + _FH, np.float32(box[k, 1]) + _FH
                touched = False
                acc[:] = _F0
                for v in range(max(box[k, 2], y0), min(box[k, 3] + 1, y1)):
                    r = v - y0
                    if row_max[r] < jl:
                        continue
                    dy = np.float32(v) + _FH - my
                    if abs(dy) > radius:
                        continue
                    touched = True
                    _grad_row(state, np.uint64(r) * _U_TILE, du, u_lo, u_hi, jl, mx, half_a, half_c * dy * dy, cb * dy,
                              dy, ca, cb, cc, opacity, radius, red, green, blue, acc)
                e = entry_of[j]
                for c in range(9):
                    total = _F0
                    if touched:
                        for i in range(TILE):
                            total += acc[c * TILE + i]
                    entry_grads[e, c] = total
