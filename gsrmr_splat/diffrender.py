"""Differentiable rendering for training (:func:`render_torch`): torch projection and SH around the numba rasterizer as
an autograd Function (:class:`RasterizeFunction`). Kept apart from :mod:`~gsrmr_splat.render` so that the server's
forward path never imports torch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
import torch

from gsrmr_common.camera import Camera
from gsrmr_splat.project import EPS2D_PX2, NEAR_M, fov_limits, project_numpy
from gsrmr_splat.rasterize import TILE, backward_kernel, depth_order, pack, rasterize_packed
from gsrmr_splat.render import _check_background
from gsrmr_splat.sh import C0, num_coeffs, sh_basis


def eval_sh_torch(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Differentiable :func:`~gsrmr_splat.sh.eval_sh_numpy` (gradient 0 where the clamp is active)."""
    k = num_coeffs(degree)
    basis = torch.stack(sh_basis(dirs[:, 0], dirs[:, 1], dirs[:, 2], degree, torch), dim=1)  # N×k
    col = (basis[:, :, None] * sh[:, :k, :]).sum(dim=1)
    return torch.clamp_min(col + 0.5, 0.0)


def quat_to_rotmat_torch(quats: torch.Tensor) -> torch.Tensor:
    """N×4 (w, x, y, z), normalised here → N×3×3 rotation matrices."""
    q = quats / quats.norm(dim=1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=1).reshape(-1, 3, 3)


