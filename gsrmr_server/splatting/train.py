"""Trainer: nerfstudio dataset → Gaussian model (.ply), the 3DGS recipe on the CPU.

* Loss 0.8·L1 + 0.2·(1 − SSIM), SSIM with the 11×11, σ = 1.5 Gaussian window of
  :mod:`gsrmr_common.metrics` (zero padding, C1 = 0.01², C2 = 0.03²) in torch (:func:`ssim_torch`).
* Adam (eps 1e-15) with the 3DGS learning rates; the position rate decays exponentially from
  1.6e-4·extent to 1.6e-6·extent, extent = 1.1 × the largest camera distance from the cameras' mean.
* Adaptive density control (3DGS): every ``densify_interval`` iterations between ``densify_from`` and
  ``densify_until``, Gaussians whose mean NDC-space positional gradient exceeds ``grad_threshold``
  are cloned (small: max scale ≤ 0.01·extent) or split in two (large), within ``budget`` Gaussians
  (highest gradients first); Gaussians with opacity < ``prune_opacity`` are pruned, and after the
  first opacity reset also those larger than 0.1·extent in the world or 20 px on screen. Opacities
  are reset to ≤ 0.01 every ``opacity_reset_interval``. Gaussians that no training view has seen
  for two passes over the views are pruned as unused, and a final pass removes every Gaussian whose
  largest blending weight over all training views is below 1/255 (it cannot change any pixel).
* The SH degree is raised by one every ``sh_increase_interval`` up to ``sh_degree``.
* Initialisation: back-projected depth pixels when the dataset has depth, else random points in the
  cameras' bounding box grown by the extent; scales from the 3-nearest-neighbour distance.
* Checkpoints (torch.save) hold parameters, Adam moments, statistics, iteration and RNG state.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
import math
from pathlib import Path
import time
from typing import NamedTuple

import cv2
import numba as nb
import numpy as np
from scipy.spatial import cKDTree
import torch
from tqdm import tqdm

from gsrmr_common.camera import Camera
from gsrmr_common.metrics import SSIM_C1, SSIM_C2, gaussian_window_1d, psnr
from gsrmr_common.nerfstudio import DatasetFrame, read_dataset
from gsrmr_server.splatting.diffrender import render_torch
from gsrmr_server.splatting.model import GaussianModel
from gsrmr_server.splatting.project import NEAR_M, project_numpy
from gsrmr_server.splatting.rasterize import TILE, depth_order
from gsrmr_server.splatting.render import render

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


def ssim_torch(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two H×W×C images, identical to :func:`gsrmr_common.metrics.ssim` (differentiable)."""
    g = torch.as_tensor(gaussian_window_1d(), dtype=a.dtype)
    win = (g[:, None] * g[None, :])[None, None]
    c = a.shape[2]
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    w = win.expand(c, 1, -1, -1)
    pad = win.shape[-1] // 2

    def blur(t: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.conv2d(t, w, padding=pad, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x * mu_x
    syy = blur(y * y) - mu_y * mu_y
    sxy = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
    return (num / den).mean()


def train_loss(pred: torch.Tensor, target: torch.Tensor, lam: float = 0.2) -> torch.Tensor:
    """(1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2 (the 3DGS loss and the paper's MR loss)."""
    return (1.0 - lam) * (pred - target).abs().mean() + lam * (1.0 - ssim_torch(pred, target))


@dataclass
class TrainConfig:
    """Trainer settings (3DGS defaults where they exist; iteration counts shortened for the CPU)."""

    iterations: int = 6000
    budget: int = 200_000
    resolution: int | None = None  # train at this image width (keeps aspect); None = as stored
    sh_degree: int = 1
    sh_increase_interval: int = 1000
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 0.05
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    densify_from: int = 300
    densify_until: int = 4000
    densify_interval: int = 100
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    opacity_reset_interval: int = 3000
    max_screen_px: float = 20.0
    init_points: int = 30_000
    seed: int = 0
    checkpoint_every: int = 1000
    near_m: float = NEAR_M
    final_prune: bool = True
    torch_threads: int | None = 1  # torch.set_num_threads for the process (None = leave as is)

    def to_dict(self) -> dict:
        """JSON-friendly dict."""
        return asdict(self)


def _plain(value):
    """A numpy scalar as the Python number it holds (checkpoints hold no numpy objects)."""
    return value.item() if isinstance(value, np.generic) else value


class HistoryRow(NamedTuple):
    """One progress record of :meth:`Trainer.train`."""

    iteration: int
    wall_s: float
    cpu_s: float
    loss: float
    test_psnr_db: float
    num_gaussians: int


@dataclass
class TrainState:
    """Everything a checkpoint holds besides the config."""

    params: dict[str, torch.Tensor]
    exp_avg: dict[str, torch.Tensor]
    exp_avg_sq: dict[str, torch.Tensor]
    step: int = 0
    grad_accum: torch.Tensor = field(default_factory=lambda: torch.zeros(0))
    grad_count: torch.Tensor = field(default_factory=lambda: torch.zeros(0))
    max_radius: torch.Tensor = field(default_factory=lambda: torch.zeros(0))
    last_seen: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    sh_active: int = 0
    history: list = field(default_factory=list)


def scene_extent(cameras: list[Camera]) -> float:
    """3DGS ``getNerfppNorm`` radius: 1.1 × the largest camera distance from the cameras' mean (≥ 1e-3 m)."""
    centers = np.array([c.center_world for c in cameras])
    return float(max(1.1 * np.linalg.norm(centers - centers.mean(0), axis=1).max(), 1e-3))


def _resize_frames(frames: list[DatasetFrame], width: int | None) -> list[DatasetFrame]:
    if width is None:
        return frames
    out = []
    for f in frames:
        k = f.camera.intrinsics
        if k.width == width:
            out.append(f)
            continue
        height = max(1, round(k.height * width / k.width))
        cam = Camera(k.scaled(width, height), f.camera.world_to_camera)
        img = cv2.resize(f.image, (width, height), interpolation=cv2.INTER_AREA)
        depth = None if f.depth_m is None else cv2.resize(f.depth_m, (width, height),
                                                           interpolation=cv2.INTER_NEAREST)
        out.append(DatasetFrame(cam, img, depth, f.pose, f.file_path))
    return out


def init_points(frames: list[DatasetFrame], n_points: int, extent: float,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(N×3 points [m], N×3 colours in [0, 1]) from depth maps if present, else random in a box."""
    with_depth = [f for f in frames if f.depth_m is not None]
    if with_depth:
        pts, cols = [], []
        per = max(1, n_points // len(with_depth))
        for f in with_depth:
            valid = np.argwhere(np.isfinite(f.depth_m) & (f.depth_m > 0))
            if valid.size == 0:
                continue
            pick = valid[rng.choice(len(valid), size=min(per, len(valid)), replace=False)]
            z = f.depth_m[pick[:, 0], pick[:, 1]].astype(np.float64)
            k = f.camera.intrinsics
            x = (pick[:, 1] + 0.5 - k.cx) / k.fx * z
            y = (pick[:, 0] + 0.5 - k.cy) / k.fy * z
            c2w = f.camera.camera_to_world
            pts.append(np.stack([x, y, z], 1) @ c2w[:3, :3].T + c2w[:3, 3])
            cols.append(f.image[pick[:, 0], pick[:, 1]])
        if pts:
            return np.concatenate(pts), np.concatenate(cols).astype(np.float64)
    centers = np.array([f.camera.center_world for f in frames])
    lo, hi = centers.min(0) - extent, centers.max(0) + extent
    return rng.uniform(lo, hi, size=(n_points, 3)), rng.uniform(0.2, 0.8, size=(n_points, 3))


def knn_scales(points: np.ndarray) -> np.ndarray:
    """sqrt(mean squared distance to the 3 nearest neighbours), as 3DGS's distCUDA2 initialisation."""
    if len(points) < 4:
        return np.full(len(points), 0.01)
    d, _ = cKDTree(points).query(points, k=4)
    return np.sqrt(np.maximum(np.mean(d[:, 1:] ** 2, axis=1), 1e-14))


@nb.njit(parallel=True, cache=True)
def _max_weight_kernel(packed, box, offsets, lst, width, height, tile, tiles_x, n_chunks, out):
    """Per packed row, the largest blending weight T·α it gets at any pixel (same rules as forward)."""
    n_tiles = offsets.shape[0] - 1
    for ch in nb.prange(n_chunks):
        buf = out[ch]
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
                        buf[k] = max(buf[k], alpha * trans[p])
                        trans[p] = t_next


def max_blend_weight(model: GaussianModel, cameras: list[Camera], near_m: float = NEAR_M) -> np.ndarray:
    """For each Gaussian, its largest blending weight T·α over every pixel of every camera."""
    from gsrmr_server.splatting.rasterize import bin_kernel, pack

    best = np.zeros(model.num_gaussians)
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
        _max_weight_kernel(packed, b, offsets, lst, k.width, k.height, TILE, tiles_x, n_chunks, out)
        np.maximum.at(best, order, out.max(axis=0))
    return best


class Trainer:
    """Optimises a Gaussian model on a list of training frames (see the module docstring)."""

    def __init__(self, frames: list[DatasetFrame], config: TrainConfig | None = None,
                 test_frames: list[DatasetFrame] | None = None) -> None:
        self.config = config or TrainConfig()
        cfg = self.config
        if cfg.torch_threads:
            # The torch ops here are small; a second OpenMP pool next to numba's costs up to 5× per step.
            torch.set_num_threads(cfg.torch_threads)
        if not frames:
            raise ValueError("Trainer: no training frames")
        self.frames = _resize_frames(frames, cfg.resolution)
        self.test_frames = _resize_frames(test_frames or [], cfg.resolution)
        self.targets = [torch.from_numpy(np.ascontiguousarray(f.image, np.float32)) for f in self.frames]
        self.extent = scene_extent([f.camera for f in self.frames])
        self.rng = np.random.default_rng(cfg.seed)
        self.torch_gen = torch.Generator().manual_seed(cfg.seed)
        self.state = self._initial_state()
        self._perm: list[int] = []

    @classmethod
    def from_dataset(cls, path: str | Path, config: TrainConfig | None = None,
                     holdout_every: int = 0) -> Trainer:
        """Read a nerfstudio dataset; every ``holdout_every``-th frame (if > 0) becomes a test view."""
        frames = read_dataset(path)
        if holdout_every > 0:
            test = [f for i, f in enumerate(frames) if i % holdout_every == holdout_every - 1]
            train = [f for i, f in enumerate(frames) if i % holdout_every != holdout_every - 1]
            return cls(train, config, test)
        return cls(frames, config)

    # ------------------------------------------------------------------ state
    def _initial_state(self) -> TrainState:
        cfg = self.config
        pts, cols = init_points(self.frames, cfg.init_points, self.extent, self.rng)
        scales = np.clip(knn_scales(pts), 1e-4, 0.1 * self.extent)
        model = GaussianModel.from_points(pts, np.clip(cols, 0, 1), scales_m=scales, opacities=0.1,
                                          degree=cfg.sh_degree)
        return self._state_from_model(model)

    def _state_from_model(self, model: GaussianModel) -> TrainState:
        n = model.num_gaussians
        params = {"means": torch.from_numpy(model.means.copy()), "quats": torch.from_numpy(model.quats.copy()),
                  "log_scales": torch.from_numpy(model.log_scales.copy()),
                  "opacity_logits": torch.from_numpy(model.opacity_logits.copy()),
                  "sh_dc": torch.from_numpy(model.sh[:, :1].copy()),
                  "sh_rest": torch.from_numpy(model.sh[:, 1:].copy())}
        return TrainState(params, {k: torch.zeros_like(v) for k, v in params.items()},
                          {k: torch.zeros_like(v) for k, v in params.items()}, 0, torch.zeros(n), torch.zeros(n),
                          torch.zeros(n), torch.zeros(n, dtype=torch.long), 0, [])

    @property
    def num_gaussians(self) -> int:
        """Current Gaussian count."""
        return int(self.state.params["means"].shape[0])

    def model(self) -> GaussianModel:
        """The current model as a :class:`GaussianModel` (SH of the configured degree)."""
        p = self.state.params
        sh = torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
        return GaussianModel(p["means"].numpy(), p["quats"].numpy(), p["log_scales"].numpy(),
                             p["opacity_logits"].numpy(), sh.numpy())

    def lr(self, name: str, step: int) -> float:
        """Learning rate of a parameter group at ``step`` (position: exponential decay × extent)."""
        cfg = self.config
        if name == "means":
            t = min(max(step / max(cfg.iterations, 1), 0.0), 1.0)
            return math.exp((1 - t) * math.log(cfg.lr_means) + t * math.log(cfg.lr_means_final)) * self.extent
        return {"quats": cfg.lr_quats, "log_scales": cfg.lr_scales, "opacity_logits": cfg.lr_opacity,
                "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_rest}[name]

    # ------------------------------------------------------------------ one step
    def _next_view(self) -> int:
        if not self._perm:
            self._perm = list(self.rng.permutation(len(self.frames)))
        return int(self._perm.pop())

    def step(self) -> tuple[float, float]:
        """One optimisation step on one training view; returns (loss, PSNR dB of that view)."""
        cfg, st = self.config, self.state
        it = st.step + 1
        view = self._next_view()
        frame, target = self.frames[view], self.targets[view]
        p = st.params
        for v in p.values():
            v.requires_grad_(True)
            v.grad = None
        sh = torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
        out = render_torch(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], sh, frame.camera,
                           cfg.background, sh_degree=st.sh_active, near_m=cfg.near_m)
        loss = train_loss(out.rgb, target)
        loss.backward()
        with torch.no_grad():
            idx = torch.from_numpy(out.index)
            if out.means2d.grad is not None and len(idx):
                k = frame.camera.intrinsics
                g = out.means2d.grad * torch.tensor([0.5 * k.width, 0.5 * k.height])
                st.grad_accum.index_add_(0, idx, g.norm(dim=1))
                st.grad_count.index_add_(0, idx, torch.ones(len(idx)))
                st.max_radius[idx] = torch.maximum(st.max_radius[idx],
                                                   torch.from_numpy(out.radius_px.astype(np.float32)))
            st.last_seen[idx] = it
            self._adam(it)
            mse = float(((out.rgb.clamp(0, 1) - target) ** 2).mean())
        st.step = it
        if it % cfg.sh_increase_interval == 0 and st.sh_active < cfg.sh_degree:
            st.sh_active += 1
        if cfg.densify_from <= it <= cfg.densify_until and it % cfg.densify_interval == 0:
            self.densify_and_prune(it)
        if it % cfg.opacity_reset_interval == 0 and it <= cfg.densify_until:
            self.reset_opacity()
        return float(loss.detach()), -10.0 * math.log10(max(mse, 1e-10))

    def _adam(self, it: int, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-15) -> None:
        st = self.state
        for name, v in st.params.items():
            if v.grad is None:
                continue
            g = v.grad
            m, s = st.exp_avg[name], st.exp_avg_sq[name]
            m.mul_(beta1).add_(g, alpha=1 - beta1)
            s.mul_(beta2).addcmul_(g, g, value=1 - beta2)
            bc1, bc2 = 1 - beta1**it, 1 - beta2**it
            v.requires_grad_(False)
            v.addcdiv_(m, (s / bc2).sqrt_().add_(eps), value=-self.lr(name, it) / bc1)
            v.grad = None

    # ------------------------------------------------------------------ density control
    def _apply(self, keep: torch.Tensor, new: dict[str, torch.Tensor] | None = None) -> None:
        """Keep rows ``keep`` of every per-Gaussian tensor and append ``new`` rows (zero optimiser state)."""
        st = self.state
        for name in PARAM_NAMES:
            parts = [st.params[name][keep].detach()]
            m_parts, s_parts = [st.exp_avg[name][keep]], [st.exp_avg_sq[name][keep]]
            if new is not None:
                parts.append(new[name])
                m_parts.append(torch.zeros_like(new[name]))
                s_parts.append(torch.zeros_like(new[name]))
            st.params[name] = torch.cat(parts).contiguous()
            st.exp_avg[name] = torch.cat(m_parts).contiguous()
            st.exp_avg_sq[name] = torch.cat(s_parts).contiguous()
        n_new = 0 if new is None else new["means"].shape[0]
        st.grad_accum = torch.cat([st.grad_accum[keep], torch.zeros(n_new)])
        st.grad_count = torch.cat([st.grad_count[keep], torch.zeros(n_new)])
        st.max_radius = torch.cat([st.max_radius[keep], torch.zeros(n_new)])
        st.last_seen = torch.cat([st.last_seen[keep], torch.full((n_new,), st.step, dtype=torch.long)])

    def densify_and_prune(self, it: int) -> None:
        """Clone, split and prune (3DGS adaptive density control) under the Gaussian budget."""
        cfg, st = self.config, self.state
        p = {k: v.detach() for k, v in st.params.items()}
        n = p["means"].shape[0]
        grads = st.grad_accum / st.grad_count.clamp_min(1)
        scale_max = p["log_scales"].exp().max(dim=1).values
        candidates = grads >= cfg.grad_threshold
        room = max(cfg.budget - n, 0)
        is_split = candidates & (scale_max > cfg.percent_dense * self.extent)
        # a split adds one net Gaussian, a clone adds one: rank by gradient and keep what fits
        cand_idx = torch.nonzero(candidates).flatten()
        if len(cand_idx) > room:
            cand_idx = cand_idx[torch.argsort(grads[cand_idx], descending=True)[:room]]
        chosen = torch.zeros(n, dtype=torch.bool)
        chosen[cand_idx] = True
        clone = chosen & ~is_split
        split = chosen & is_split
        new: dict[str, list[torch.Tensor]] = {k: [] for k in PARAM_NAMES}
        for k in PARAM_NAMES:
            new[k].append(p[k][clone])
        if split.any():
            sidx = torch.nonzero(split).flatten()
            std = p["log_scales"][sidx].exp()
            from gsrmr_server.splatting.diffrender import quat_to_rotmat_torch

            rot = quat_to_rotmat_torch(p["quats"][sidx])
            for _ in range(2):
                sample = torch.randn(std.shape, generator=self.torch_gen, dtype=std.dtype) * std
                new["means"].append(p["means"][sidx] + (rot @ sample[:, :, None])[:, :, 0])
                new["log_scales"].append(p["log_scales"][sidx] - math.log(1.6))
                for k in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
                    new[k].append(p[k][sidx])
        new_t = {k: torch.cat(v) for k, v in new.items()}
        opac = torch.sigmoid(p["opacity_logits"])
        prune = (opac < cfg.prune_opacity) | split
        if it > cfg.opacity_reset_interval:
            prune |= (st.max_radius > cfg.max_screen_px) | (scale_max > 0.1 * self.extent)
        unused_after = 2 * len(self.frames)
        if it > unused_after:
            prune |= st.last_seen < it - unused_after
        self._apply(~prune, new_t)
        st.grad_accum.zero_()
        st.grad_count.zero_()
        st.max_radius.zero_()

    def reset_opacity(self) -> None:
        """3DGS opacity reset: opacity ← min(opacity, 0.01), with its Adam moments cleared."""
        st = self.state
        logit_001 = math.log(0.01 / 0.99)
        st.params["opacity_logits"] = torch.clamp_max(st.params["opacity_logits"].detach(), logit_001)
        st.exp_avg["opacity_logits"].zero_()
        st.exp_avg_sq["opacity_logits"].zero_()

    def prune_unused(self) -> int:
        """Remove Gaussians that change no training pixel (max blending weight < 1/255); returns count."""
        weights = max_blend_weight(self.model(), [f.camera for f in self.frames], self.config.near_m)
        keep = torch.from_numpy(weights >= 1.0 / 255.0)
        removed = int((~keep).sum())
        self._apply(keep)
        return removed

    # ------------------------------------------------------------------ evaluation, IO, loop
    def evaluate(self, frames: list[DatasetFrame] | None = None) -> float:
        """Mean PSNR (dB) of the fast renderer on ``frames`` (default: the held-out test frames)."""
        frames = self.test_frames if frames is None else frames
        if not frames:
            return float("nan")
        model = self.model()
        vals = [psnr(render(model, f.camera, self.config.background, sh_degree=self.state.sh_active,
                            near_m=self.config.near_m).rgb, f.image) for f in frames]
        return float(np.mean(vals))

    def save_checkpoint(self, path: str | Path) -> Path:
        """torch.save everything needed to resume: tensors and plain Python types only, so that
        :meth:`load_checkpoint` reads it with ``torch.load(weights_only=True)`` (no arbitrary unpickling)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        st = self.state
        torch.save({"config": self.config.to_dict(), "params": st.params, "exp_avg": st.exp_avg,
                    "exp_avg_sq": st.exp_avg_sq, "step": st.step, "grad_accum": st.grad_accum,
                    "grad_count": st.grad_count, "max_radius": st.max_radius, "last_seen": st.last_seen,
                    "sh_active": int(st.sh_active), "history": [tuple(_plain(v) for v in h) for h in st.history],
                    "rng": self.rng.bit_generator.state,
                    "torch_rng": self.torch_gen.get_state(), "extent": float(self.extent),
                    "perm": [int(i) for i in self._perm]}, path)
        return path

    def load_checkpoint(self, path: str | Path) -> None:
        """Resume from :meth:`save_checkpoint` output (the frames must be the same dataset)."""
        ck = torch.load(Path(path), weights_only=True)  # tensors and plain types only: no arbitrary unpickling
        st = self.state
        st.params, st.exp_avg, st.exp_avg_sq = ck["params"], ck["exp_avg"], ck["exp_avg_sq"]
        st.step, st.grad_accum, st.grad_count = ck["step"], ck["grad_accum"], ck["grad_count"]
        st.max_radius, st.last_seen, st.sh_active = ck["max_radius"], ck["last_seen"], ck["sh_active"]
        st.history = [HistoryRow(*h) for h in ck["history"]]
        self.rng.bit_generator.state = ck["rng"]
        self.torch_gen.set_state(ck["torch_rng"])
        self.extent = ck["extent"]
        self._perm = [int(i) for i in ck["perm"]]

    def train(self, iterations: int | None = None, *, checkpoint: str | Path | None = None,
              eval_every: int = 0, progress: bool = True, time_budget_s: float | None = None,
              cpu_budget_s: float | None = None) -> GaussianModel:
        """Run until ``iterations`` (default: config), ``time_budget_s`` of wall time or ``cpu_budget_s``
        of process CPU time (all threads; excludes held-out evaluation); returns the model.

        Appends :class:`HistoryRow` (iteration, wall s, CPU s, train loss, held-out PSNR or NaN,
        Gaussian count) to ``state.history`` every ``eval_every`` iterations and at the end.
        """
        total = self.config.iterations if iterations is None else iterations
        st = self.state
        wall0 = time.perf_counter() - (st.history[-1].wall_s if st.history else 0.0)
        cpu_used = st.history[-1].cpu_s if st.history else 0.0
        bar = tqdm(total=total, initial=st.step, disable=not progress, unit="it", dynamic_ncols=True)
        loss = float("nan")
        while st.step < total:
            c0 = time.process_time()
            loss, view_psnr = self.step()
            cpu_used += time.process_time() - c0
            bar.update(1)
            if st.step % 10 == 0:
                bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{view_psnr:.2f}", n=self.num_gaussians)
            if eval_every and st.step % eval_every == 0:
                st.history.append(HistoryRow(st.step, time.perf_counter() - wall0, cpu_used, loss, self.evaluate(),
                                             self.num_gaussians))
            if checkpoint and self.config.checkpoint_every and st.step % self.config.checkpoint_every == 0:
                self.save_checkpoint(checkpoint)
            if time_budget_s is not None and time.perf_counter() - wall0 >= time_budget_s:
                break
            if cpu_budget_s is not None and cpu_used >= cpu_budget_s:
                break
        bar.close()
        if self.config.final_prune:
            c0 = time.process_time()
            self.prune_unused()
            cpu_used += time.process_time() - c0
        st.history.append(HistoryRow(st.step, time.perf_counter() - wall0, cpu_used, loss, self.evaluate(),
                                     self.num_gaussians))
        if checkpoint:
            self.save_checkpoint(checkpoint)
        return self.model()
