"""Per-frame corrections learned with the model, one row per training frame in a :class:`FrameCorrections`: a camera
pose refinement δ = (ω rad, τ m) in world (``map``) axes, rotating about the camera's optical centre
(:func:`corrected_world_to_camera`), and an exposure model exp(g)·rgb + b per channel (:func:`apply_exposure`, training
only). Each table's mean row is held at zero (the gauge: the model stays in ``map``). Design, rates and measurements:
docs/splatting.md, "Training on what a robot records".
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
import torch

from gsrmr_common.nerfstudio import DatasetFrame
from gsrmr_splat.diffrender import render_torch
from gsrmr_splat.losses import train_loss
from gsrmr_splat.project import NEAR_M

POSE_DIM = 6  # (ω_x, ω_y, ω_z) rad, (τ_x, τ_y, τ_z) m: world axes, rotation about the camera centre
EXPOSURE_DIM = 6  # (log-gain r, g, b), (bias r, g, b): rgb in [0, 1]
_SMALL_ANGLE_RAD2 = 1e-8  # below this θ² the Taylor series of Rodrigues' coefficients is exact in float64


def hat(v: torch.Tensor) -> torch.Tensor:
    """3-vector → 3×3 skew matrix [v]× (v × x = [v]× x)."""
    z = torch.zeros((), dtype=v.dtype)
    return torch.stack([torch.stack([z, -v[2], v[1]]), torch.stack([v[2], z, -v[0]]),
                        torch.stack([-v[1], v[0], z])])


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rotation vector ω [rad] → 3×3 rotation matrix (Rodrigues), differentiable also at ω = 0."""
    theta2 = (omega * omega).sum()
    small = theta2 < _SMALL_ANGLE_RAD2
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)  # keeps sqrt and the divisions finite at 0
    theta = torch.sqrt(safe2)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    k = hat(omega)
    return torch.eye(3, dtype=omega.dtype) + a * k + b * (k @ k)


