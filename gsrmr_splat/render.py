"""Public forward renderer: ``render(model, camera, background) -> RenderOutput``.

Camera: :class:`gsrmr_common.camera.Camera` (OpenCV axes, world→camera 4×4, pixel centres at +0.5).
Pipeline: numba projection and culling (near plane :data:`~gsrmr_splat.project.NEAR_M`) →
uint64 depth/index key sort → SH colour of the visible Gaussians → numba tile binning → parallel
float32 compositing (:mod:`~gsrmr_splat.display_raster`; another ``tile`` size takes the
float64 training kernel, for tests). Conventions are listed in :mod:`~gsrmr_splat.project` and
:mod:`~gsrmr_splat.rasterize`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_splat.display_raster import TILE as DISPLAY_TILE
from gsrmr_splat.display_raster import rasterize_display
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.project import NEAR_M, project_numpy
from gsrmr_splat.rasterize import (
    PACK_WIDTH,
    TILE,
    depth_order,
    gather_pack_kernel,
    rasterize_packed,
)
from gsrmr_splat.sh import eval_sh_kernel

MAX_PIXELS = 4096 * 4096


@dataclass
class RenderOutput:
    """Rendered view: ``rgb`` H×W×3 float32 in [0, 1], ``alpha`` H×W (1 − final transmittance),
    ``depth`` H×W camera-space z in metres (alpha-normalised expected depth; 0 where nothing was hit),
    and ``num_visible``, the Gaussians that survived culling."""

    rgb: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    num_visible: int


def gaussian_colors(model: GaussianModel, index: np.ndarray, camera_center_w: np.ndarray,
                    degree: int | None = None) -> np.ndarray:
    """Colours max(0, SH(dir) + 0.5) of the Gaussians ``index``, dir = normalise(mean − centre)."""
    degree = model.sh_degree if degree is None else min(degree, model.sh_degree)
    out = np.empty((index.shape[0], 3), np.float64)
    eval_sh_kernel(model.sh, model.means, np.ascontiguousarray(index, np.int64),
                   np.asarray(camera_center_w, np.float64), int(degree), out)
    return out


def _check_background(background) -> np.ndarray:
    bg = np.asarray(background, dtype=np.float64).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise ValueError(f"background must be 3 finite values (RGB in [0, 1]), got {background!r}")
    return bg


def render(model: GaussianModel, camera: Camera, background=(0.0, 0.0, 0.0), *, near_m: float = NEAR_M,
           sh_degree: int | None = None, tile: int = TILE, threads: int | None = None) -> RenderOutput:
    """Render ``model`` seen by ``camera`` over a flat ``background`` colour (RGB in [0, 1]).

    ``sh_degree`` caps the SH degree used (None = the model's). ``threads`` sets the numba thread
    count for this call (None = numba's current setting, all cores by default; 1 is faster when the
    cores are already busy with other processes). Raises ValueError for an image larger than
    :data:`MAX_PIXELS` or a non-finite background; NaN parameters are culled (never NaN output).
    """
    if threads is not None:
        previous = numba.get_num_threads()
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
        try:
            return render(model, camera, background, near_m=near_m, sh_degree=sh_degree, tile=tile)
        finally:
            numba.set_num_threads(previous)
    bg = _check_background(background)
    width, height = camera.width, camera.height
    if width * height > MAX_PIXELS:
        raise ValueError(f"render: {width}×{height} exceeds the {MAX_PIXELS}-pixel limit")
    k = camera.intrinsics
    intr = (k.fx, k.fy, k.cx, k.cy)
    geom, box = project_numpy(model.means, model.quats, model.log_scales, model.opacity_logits,
                              camera.world_to_camera, intr, width, height, near_m)
    visible = np.nonzero((box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3]))[0]
    order = visible[depth_order(geom[visible, 6])]
    degree = model.sh_degree if sh_degree is None else min(sh_degree, model.sh_degree)
    if degree == 0:
        colors = np.zeros((0, 3))
    else:
        colors = gaussian_colors(model, order, camera.center_world, degree)
        bad = ~np.all(np.isfinite(colors), axis=1)
        if bad.any():  # NaN SH: drop those Gaussians instead of painting NaN
            order, colors = order[~bad], colors[~bad]
    fast = tile == DISPLAY_TILE
    packed = np.empty((order.shape[0], PACK_WIDTH), np.float32 if fast else np.float64)
    pbox = np.empty((order.shape[0], 4), np.int64)
    gather_pack_kernel(geom, box, order, colors, np.ascontiguousarray(model.sh[:, 0, :]), packed, pbox)
    if degree == 0 and not np.all(np.isfinite(packed[:, 6:9])):
        ok = np.all(np.isfinite(packed[:, 6:9]), axis=1)
        packed, pbox = np.ascontiguousarray(packed[ok]), np.ascontiguousarray(pbox[ok])
    if fast:
        rgb, alpha, depth = rasterize_display(packed, pbox, width, height, bg)
    else:
        rgb, alpha, depth, _, _, _ = rasterize_packed(packed, pbox, width, height, bg, tile)
    np.clip(rgb, 0.0, 1.0, out=rgb)
    return RenderOutput(rgb, alpha, depth, int(packed.shape[0]))