def project_torch(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                  world_to_camera: torch.Tensor, intr: tuple[float, float, float, float], width: int,
                  height: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Differentiable projection (same maths as :func:`project_kernel`, no culling).

    Returns (means2d N×2 px, conic N×3 (a, b, c), cov2d N×3 (xx, xy, yy) px², depth z N m).
    Callers cull with the non-differentiable numba pass (which also gives the radii and boxes).
    """
    fx, fy, cx, cy = intr
    lims = fov_limits(fx, fy, cx, cy, width, height)
    rot_w = world_to_camera[:3, :3]
    p = means @ rot_w.T + world_to_camera[:3, 3]
    x, y, z = p.unbind(1)
    z_safe = z.clamp_min(1e-6)
    tx = torch.clamp(x / z_safe, -lims[0], lims[1]) * z_safe
    ty = torch.clamp(y / z_safe, -lims[2], lims[3]) * z_safe
    zeros = torch.zeros_like(z)
    jac = torch.stack([fx / z_safe, zeros, -fx * tx / z_safe**2,
                       zeros, fy / z_safe, -fy * ty / z_safe**2], dim=1).reshape(-1, 2, 3)
    m = quat_to_rotmat_torch(quats) * torch.exp(log_scales)[:, None, :]
    pm = jac @ (rot_w[None] @ m)
    cov = pm @ pm.transpose(1, 2)
    ca = cov[:, 0, 0] + EPS2D_PX2
    cb = cov[:, 0, 1]
    cc = cov[:, 1, 1] + EPS2D_PX2
    det = (ca * cc - cb * cb).clamp_min(1e-12)
    conic = torch.stack([cc / det, -cb / det, ca / det], dim=1)
    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=1)
    return means2d, conic, torch.stack([ca, cb, cc], dim=1), z


class RasterizeFunction(torch.autograd.Function):
    """Differentiable rasterization of depth-ordered Gaussians (inputs already culled and sorted).

    Differentiable inputs: means2d M×2 px, conic M×3, colors M×3, opacity M. Non-differentiable:
    depth M, radius M, box M×4 (pixel ranges), background 3, width, height. Outputs rgb H×W×3 and
    alpha H×W in the dtype of ``means2d``."""

    @staticmethod
    def forward(ctx, means2d, conic, colors, opacity, depth, radius, box, background, width, height):
        packed = pack(means2d.detach().numpy(), conic.detach().numpy(), opacity.detach().numpy(),
                      colors.detach().numpy(), depth.detach().numpy(), radius.detach().numpy())
        bg = np.asarray(background, np.float64)
        rgb, alpha, _, final_t, last, bins = rasterize_packed(packed, box, width, height, bg, TILE, np.float64)
        ctx.saved = (packed, bins, bg, final_t, last, width, height)
        ctx.dtype = means2d.dtype
        return torch.from_numpy(rgb).to(means2d.dtype), torch.from_numpy(alpha).to(means2d.dtype)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha):
        packed, (box, offsets, lst, tiles_x, tile), bg, final_t, last, width, height = ctx.saved
        n_chunks = max(1, nb.get_num_threads())
        grads = np.zeros((n_chunks, packed.shape[0], 9), np.float64)
        g_rgb_np = np.ascontiguousarray(g_rgb.detach().numpy(), np.float64) if g_rgb is not None \
            else np.zeros((height, width, 3))
        g_a_np = np.ascontiguousarray(g_alpha.detach().numpy(), np.float64) if g_alpha is not None \
            else np.zeros((height, width))
        backward_kernel(packed, box, offsets, lst, width, height, tile, tiles_x, bg, final_t, last, g_rgb_np,
                        g_a_np, n_chunks, grads)
        g = torch.from_numpy(grads.sum(axis=0)).to(ctx.dtype)
        return g[:, 0:2], g[:, 2:5], g[:, 6:9], g[:, 5], None, None, None, None, None, None


@dataclass
class TorchRenderOutput:
    """Differentiable render: ``rgb`` H×W×3 and ``alpha`` H×W tensors (not clipped), ``means2d`` M×2
    pixel centres of the visible Gaussians (gradient retained, for densification), ``index`` M model
    indices of those Gaussians in depth order, ``radius_px`` M 3-sigma radii."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    means2d: torch.Tensor
    index: np.ndarray
    radius_px: np.ndarray


def render_torch(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
                 opacity_logits: torch.Tensor, sh: torch.Tensor, camera: Camera, background=(0.0, 0.0, 0.0),
                 *, sh_degree: int = 0, near_m: float = NEAR_M,
                 world_to_camera: torch.Tensor | None = None) -> TorchRenderOutput:
    """Differentiable render for training (parameters as torch tensors, same layout as the model).

    Culling, depth sort and tile binning are non-differentiable (numba); projection, activations
    and SH are torch autograd; compositing is :class:`RasterizeFunction` (numba forward and exact
    numba backward). Same image as :func:`render` up to float rounding.

    ``world_to_camera`` (4×4 tensor, OpenCV axes), when given, replaces ``camera.world_to_camera`` (the
    intrinsics stay the camera's): the pose as a function of learned parameters (pose refinement,
    :mod:`~gsrmr_splat.camera_opt`). Gradients then reach it through the projected means, the
    conics and depths (the projection Jacobian) and the SH view directions (the camera centre −Rᵀt); the
    culling, sort and binning pass uses its detached value.
    """
    bg = _check_background(background)
    width, height = camera.width, camera.height
    k = camera.intrinsics
    intr = (k.fx, k.fy, k.cx, k.cy)
    pose_np = camera.world_to_camera if world_to_camera is None else \
        world_to_camera.detach().to(torch.float64).numpy()
    with torch.no_grad():
        arrays = [t.detach().float().numpy() for t in (means, quats, log_scales, opacity_logits)]
        geom, box = project_numpy(*arrays, pose_np, intr, width, height, near_m)
    visible = np.nonzero((box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3]))[0]
    order = visible[depth_order(geom[visible, 6])]
    idx = torch.from_numpy(order)
    m = means[idx]
    if world_to_camera is None:
        w2c = torch.as_tensor(camera.world_to_camera, dtype=means.dtype)
    else:
        w2c = world_to_camera.to(means.dtype)
    means2d, conic, _, z = project_torch(m, quats[idx], log_scales[idx], w2c, intr, width, height)
    if means2d.requires_grad:
        means2d.retain_grad()
    opac = torch.sigmoid(opacity_logits[idx])
    degree = min(sh_degree, round(sh.shape[1] ** 0.5) - 1)
    if degree == 0:
        colors = torch.clamp_min(sh[idx, 0, :] * C0 + 0.5, 0.0)
    else:
        if world_to_camera is None:
            center = torch.as_tensor(camera.center_world, dtype=means.dtype)
        else:
            center = (-world_to_camera[:3, :3].T @ world_to_camera[:3, 3]).to(means.dtype)
        dirs = m - center
        dirs = dirs / dirs.norm(dim=1, keepdim=True).clamp_min(1e-12)
        colors = eval_sh_torch(sh[idx], dirs, degree)
    radius = torch.from_numpy(geom[order, 7].astype(np.float64))
    rgb, alpha = RasterizeFunction.apply(means2d, conic, colors, opac, z.detach(), radius, box[order], bg,
                                         width, height)
    return TorchRenderOutput(rgb, alpha, means2d, order, geom[order, 7])
