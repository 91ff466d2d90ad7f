"""The public forward renderer, :func:`render` → :class:`RenderOutput` (numba, no torch): projection and culling, depth
sort, SH colour, tile binning and float32 compositing (:mod:`~gsrmr_splat.display_raster`). Conventions and pipeline:
docs/splatting.md, "Conventions" and "How the fast path works".
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
    """What :func:`render` returns: float32 images of the camera's size, H×W pixels.

    Attributes:
        rgb: H×W×3 colour, RGB in [0, 1] (clipped), the background included.
        alpha: H×W accumulated opacity, 1 − the final transmittance.
        depth: H×W alpha-normalised expected depth Σ T·α·z / alpha: camera-space z in metres (along the optical
            axis, not the ray length); 0 where alpha is 0.
        num_visible: How many Gaussians survived culling and were composited.

    Example:
        ::

            out = render(model, camera)
            hit = out.alpha > 0.5
            mean_depth_m = float(out.depth[hit].mean())
    """

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
    """Render ``model`` seen by ``camera`` over a flat ``background`` colour.

    numba only (torch is never imported); a pure function of its inputs, which several Python threads may call at
    once. Gaussians with NaN parameters are culled, so the output never holds NaN. The rules (near plane,
    footprint, alpha, compositing): docs/splatting.md, "Conventions".

    Args:
        model: The Gaussians, world frame, metres.
        camera: A :class:`gsrmr_common.camera.Camera`: OpenCV axes (x right, y down, z forward), a world→camera
            4×4 rigid transform in metres, pinhole intrinsics in pixels with pixel centres at +0.5.
        background: RGB in [0, 1] (three values, or one grey value), composited behind the Gaussians.
        near_m: Gaussians whose camera z is below this (metres) are culled.
        sh_degree: Cap on the SH degree used (None: the model's).
        tile: Tile size in pixels: the default takes the float32 display kernel, another size the float64 training
            kernel (for tests).
        threads: numba thread count for this call (None: numba's current setting, all cores by default; 1 is
            faster when the cores are already busy with other processes).

    Returns:
        RenderOutput: ``rgb`` H×W×3 in [0, 1], ``alpha`` and ``depth`` (camera z, metres) H×W, and the count of
        visible Gaussians.

    Raises:
        ValueError: The image has more than :data:`MAX_PIXELS` pixels, or ``background`` is not 3 finite values.

    Example:
        ::

            import math
            from gsrmr_common.camera import CameraMount, Intrinsics, camera_from_pose

            model = GaussianModel.load_ply("room.ply")
            camera = camera_from_pose(1.0, 0.5, 0.0, CameraMount(), Intrinsics.from_fov(320, 240, math.radians(70)))
            out = render(model, camera, (0.0, 0.0, 0.0), threads=1)
            out.rgb.shape  # (240, 320, 3)
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
