"""The fused training engine (``TrainConfig.engine = "fused"``, :class:`FusedEngine`): one training step — projection,
SH, rasterizer, the loss 0.8·L1 + 0.2·(1 − SSIM), their backward passes and Adam — in numba kernels, without autograd.

The maths is the torch engine's; only rounding differs (projection float64, rasterizer and SSIM float32, every sum in a
fixed order, so no result depends on the numba thread count). Parameters, Adam moments and density statistics stay the
trainer's torch tensors (the kernels work on their numpy views); the pose correction's gradient is closed-form numpy
(:func:`pose_gradient`). Design and timings: docs/splatting.md, "Training speed: the fused engine".
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import time

import numba
import numpy as np
import torch

from gsrmr_common.camera import Camera
from gsrmr_splat.fused_kernels import (
    GEOM_WIDTH,
    N_REDUCE,
    RASTER_GRADS,
    adam_kernel,
    gather_kernel,
    project_backward_kernel,
    project_forward_kernel,
)
from gsrmr_splat.fused_loss import FusedLoss
from gsrmr_splat.fused_raster import TILE, backward_kernel32, bin_entries_kernel, forward_kernel32
from gsrmr_splat.optim import TrainState
from gsrmr_splat.project import fov_limits
from gsrmr_splat.rasterize import PACK_WIDTH, depth_order

#: a step this small (pixels and Gaussians) runs on one numba thread (FusedEngine.step)
SMALL_STEP_PIXELS = 128 * 96
SMALL_STEP_GAUSSIANS = 20_000
LOSS_LAMBDA = 0.2  # weight of the (1 − SSIM) term, train_loss's λ
ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-15
_SMALL_ANGLE_RAD2 = 1e-8  # camera_opt's: below this θ² the series of Rodrigues' coefficients


@dataclass
class FusedStepResult:
    """What one fused step returns: the photometric loss, the MSE of the clipped render (exposure applied), the
    gradients of the frame's pose and exposure rows (including their L2 penalties; None when off), the rendered
    Gaussians' indices in depth order and the parameters' gradients (per name, shaped as the parameter; the
    engine's buffers: valid until its next step)."""

    loss: float
    mse: float
    pose_grad: np.ndarray | None
    exposure_grad: np.ndarray | None
    order: np.ndarray
    grads: dict[str, np.ndarray]


def _hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """:func:`~gsrmr_splat.camera_opt.so3_exp` in numpy (Rodrigues; the same small-angle series)."""
    theta2 = float(omega @ omega)
    if theta2 < _SMALL_ANGLE_RAD2:
        a, b = 1.0 - theta2 / 6.0, 0.5 - theta2 / 24.0
    else:
        theta = math.sqrt(theta2)
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta2
    k = _hat(omega)
    return np.eye(3) + a * k + b * (k @ k)


def so3_right_jacobian(v: np.ndarray) -> np.ndarray:
    """J_r(v) = I − (1 − cos θ)/θ²·[v]× + (θ − sin θ)/θ³·[v]×², with ∂Exp(v)/∂v_k = Exp(v)·[J_r(v)·e_k]×."""
    theta2 = float(v @ v)
    if theta2 < _SMALL_ANGLE_RAD2:
        b, c = 0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0
    else:
        theta = math.sqrt(theta2)
        b, c = (1.0 - math.cos(theta)) / theta2, (theta - math.sin(theta)) / (theta2 * theta)
    k = _hat(v)
    return np.eye(3) - b * k + c * (k @ k)


def corrected_world_to_camera(world_to_camera: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """:func:`~gsrmr_splat.camera_opt.corrected_world_to_camera` in numpy float64: camera→world rotation
    Exp(ω)·Rᵀ, optical centre c + τ."""
    w2c = np.asarray(world_to_camera, np.float64)
    d = np.asarray(delta, np.float64)
    rot = w2c[:3, :3] @ so3_exp(d[:3]).T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ (-w2c[:3, :3].T @ w2c[:3, 3] + d[3:])
    return out


def pose_gradient(world_to_camera: np.ndarray, delta: np.ndarray, g_rot: np.ndarray, g_trans: np.ndarray,
                  g_center: np.ndarray) -> np.ndarray:
    """dL/dδ from dL/dR' (``g_rot``), dL/dt' (``g_trans``) and dL/dc' (``g_center``, the camera centre the SH
    directions start from) of the corrected pose [R' | t'] = :func:`corrected_world_to_camera`: with c' = c + τ,
    t' = −R'c' and R' = R·Exp(−ω), dL/dτ = g_c − R'ᵀ g_t and, with G = g_R − g_t c'ᵀ and A = Exp(−ω)ᵀ Rᵀ G,
    dL/dω = −J_r(−ω)ᵀ (A₃₂ − A₂₃, A₁₃ − A₃₁, A₂₁ − A₁₂)."""
    w2c = np.asarray(world_to_camera, np.float64)
    d = np.asarray(delta, np.float64)
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    center = -rot.T @ trans + d[3:]
    e = so3_exp(-d[:3])
    g = g_rot - np.outer(g_trans, center)
    a = e.T @ rot.T @ g
    w = np.array([a[2, 1] - a[1, 2], a[0, 2] - a[2, 0], a[1, 0] - a[0, 1]])
    return np.concatenate([-so3_right_jacobian(-d[:3]).T @ w, g_center - (rot @ e).T @ g_trans])


def _flat(t: torch.Tensor) -> np.ndarray:
    """A contiguous tensor as a flat numpy view (shares memory with the tensor)."""
    return t.detach().numpy().reshape(-1)


def _rows(t: torch.Tensor) -> np.ndarray:
    """A per-Gaussian tensor as an N×D numpy view (shares memory with the tensor)."""
    a = t.detach().numpy()
    return a.reshape(a.shape[0], -1)


class ThreadChooser:
    """One thread or all of them, by measurement: of every :attr:`period` steps, the first :attr:`probe` run on
    one thread and the next :attr:`probe` on all; the rest on whichever had the lower median step time. The
    choice follows the machine's load within a period and never changes a result (the fused step does not
    depend on the thread count)."""

    def __init__(self, period: int = 300, probe: int = 8) -> None:
        self.period, self.probe = period, probe
        self._n = 0
        self._times: dict[int, list[float]] = {}
        self._best: int | None = None

    def threads(self, most: int) -> int:
        """The thread count of the next step (``most``: numba's current count)."""
        if most <= 1:
            return 1
        phase = self._n % self.period
        if phase == 0:
            self._times = {}
        if phase < self.probe:
            return 1
        if phase < 2 * self.probe:
            return most
        if self._best is None or phase == 2 * self.probe:
            one, many = self._times.get(1, []), [t for n, ts in self._times.items() if n > 1 for t in ts]
            self._best = 1 if one and many and float(np.median(one)) < float(np.median(many)) else most
        return min(self._best, most)

    def record(self, threads: int, seconds: float) -> None:
        """The wall time of the step just run on ``threads``."""
        if self._n % self.period < 2 * self.probe:
            self._times.setdefault(threads, []).append(seconds)
        self._n += 1

    @property
    def choice(self) -> int | None:
        """The thread count chosen at the last probe (None before the first)."""
        return self._best


class FusedEngine:
    """Runs :meth:`step` on a :class:`~gsrmr_splat.optim.TrainState`; holds the rasterizer's
    gradient buffer between steps."""

    def __init__(self, adaptive_threads: bool = True) -> None:
        #: choose between one thread and numba's count by timing (:meth:`step`); off: always numba's count
        self.adaptive_threads = adaptive_threads
        self._chooser = ThreadChooser()
        self._loss = FusedLoss(LOSS_LAMBDA)
        self._entry_grads = np.zeros((0, RASTER_GRADS), np.float32)
        self._geom = np.zeros((0, GEOM_WIDTH))
        self._box = np.zeros((0, 4), np.int32)
        self._grads: dict[str, np.ndarray] = {}
        self._dirty = False
        #: when a dict, wall seconds per phase are added to it (a profile: bench/perf/train.py --profile)
        self.timings: dict[str, float] | None = None
        self.clock = time.perf_counter  # the clock of the profile (time.thread_time: CPU of a 1-thread run)
        self._t = 0.0

    def _phase(self, name: str | None) -> None:
        """Close the running phase (adding its wall time to :attr:`timings` under ``name``), start the next."""
        if self.timings is None:
            return
        now = self.clock()
        if name is not None:
            self.timings[name] = self.timings.get(name, 0.0) + now - self._t
        self._t = now

    def _entry_buffer(self, rows: int) -> np.ndarray:
        """The rasterizer backward's per-entry gradient rows (float32, reused; grown by a quarter when short)."""
        buf = self._entry_grads
        if buf.shape[0] < rows:
            buf = np.empty((max(rows, int(1.25 * buf.shape[0])), RASTER_GRADS), np.float32)
            self._entry_grads = buf
        return buf

    def _grad_arrays(self, params: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        """Dense gradient buffers shaped as the parameters, zero (Adam zeroes them again after reading)."""
        g = self._grads
        if any(name not in g or g[name].shape != tuple(v.shape) or g[name].dtype != v.detach().numpy().dtype
               for name, v in params.items()):
            g = {name: np.zeros(tuple(v.shape), v.detach().numpy().dtype) for name, v in params.items()}
            self._grads = g
        return g

    def step(self, state: TrainState, camera: Camera, target: np.ndarray, it: int, lr, **options) -> FusedStepResult:
        """One optimisation step of ``state`` on the view ``camera`` / ``target`` (H×W×3 float32) at iteration
        ``it`` (Adam's step count; ``lr(name, it)`` the learning rate of each group): :meth:`gradients`, then Adam
        over every row of every parameter (rows no Gaussian gradient reached: gradient zero, as torch's). Updates
        the parameters, Adam moments and density statistics in place; the correction rows are left to the caller
        (their gradients are returned).

        Threads: numba's current count is the most a step uses. A small step (at most :data:`SMALL_STEP_PIXELS`
        pixels and :data:`SMALL_STEP_GAUSSIANS` Gaussians) runs on one: its kernels are too short to gain from
        more. Otherwise, with :attr:`adaptive_threads`, :class:`ThreadChooser` times steps on one thread and on
        all of them now and then and runs the faster: on a machine whose cores are busy with other work, each of a
        step's parallel regions waits for its threads to be scheduled, and one thread is then several times faster.
        The result does not depend on the thread count."""
        threads = numba.get_num_threads()
        small = camera.width * camera.height <= SMALL_STEP_PIXELS and state.params["means"].shape[0] <= \
            SMALL_STEP_GAUSSIANS
        use = 1 if small else (self._chooser.threads(threads) if self.adaptive_threads else threads)
        if use != threads:
            numba.set_num_threads(use)
        try:
            t0 = time.perf_counter()
            res = self._step(state, camera, target, it, lr, **options)
            if self.adaptive_threads and not small:
                self._chooser.record(use, time.perf_counter() - t0)
            return res
        finally:
            if use != threads:
                numba.set_num_threads(threads)

    def _step(self, state: TrainState, camera: Camera, target: np.ndarray, it: int, lr, **options) -> FusedStepResult:
        res = self.gradients(state, camera, target, it, **options)
        self._phase(None)
        beta1, beta2 = ADAM_BETAS
        bc1, bc2 = 1 - beta1**it, 1 - beta2**it
        names = [name for name, v in state.params.items() if v.numel()]
        adam_kernel(tuple(_flat(state.params[n]) for n in names), tuple(_flat(state.exp_avg[n]) for n in names),
                    tuple(_flat(state.exp_avg_sq[n]) for n in names), tuple(res.grads[n].reshape(-1) for n in names),
                    np.array([lr(n, it) / bc1 for n in names]), bc2, beta1, beta2, ADAM_EPS)
        self._dirty = False
        self._phase("adam")
        return res

    def gradients(self, state: TrainState, camera: Camera, target: np.ndarray, it: int, *,
                  background=(0.0, 0.0, 0.0), near_m: float, sh_degree: int, pose: np.ndarray | None = None,
                  pose_reg: float = 0.0, exposure: np.ndarray | None = None,
                  exposure_reg: float = 0.0) -> FusedStepResult:
        """Render ``state``'s parameters from ``camera``, the loss against ``target`` and its gradients: of every
        parameter in ``grads`` and, with ``pose`` (the frame's correction δ = (ω rad, τ m): the camera's pose
        corrected by it, :func:`corrected_world_to_camera`) or ``exposure`` (gain and bias rows on the render
        before the loss), of those rows (L2 penalties ``pose_reg`` / ``exposure_reg`` included). Adds the view to
        the density statistics of ``state`` (last seen at ``it``)."""
        self._phase(None)
        p = state.params
        means, quats = _rows(p["means"]), _rows(p["quats"])
        log_scales, logits = _rows(p["log_scales"]), p["opacity_logits"].detach().numpy()
        sh_dc, sh_rest = p["sh_dc"].detach().numpy(), p["sh_rest"].detach().numpy()
        n = means.shape[0]
        width, height = camera.width, camera.height
        k = camera.intrinsics
        intr = np.array([k.fx, k.fy, k.cx, k.cy], np.float64)
        lims = np.asarray(fov_limits(k.fx, k.fy, k.cx, k.cy, width, height), np.float64)
        if pose is None:
            w2c = np.ascontiguousarray(camera.world_to_camera, np.float64)
            center = np.ascontiguousarray(camera.center_world, np.float64)  # one kernel specialisation for both
        else:
            w2c = corrected_world_to_camera(camera.world_to_camera, pose)
            center = np.ascontiguousarray(-w2c[:3, :3].T @ w2c[:3, 3])
        degree = min(sh_degree, round((1 + sh_rest.shape[1]) ** 0.5) - 1)
        # projection, culling, depth order (the torch path's project_numpy + depth_order)
        if self._geom.shape[0] < n:  # reused: a fresh array of this size costs its page faults every step
            self._geom = np.empty((int(1.25 * n), GEOM_WIDTH), np.float64)
            self._box = np.empty((int(1.25 * n), 4), np.int32)
        geom, box = self._geom[:n], self._box[:n]
        if n:
            project_forward_kernel(means, quats, log_scales, logits, w2c, intr, lims, int(width), int(height),
                                   float(near_m), geom, box)
        self._phase("project")
        visible = np.flatnonzero((box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3]))
        perm = depth_order(geom[visible, 6])
        order = visible[perm]
        m_rows = order.shape[0]
        self._phase("sort")
        packed = np.empty((m_rows, PACK_WIDTH), np.float32)
        pbox = np.empty((m_rows, 4), np.int64)
        gather_kernel(geom, box, order, means, sh_dc, sh_rest, center, degree, packed, pbox)
        self._phase("gather+sh")
        # rasterizer forward (float32, vectorised: fused_raster)
        tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
        offsets, lst, entry_start, entry_of = bin_entries_kernel(pbox, tiles_x, tiles_y, perm)
        self._phase("bin")
        bg = np.asarray(background, np.float64)
        rgb = np.empty((height, width, 3), np.float32)
        final_t = np.empty((height, width), np.float32)
        last = np.empty((height, width), np.int64)
        forward_kernel32(packed, pbox, offsets, lst, width, height, tiles_x, bg, rgb, final_t, last)
        self._phase("raster forward")
        # exposure, loss and its gradient
        shown = rgb
        if exposure is not None:
            e = np.asarray(exposure, np.float64)
            gain = np.exp(e[:3])
            shown = (rgb * gain + e[3:]).astype(np.float32)
        g_shown = np.empty((height, width, 3), np.float32)
        loss, _, mse = self._loss(shown, target, g_shown)
        exposure_grad = None
        g_rgb = g_shown
        if exposure is not None:
            g64 = g_shown.astype(np.float64)
            g_gain = (g64 * rgb).sum(axis=(0, 1)) * gain
            g_bias = g64.sum(axis=(0, 1))
            exposure_grad = np.concatenate([g_gain, g_bias]) + 2.0 * exposure_reg * e
            g_rgb = g_shown * gain
        self._phase("loss")
        # rasterizer backward
        entry_grads = self._entry_buffer(lst.shape[0])
        backward_kernel32(packed, pbox, offsets, lst, width, height, tiles_x, bg, final_t, last, g_rgb, entry_of,
                          entry_grads)
        self._phase("raster backward")
        # chain rule to the parameters, density statistics
        g = self._grad_arrays(p)
        if self._dirty:  # gradients() ran without step()'s Adam, which zeroes what it reads
            for arr in g.values():
                arr.fill(0.0)
        self._dirty = True
        pose_grads = np.zeros((N_REDUCE, 15))
        want_pose = pose is not None
        rank = np.empty_like(perm)
        rank[perm] = np.arange(m_rows)
        project_backward_kernel(visible, rank, entry_grads, entry_start, geom, means, quats, log_scales,
                                logits, sh_dc, sh_rest, w2c, intr, lims, center, degree, g["means"], g["quats"],
                                g["log_scales"],
                                g["opacity_logits"], g["sh_dc"], g["sh_rest"], pose_grads, want_pose,
                                0.5 * width, 0.5 * height, packed[:, 10], state.grad_accum.numpy(),
                                state.grad_count.numpy(), state.max_radius.numpy(), state.last_seen.numpy(), it)
        self._phase("project backward")
        pose_grad = None
        if want_pose:
            pg = pose_grads.sum(axis=0)
            pose_grad = pose_gradient(camera.world_to_camera, pose, pg[:9].reshape(3, 3), pg[9:12], pg[12:15]) \
                + 2.0 * pose_reg * np.asarray(pose, np.float64)
        self._phase("pose")
        return FusedStepResult(float(loss), float(mse), pose_grad, exposure_grad, order, g)

