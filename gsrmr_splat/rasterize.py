"""Numba tile rasterizer in float64, the torch training engine's: binning, front-to-back compositing and its exact
backward pass (:mod:`~gsrmr_splat.display_raster` is the faster float32 forward of :func:`~gsrmr_splat.render.render`,
:mod:`~gsrmr_splat.fused_raster` the fused engine's). Gaussians come *packed* in depth order, one row each
(:func:`pack`); tiles run in parallel, dealt interleaved, and the backward gives every thread its own gradient buffer.
Rules: docs/splatting.md, "Conventions" and "How the fast path works".
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

TILE = 16
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1e-4
PACK_WIDTH = 12
SPAN_MARGIN_PX = 1e-3
N_CHUNKS = 64  # interleaved work units of the forward prange


@nb.njit(cache=True)
def bin_kernel(box, tile, tiles_x, tiles_y):
    """Tile lists from per-Gaussian pixel boxes (rows already in depth order).

    Returns (offsets of length tiles_x·tiles_y + 1, flat list of packed-row indices); each tile's
    slice is in depth order because rows are visited in order (a counting sort by tile).
    """
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, np.int64)
    m = box.shape[0]
    for k in range(m):
        for ty in range(box[k, 2] // tile, box[k, 3] // tile + 1):
            for tx in range(box[k, 0] // tile, box[k, 1] // tile + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    fill = offsets[:-1].copy()
    lst = np.empty(offsets[-1], np.int32)
    for k in range(m):
        for ty in range(box[k, 2] // tile, box[k, 3] // tile + 1):
            for tx in range(box[k, 0] // tile, box[k, 1] // tile + 1):
                t = ty * tiles_x + tx
                lst[fill[t]] = k
                fill[t] += 1
    return offsets, lst


@nb.njit(parallel=True, cache=True, fastmath=True)
def forward_kernel(packed, box, offsets, lst, width, height, tile, tiles_x, bg, out_rgb, out_alpha, out_depth,
                   out_t, out_last):
    """Composite every pixel; writes rgb, alpha, depth, final transmittance and last list position.

    Gaussian-major inside a tile: each listed Gaussian updates only the pixels of its
    opacity-limited box (outside it α < 1/255 anyway), in depth order; the tile stops early when
    every pixel has reached T < 1e-4.
    """
    n_tiles = offsets.shape[0] - 1
    for chunk in nb.prange(N_CHUNKS):  # interleaved tiles: balanced threads (see module docstring)
        for t in range(chunk, n_tiles, N_CHUNKS):
            ty, tx = t // tiles_x, t % tiles_x
            x0, y0 = tx * tile, ty * tile
            x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
            tw = x1 - x0
            npix = tw * (y1 - y0)
            start, end = offsets[t], offsets[t + 1]
            trans = np.ones(npix)
            col = np.zeros((npix, 4))
            last = np.full(npix, start)
            done = np.zeros(npix, np.bool_)
            row_left = np.full(y1 - y0, tw)  # pixels of each tile row still compositing
            n_done = 0
            for j in range(start, end):
                k = lst[j]
                mx, my = packed[k, 0], packed[k, 1]
                ca, cb, cc = packed[k, 2], packed[k, 3], packed[k, 4]
                opac, rad, cut = packed[k, 5], packed[k, 10], packed[k, 11]
                ua, ub = max(box[k, 0], x0), min(box[k, 1] + 1, x1)
                for v in range(max(box[k, 2], y0), min(box[k, 3] + 1, y1)):
                    dy = v + 0.5 - my
                    if abs(dy) > rad or row_left[v - y0] == 0:
                        continue
                    # exact span of this row where σ ≤ cut (½a·dx² + b·dy·dx + ½c·dy² − cut ≤ 0), widened
                    # by SPAN_MARGIN_PX so rounding never drops a pixel; each pixel is still tested below
                    disc = (cb * dy) * (cb * dy) - ca * (cc * dy * dy - 2.0 * cut)
                    if disc < 0.0:
                        continue
                    root = math.sqrt(disc)
                    lo = mx - 0.5 + (-cb * dy - root) / ca - SPAN_MARGIN_PX
                    hi = mx - 0.5 + (-cb * dy + root) / ca + SPAN_MARGIN_PX
                    u_lo = max(ua, int(math.ceil(lo)))
                    u_hi = min(ub, int(math.floor(hi)) + 1)
                    if u_lo >= u_hi:
                        continue
                    row = (v - y0) * tw - x0
                    # exp(−σ) along the row by recurrence: σ(dx + 1) − σ(dx) = a·dx + a/2 + b·dy, whose
                    # increments grow by a per pixel, so two multiplications replace one exp per pixel
                    dx0 = u_lo + 0.5 - mx
                    gauss = math.exp(-(0.5 * (ca * dx0 * dx0 + cc * dy * dy) + cb * dx0 * dy))
                    ratio = math.exp(-(ca * dx0 + 0.5 * ca + cb * dy))
                    ratio_step = math.exp(-ca)
                    for u in range(u_lo, u_hi):
                        g_u = gauss
                        gauss *= ratio
                        ratio *= ratio_step
                        p = row + u
                        if done[p]:
                            continue
                        if abs(u + 0.5 - mx) > rad:
                            continue
                        alpha = min(ALPHA_MAX, opac * g_u)
                        if alpha < ALPHA_MIN:
                            continue
                        tp = trans[p]
                        t_next = tp * (1.0 - alpha)
                        if t_next < T_MIN:
                            done[p] = True
                            n_done += 1
                            row_left[v - y0] -= 1
                            continue
                        w = alpha * tp
                        col[p, 0] += w * packed[k, 6]
                        col[p, 1] += w * packed[k, 7]
                        col[p, 2] += w * packed[k, 8]
                        col[p, 3] += w * packed[k, 9]
                        trans[p] = t_next
                        last[p] = j + 1
                if n_done == npix:
                    break
            for v in range(y0, y1):
                for u in range(x0, x1):
                    p = (v - y0) * tw + (u - x0)
                    tp = trans[p]
                    out_rgb[v, u, 0] = col[p, 0] + tp * bg[0]
                    out_rgb[v, u, 1] = col[p, 1] + tp * bg[1]
                    out_rgb[v, u, 2] = col[p, 2] + tp * bg[2]
                    a = 1.0 - tp
                    out_alpha[v, u] = a
                    out_depth[v, u] = col[p, 3] / a if a > 1e-8 else 0.0
                    out_t[v, u] = tp
                    out_last[v, u] = last[p]


@nb.njit(parallel=True, cache=True, fastmath=True)
def backward_kernel(packed, box, offsets, lst, width, height, tile, tiles_x, bg, final_t, last_pos, g_rgb,
                    g_alpha, n_chunks, grads):
    """Gradients of the loss w.r.t. each packed row, given dL/d rgb (H×W×3) and dL/d alpha (H×W).

    ``grads`` is (n_chunks, M, 9): d/d (mx, my, conic_a, conic_b, conic_c, opacity, r, g, b);
    chunk c handles tiles c, c + n_chunks, … so threads never write the same buffer. Walks each
    tile's list back to front, undoing the transmittance (T_i = T_{i+1} / (1 − α_i)) as 3DGS does.
    """
    n_tiles = offsets.shape[0] - 1
    for ch in nb.prange(n_chunks):
        gbuf = grads[ch]
        for t in range(ch, n_tiles, n_chunks):
            ty, tx = t // tiles_x, t % tiles_x
            x0, y0 = tx * tile, ty * tile
            x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
            tw = x1 - x0
            npix = tw * (y1 - y0)
            start = offsets[t]
            trans = np.empty(npix)
            t_final = np.empty(npix)
            acc = np.empty((npix, 3))
            dcol = np.empty((npix, 3))
            dalpha_out = np.empty(npix)
            last = np.empty(npix, np.int64)
            jmax = start
            for v in range(y0, y1):
                for u in range(x0, x1):
                    p = (v - y0) * tw + (u - x0)
                    tf = final_t[v, u]
                    trans[p] = tf
                    t_final[p] = tf
                    for c in range(3):
                        acc[p, c] = tf * bg[c]
                        dcol[p, c] = g_rgb[v, u, c]
                    dalpha_out[p] = g_alpha[v, u]
                    last[p] = last_pos[v, u]
                    jmax = max(jmax, last_pos[v, u])
            for j in range(jmax - 1, start - 1, -1):
                k = lst[j]
                mx, my = packed[k, 0], packed[k, 1]
                ca, cb, cc = packed[k, 2], packed[k, 3], packed[k, 4]
                opac, rad, cut = packed[k, 5], packed[k, 10], packed[k, 11]
                c0, c1, c2 = packed[k, 6], packed[k, 7], packed[k, 8]
                ua, ub = max(box[k, 0], x0), min(box[k, 1] + 1, x1)
                for v in range(max(box[k, 2], y0), min(box[k, 3] + 1, y1)):
                    dy = v + 0.5 - my
                    if abs(dy) > rad:
                        continue
                    # same row span and exp recurrence as forward_kernel
                    disc = (cb * dy) * (cb * dy) - ca * (cc * dy * dy - 2.0 * cut)
                    if disc < 0.0:
                        continue
                    root = math.sqrt(disc)
                    u_lo = max(ua, int(math.ceil(mx - 0.5 + (-cb * dy - root) / ca - SPAN_MARGIN_PX)))
                    u_hi = min(ub, int(math.floor(mx - 0.5 + (-cb * dy + root) / ca + SPAN_MARGIN_PX)) + 1)
                    if u_lo >= u_hi:
                        continue
                    row = (v - y0) * tw - x0
                    dx0 = u_lo + 0.5 - mx
                    g_next = math.exp(-(0.5 * (ca * dx0 * dx0 + cc * dy * dy) + cb * dx0 * dy))
                    ratio = math.exp(-(ca * dx0 + 0.5 * ca + cb * dy))
                    ratio_step = math.exp(-ca)
                    for u in range(u_lo, u_hi):
                        gauss = g_next
                        g_next *= ratio
                        ratio *= ratio_step
                        p = row + u
                        if j >= last[p]:
                            continue
                        dx = u + 0.5 - mx
                        if abs(dx) > rad:
                            continue
                        raw = opac * gauss
                        alpha = min(ALPHA_MAX, raw)
                        if alpha < ALPHA_MIN:
                            continue
                        one_m = 1.0 - alpha
                        t_i = trans[p] / one_m
                        w = t_i * alpha
                        d0, d1, d2 = dcol[p, 0], dcol[p, 1], dcol[p, 2]
                        gbuf[k, 6] += w * d0
                        gbuf[k, 7] += w * d1
                        gbuf[k, 8] += w * d2
                        d_alpha = (d0 * (t_i * c0 - acc[p, 0] / one_m) + d1 * (t_i * c1 - acc[p, 1] / one_m)
                                   + d2 * (t_i * c2 - acc[p, 2] / one_m) + dalpha_out[p] * t_final[p] / one_m)
                        acc[p, 0] += w * c0
                        acc[p, 1] += w * c1
                        acc[p, 2] += w * c2
                        trans[p] = t_i
                        if raw >= ALPHA_MAX:
                            continue
                        gbuf[k, 5] += gauss * d_alpha
                        d_sig = -alpha * d_alpha
                        gbuf[k, 0] -= d_sig * (ca * dx + cb * dy)
                        gbuf[k, 1] -= d_sig * (cb * dx + cc * dy)
                        gbuf[k, 2] += d_sig * 0.5 * dx * dx
                        gbuf[k, 3] += d_sig * dx * dy
                        gbuf[k, 4] += d_sig * 0.5 * dy * dy


def depth_order(depth: np.ndarray) -> np.ndarray:
    """Positions sorting ``depth`` (all > 0) ascending, ties by position, via one uint64 key sort.

    Positive float32 bit patterns order like the floats, so (bits << 32 | position) is a unique key:
    the result equals a stable argsort, which is what 3DGS's radix sort gives on duplicated Gaussians.
    """
    bits = np.ascontiguousarray(depth, dtype=np.float32).view(np.uint32).astype(np.uint64)
    keys = (bits << np.uint64(32)) | np.arange(depth.shape[0], dtype=np.uint64)
    keys.sort()
    return (keys & np.uint64(0xFFFFFFFF)).astype(np.int64)


def pack(means2d, conic, opacity, colors, depth, radius) -> np.ndarray:
    """M×:data:`PACK_WIDTH` float64 rows in the layout the kernels read: ``(mx, my, conic_a, conic_b, conic_c,
    opacity, r, g, b, depth_z, radius, log(255·opacity))`` per Gaussian (pixels; camera z in metres)."""
    m = means2d.shape[0]
    out = np.empty((m, PACK_WIDTH), np.float64)
    out[:, 0:2] = means2d
    out[:, 2:5] = conic
    out[:, 5] = opacity
    out[:, 6:9] = colors
    out[:, 9] = depth
    out[:, 10] = radius
    with np.errstate(divide="ignore"):
        out[:, 11] = np.log(255.0 * np.asarray(opacity, np.float64)) + 1e-9
    return out


@nb.njit(parallel=True, cache=True)
def gather_pack_kernel(geom, box, order, colors, sh0, out, out_box):
    """Fused gather for the render path: packed rows and boxes of ``geom``/``box`` rows ``order``.

    Colours come from ``colors`` (M×3, already evaluated) when it has M rows, otherwise from the DC
    coefficients ``sh0`` (N×3) as max(0, C0·sh0 + 0.5).
    """
    use_sh0 = colors.shape[0] != order.shape[0]
    for j in nb.prange(order.shape[0]):
        i = order[j]
        for c in range(5):
            out[j, c] = geom[i, c]
        out[j, 5] = geom[i, 5]
        for c in range(3):
            out[j, 6 + c] = max(0.0, 0.28209479177387814 * sh0[i, c] + 0.5) if use_sh0 else colors[j, c]
        out[j, 9] = geom[i, 6]
        out[j, 10] = geom[i, 7]
        out[j, 11] = math.log(255.0 * float(geom[i, 5])) + 1e-9
        for c in range(4):
            out_box[j, c] = box[i, c]


def rasterize_packed(packed: np.ndarray, box: np.ndarray, width: int, height: int, background: np.ndarray,
                     tile: int = TILE, dtype=np.float32):
    """Forward pass over depth-ordered packed rows; returns (rgb, alpha, depth, final_T, last, bins).

    rgb/alpha/depth are ``dtype`` (float32 for display, float64 for training and gradient checks).
    """
    tiles_x, tiles_y = (width + tile - 1) // tile, (height + tile - 1) // tile
    box = np.ascontiguousarray(box, np.int64)
    offsets, lst = bin_kernel(box, tile, tiles_x, tiles_y)
    rgb = np.empty((height, width, 3), dtype)
    alpha = np.empty((height, width), dtype)
    depth = np.empty((height, width), dtype)
    final_t = np.empty((height, width), np.float64)
    last = np.empty((height, width), np.int64)
    bg = np.asarray(background, np.float64)
    forward_kernel(packed, box, offsets, lst, width, height, tile, tiles_x, bg,
                   rgb, alpha, depth, final_t, last)
    return rgb, alpha, depth, final_t, last, (box, offsets, lst, tiles_x, tile)
