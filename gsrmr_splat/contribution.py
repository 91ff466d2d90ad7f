"""How much each Gaussian contributes to a set of views: its largest blending weight α·T at any pixel and the sum of its
weights over every pixel (a numba tile kernel with the forward pass's rules). The maximum prunes Gaussians that change
no pixel; the sum ranks them for compaction (:mod:`gsrmr_splat.compact`).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.project import NEAR_M, project_numpy
from gsrmr_splat.rasterize import TILE, bin_kernel, depth_order, pack


@nb.njit(parallel=True, cache=True)
def _weight_kernel(packed, box, offsets, lst, width, height, tile, tiles_x, n_chunks, out, total):
    """Per packed row, the largest blending weight T·α it gets at any pixel (``out``) and their sum over
    the pixels (``total``); same rules as forward."""
    n_tiles = offsets.shape[0] - 1
    for ch in nb.prange(n_chunks):
        buf = out[ch]
        acc = total[ch]
        for t in range(ch, n_tiles, n_chunks):
            ty, tx = t // tiles_x, t % tiles_x
            x0, y0 = tx * tile, ty * tile
            x1, y1 = min(x0 + tile, width), min(y0 + tile, height)
            tw = x1 - x0
            trans = np.ones(tw * (y1 - y0))
            done = np.zeros(tw * (y1 - y0), np.bool_)
            for j in range(offsets[t], offsets[t + 1]):
                k = lst[j]
                for v in range(max(box[k, 2], y0), min(box[k, 3] + 1, y1)):
                    dy = v + 0.5 - packed[k, 1]
                    if abs(dy) > packed[k, 10]:
                        continue
                    for u in range(max(box[k, 0], x0), min(box[k, 1] + 1, x1)):
                        p = (v - y0) * tw + u - x0
                        dx = u + 0.5 - packed[k, 0]
                        if done[p] or abs(dx) > packed[k, 10]:
                            continue
                        sig = 0.5 * (packed[k, 2] * dx * dx + packed[k, 4] * dy * dy) + packed[k, 3] * dx * dy
                        if sig < 0.0 or sig > packed[k, 11]:
                            continue
                        alpha = min(0.99, packed[k, 5] * math.exp(-sig))
                        if alpha < 1.0 / 255.0:
                            continue
                        t_next = trans[p] * (1.0 - alpha)
                        if t_next < 1e-4:
                            done[p] = True
                            continue
                        w = alpha * trans[p]
                        buf[k] = max(buf[k], w)
                        acc[k] += w
                        trans[p] = t_next


def blend_weights(model: GaussianModel, cameras: list[Camera], near_m: float = NEAR_M) -> tuple[np.ndarray, np.ndarray]:
    """For each Gaussian, (the sum of its blending weights T·α over every pixel of every camera, the
    largest one): its accumulated contribution to those views and whether it changes any pixel at all."""
    best = np.zeros(model.num_gaussians)
    acc = np.zeros(model.num_gaussians)
    n_chunks = max(1, nb.get_num_threads())
    for cam in cameras:
        k = cam.intrinsics
        geom, box = project_numpy(model.means, model.quats, model.log_scales, model.opacity_logits,
                                  cam.world_to_camera, (k.fx, k.fy, k.cx, k.cy), k.width, k.height, near_m)
        vis = np.nonzero((box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3]))[0]
        order = vis[depth_order(geom[vis, 6])]
        g = geom[order]
        packed = pack(g[:, 0:2], g[:, 2:5], g[:, 5], np.zeros((len(order), 3)), g[:, 6], g[:, 7])
        b = np.ascontiguousarray(box[order], np.int64)
        tiles_x, tiles_y = (k.width + TILE - 1) // TILE, (k.height + TILE - 1) // TILE
        offsets, lst = bin_kernel(b, TILE, tiles_x, tiles_y)
        out = np.zeros((n_chunks, len(order)))
        total = np.zeros((n_chunks, len(order)))
        _weight_kernel(packed, b, offsets, lst, k.width, k.height, TILE, tiles_x, n_chunks, out, total)
        np.maximum.at(best, order, out.max(axis=0))
        np.add.at(acc, order, total.sum(axis=0))
    return acc, best


def max_blend_weight(model: GaussianModel, cameras: list[Camera], near_m: float = NEAR_M) -> np.ndarray:
    """For each Gaussian, its largest blending weight T·α over every pixel of every camera."""
    return blend_weights(model, cameras, near_m)[1]
