"""The optimiser state of a training run and the operations on it: Adam per parameter group, row selection
(prune / append with zeroed moments), the opacity reset. The per-frame pose and exposure corrections have their
own per-row Adam (:class:`~gsrmr_splat.camera_opt.FrameCorrections`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
import math

import torch

from gsrmr_splat.camera_opt import FrameCorrections

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")


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
    # Per-training-frame corrections (camera_opt), None unless TrainConfig.pose_opt / exposure_opt; their
    # summaries (dicts of floats) recorded beside the history rows while either is on.
    pose: FrameCorrections | None = None
    exposure: FrameCorrections | None = None
    correction_history: list = field(default_factory=list)


def adam_step(state: TrainState, lr: Callable[[str, int], float], it: int, beta1: float = 0.9,
              beta2: float = 0.999, eps: float = 1e-15) -> None:
    """One Adam update of every parameter with a gradient (learning rate ``lr(name, it)``); clears the grads."""
    for name, v in state.params.items():
        if v.grad is None:
            continue
        g = v.grad
        m, s = state.exp_avg[name], state.exp_avg_sq[name]
        m.mul_(beta1).add_(g, alpha=1 - beta1)
        s.mul_(beta2).addcmul_(g, g, value=1 - beta2)
        bc1, bc2 = 1 - beta1**it, 1 - beta2**it
        v.requires_grad_(False)
        v.addcdiv_(m, (s / bc2).sqrt_().add_(eps), value=-lr(name, it) / bc1)
        v.grad = None


def select_rows(state: TrainState, keep: torch.Tensor, new: dict[str, torch.Tensor] | None = None) -> None:
    """Keep rows ``keep`` of every per-Gaussian tensor and append ``new`` rows (zero optimiser state)."""
    st = state
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


def reset_opacity(state: TrainState) -> None:
    """3DGS opacity reset: opacity ← min(opacity, 0.01), with its Adam moments cleared."""
    logit_001 = math.log(0.01 / 0.99)
    state.params["opacity_logits"] = torch.clamp_max(state.params["opacity_logits"].detach(), logit_001)
    state.exp_avg["opacity_logits"].zero_()
    state.exp_avg_sq["opacity_logits"].zero_()
