"""Adaptive density control (the 3DGS default strategy, as gsplat's ``DefaultStrategy``): clone, split and
prune from the accumulated screen-space gradients, radii and visibility.
"""

from __future__ import annotations

import math

import torch

from gsrmr_splat.diffrender import quat_to_rotmat_torch
from gsrmr_splat.optim import PARAM_NAMES, TrainState, select_rows
from gsrmr_splat.train_config import TrainConfig


def densify_and_prune(st: TrainState, cfg: TrainConfig, extent: float, n_views: int, it: int,
                      generator: torch.Generator) -> None:
    """Clone, split and prune (3DGS adaptive density control) under the Gaussian budget ``cfg.budget``.

    Candidates have a mean view-space positional gradient ≥ ``grad_threshold`` since the last call; the
    large ones (> ``percent_dense`` × extent) are split in two samples of their own distribution at 1/1.6
    the scale, the small ones cloned; ranked by gradient when the budget is short. Pruned: opacity below
    ``prune_opacity``, and after the first opacity reset too large on screen (radius > ``max_screen_px``) or in
    the world (largest scale > 0.1 × extent), and (with
    ``prune_unseen``) unseen for two passes over the ``n_views`` training views.
    """
    p = {k: v.detach() for k, v in st.params.items()}
    n = p["means"].shape[0]
    grads = st.grad_accum / st.grad_count.clamp_min(1)
    scale_max = p["log_scales"].exp().max(dim=1).values
    candidates = grads >= cfg.grad_threshold
    room = max(cfg.budget - n, 0)
    is_split = candidates & (scale_max > cfg.percent_dense * extent)
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
        rot = quat_to_rotmat_torch(p["quats"][sidx])
        for _ in range(2):
            sample = torch.randn(std.shape, generator=generator, dtype=std.dtype) * std
            new["means"].append(p["means"][sidx] + (rot @ sample[:, :, None])[:, :, 0])
            new["log_scales"].append(p["log_scales"][sidx] - math.log(1.6))
            for k in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
                new[k].append(p[k][sidx])
    new_t = {k: torch.cat(v) for k, v in new.items()}
    opac = torch.sigmoid(p["opacity_logits"])
    prune = (opac < cfg.prune_opacity) | split
    if it > cfg.opacity_reset_interval:
        prune |= (st.max_radius > cfg.max_screen_px) | (scale_max > 0.1 * extent)
    unused_after = 2 * n_views
    if cfg.prune_unseen and it > unused_after:
        prune |= st.last_seen < it - unused_after
    select_rows(st, ~prune, new_t)
    st.grad_accum.zero_()
    st.grad_count.zero_()
    st.max_radius.zero_()