def corrected_world_to_camera(world_to_camera: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """The recorded world→camera 4×4 (OpenCV axes) corrected by δ = (ω rad, τ m) in world axes: camera→world
    rotation Exp(ω)·Rᵀ, optical centre c + τ; (−ω, −τ) undoes (ω, τ) exactly. Differentiable in ``delta`` (and
    ``world_to_camera``)."""
    rot = world_to_camera[:3, :3]
    center = -rot.T @ world_to_camera[:3, 3]
    rot_new = rot @ so3_exp(delta[:3]).T
    t_new = -rot_new @ (center + delta[3:])
    top = torch.cat([rot_new, t_new[:, None]], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=world_to_camera.dtype)
    return torch.cat([top, bottom], dim=0)


def corrected_world_to_camera_np(world_to_camera: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """:func:`corrected_world_to_camera` on numpy float64 arrays."""
    with torch.no_grad():
        return corrected_world_to_camera(torch.as_tensor(np.asarray(world_to_camera, np.float64)),
                                         torch.as_tensor(np.asarray(delta, np.float64))).numpy()


def apply_exposure(rgb: torch.Tensor, row: torch.Tensor) -> torch.Tensor:
    """H×W×3 image → exp(g)·rgb + b per channel (row = g r, g, b then b r, g, b)."""
    return rgb * torch.exp(row[:3]).to(rgb.dtype) + row[3:].to(rgb.dtype)


def undo_exposure(image: np.ndarray, row: np.ndarray) -> np.ndarray:
    """A recorded H×W×3 image mapped back to the model's exposure: (image − b)/exp(g), clipped to [0, 1]."""
    row = np.asarray(row, np.float64)
    return np.clip((np.asarray(image, np.float64) - row[3:]) / np.exp(row[:3]), 0.0, 1.0).astype(np.float32)


@dataclass
class FrameCorrections:
    """One row of ``dim`` numbers per training frame (float64) with per-row Adam state and step counts."""

    values: torch.Tensor  # P×D
    exp_avg: torch.Tensor  # P×D
    exp_avg_sq: torch.Tensor  # P×D
    steps: torch.Tensor  # P (int64): Adam updates of each row

    @classmethod
    def zeros(cls, frames: int, dim: int) -> FrameCorrections:
        """``frames`` rows of zeros (the identity correction for both kinds)."""
        z = torch.zeros(frames, dim, dtype=torch.float64)
        return cls(z.clone(), z.clone(), z.clone(), torch.zeros(frames, dtype=torch.long))

    @property
    def frames(self) -> int:
        """P, the number of rows."""
        return int(self.values.shape[0])

    def row(self, i: int) -> torch.Tensor:
        """Row ``i`` as a fresh leaf tensor that records its gradient."""
        return self.values[i].clone().requires_grad_(True)

    def adam_update(self, i: int, grad: torch.Tensor, lr: float, beta1: float = 0.9, beta2: float = 0.999,
                    eps: float = 1e-15) -> None:
        """One Adam step of row ``i`` with its own step count (the other rows and their moments are untouched)."""
        g = grad.detach().to(torch.float64)
        self.steps[i] += 1
        n = int(self.steps[i])
        m, s = self.exp_avg[i], self.exp_avg_sq[i]
        m.mul_(beta1).add_(g, alpha=1 - beta1)
        s.mul_(beta2).addcmul_(g, g, value=1 - beta2)
        bc1, bc2 = 1 - beta1**n, 1 - beta2**n
        self.values[i].addcdiv_(m, (s / bc2).sqrt_().add_(eps), value=-lr / bc1)

    def remove_mean(self) -> None:
        """The gauge rule: subtract the mean row from every row (the corrections average to zero)."""
        self.values -= self.values.mean(dim=0, keepdim=True)

    def to_dict(self) -> dict[str, torch.Tensor]:
        """Tensors only (a checkpoint entry that ``torch.load(weights_only=True)`` reads)."""
        return {"values": self.values, "exp_avg": self.exp_avg, "exp_avg_sq": self.exp_avg_sq, "steps": self.steps}

    @classmethod
    def from_dict(cls, d: dict[str, torch.Tensor]) -> FrameCorrections:
        """Inverse of :meth:`to_dict`."""
        return cls(d["values"], d["exp_avg"], d["exp_avg_sq"], d["steps"])


def pose_summary(poses: FrameCorrections) -> dict[str, float]:
    """Mean and max over frames of the corrections' size: ‖τ‖ in cm, ‖ω‖ in degrees."""
    v = poses.values.numpy()
    trans_cm = np.linalg.norm(v[:, 3:], axis=1) * 100.0
    rot_deg = np.degrees(np.linalg.norm(v[:, :3], axis=1))
    return {"pose_delta_mean_cm": float(trans_cm.mean()), "pose_delta_max_cm": float(trans_cm.max()),
            "pose_delta_mean_deg": float(rot_deg.mean()), "pose_delta_max_deg": float(rot_deg.max())}


def exposure_summary(exposure: FrameCorrections) -> dict[str, float]:
    """Range over frames and channels of the gains exp(g) and biases b."""
    v = exposure.values.numpy()
    gains = np.exp(v[:, :3])
    return {"exposure_gain_min": float(gains.min()), "exposure_gain_max": float(gains.max()),
            "exposure_bias_min": float(v[:, 3:].min()), "exposure_bias_max": float(v[:, 3:].max())}


def pose_delta_size(delta: np.ndarray) -> tuple[float, float]:
    """(‖τ‖ cm, ‖ω‖ degrees) of one pose correction."""
    d = np.asarray(delta, np.float64)
    return float(np.linalg.norm(d[3:]) * 100.0), float(math.degrees(np.linalg.norm(d[:3])))


def per_frame_rows(file_paths: list[str], poses: FrameCorrections | None,
                   exposure: FrameCorrections | None) -> list[dict]:
    """Per frame: ``file_path``; with ``poses`` its δ (ω rad, τ m) and size (cm, degrees); with ``exposure`` its
    gains exp(g) and biases b (r, g, b)."""
    rows = []
    for i, name in enumerate(file_paths):
        row: dict = {"file_path": name}
        if poses is not None:
            d = poses.values[i].numpy()
            cm, deg = pose_delta_size(d)
            row.update({"pose_delta": [float(v) for v in d], "pose_delta_cm": cm, "pose_delta_deg": deg})
        if exposure is not None:
            e = exposure.values[i].numpy()
            row.update({"exposure_gain": [float(v) for v in np.exp(e[:3])],
                        "exposure_bias": [float(v) for v in e[3:]]})
        rows.append(row)
    return rows


def refine_pose(params: dict[str, torch.Tensor], frame: DatasetFrame, steps: int, lr: float, *,
                background=(0.0, 0.0, 0.0), sh_degree: int = 0, near_m: float = NEAR_M) -> np.ndarray:
    """Test-time pose refinement of one frame against a frozen model (``params`` as the trainer holds them):
    ``steps`` Adam steps of step size ``lr`` on the frame's δ (from zero, loss 0.8·L1 + 0.2·(1 − SSIM), no gauge
    rule: the model does not move). Returns δ (ω rad, τ m, world axes) for :func:`corrected_world_to_camera_np`."""
    p = {k: v.detach() for k, v in params.items()}
    sh = torch.cat([p["sh_dc"], p["sh_rest"]], dim=1)
    target = torch.from_numpy(np.ascontiguousarray(frame.image, np.float32))
    recorded = torch.as_tensor(frame.camera.world_to_camera, dtype=torch.float64)
    delta = FrameCorrections.zeros(1, POSE_DIM)
    for _ in range(steps):
        row = delta.row(0)
        out = render_torch(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], sh, frame.camera,
                           background, sh_degree=sh_degree, near_m=near_m,
                           world_to_camera=corrected_world_to_camera(recorded, row))
        train_loss(out.rgb, target).backward()
        if row.grad is not None:
            delta.adam_update(0, row.grad, lr)
    return delta.values[0].numpy().copy()
