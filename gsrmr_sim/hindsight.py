"""The hindsight optimum of a finished run (pure; an evaluation, never used live).

The best 0/1 schedule over the run's scored slots, a knapsack solved exactly by :func:`gsrmr_scheduler.solve`:
formulation in docs/experiments.md, "The hindsight optimum".
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gsrmr_common import link_model as link
from gsrmr_scheduler.problem import Problem
from gsrmr_scheduler.solve import solve


@dataclass(frozen=True)
class Hindsight:
    """The best schedule in hindsight over the slots that had every value."""

    energy_j: float  # Σ energy of the optimal choice
    images: int
    mean_loss: float
    slots: int  # slots used (those with all four values)
    feasible: bool  # False when even all images exceed L_th (then x = all images)
    x: np.ndarray  # 1 = image


HINDSIGHT_COLUMNS = ("energy_image_j", "energy_key_j", "image_truth_loss", "gs_truth_loss")


def hindsight_summary(rows: list[dict], loss_threshold: float) -> dict:
    """The run's regret: its energy over the slots with every hindsight value (``slots.csv`` rows) divided
    by the hindsight optimum's over the same slots (computed after the run: an evaluation, not an oracle)."""
    ok = [r for r in rows if all(r.get(c) is not None for c in HINDSIGHT_COLUMNS) and r.get("energy_j") is not None]
    if not ok:
        return {"hindsight_slots": 0, "energy_hindsight_j": math.nan, "regret": math.nan}
    h = hindsight_optimum(*(np.array([r[c] for r in ok], float) for c in HINDSIGHT_COLUMNS), loss_threshold)
    run_energy = math.fsum(float(r["energy_j"]) for r in ok)
    return {"hindsight_slots": h.slots, "energy_hindsight_j": h.energy_j, "hindsight_images": h.images,
            "hindsight_mean_loss": h.mean_loss, "hindsight_feasible": h.feasible,
            "regret": run_energy / h.energy_j if h.energy_j > 0 else math.nan}


@dataclass(frozen=True)
class RegretSplit:
    """A run's regret split in two factors (computed after the run: an evaluation, never used live).

    ``regret`` = run energy / E*(L_th) = ``placement`` × ``unspent``, with E*(L) the hindsight optimum's energy at
    a mean-loss budget L: ``placement`` = run energy / E*(the run's own mean loss) — how well the run placed its
    images for the loss it ended with (1 = no schedule leaving that loss costs less) — and ``unspent`` =
    E*(own loss) / E*(L_th) — what ending the round below L_th cost (1 when the run used the whole budget; < 1 when
    it went over)."""

    regret: float
    placement: float
    unspent: float
    mean_loss: float  # the run's mean loss over the slots used (image slots: image_loss, key slots: gs_loss)
    images: int  # the run's images over the slots used
    images_at_own_loss: int  # the hindsight optimum's at the run's own mean loss


def regret_split(x, energy_j, energy_image_j, energy_key_j, image_loss, gs_loss,
                 loss_threshold: float) -> RegretSplit:
    """Split a run's regret (see :class:`RegretSplit`); per-slot arrays of one length: what the run did (``x``, 1 =
    image) and spent (``energy_j``), and the hindsight columns of :data:`HINDSIGHT_COLUMNS`."""
    x = np.asarray(x, np.int8)
    l_img, l_gs = np.asarray(image_loss, float), np.asarray(gs_loss, float)
    run_energy = math.fsum(np.asarray(energy_j, float).tolist())
    own_loss = math.fsum(np.where(x == 1, l_img, l_gs).tolist()) / max(x.size, 1)
    at_lth = hindsight_optimum(energy_image_j, energy_key_j, l_img, l_gs, loss_threshold)
    # the run's own schedule meets its own loss exactly: a hair of tolerance keeps it feasible through the rounding
    at_own = hindsight_optimum(energy_image_j, energy_key_j, l_img, l_gs, own_loss * (1 + 1e-9) + 1e-15)
    return RegretSplit(run_energy / at_lth.energy_j, run_energy / at_own.energy_j, at_own.energy_j / at_lth.energy_j,
                       own_loss, int(x.sum()), at_own.images)


def hindsight_optimum(energy_image_j, energy_key_j, image_loss, gs_loss, loss_threshold: float) -> Hindsight:
    """Exact 0/1 optimum (see the module docstring); inputs are per-slot arrays of one length."""
    e_img, e_key = np.asarray(energy_image_j, float), np.asarray(energy_key_j, float)
    l_img, l_gs = np.asarray(image_loss, float), np.asarray(gs_loss, float)
    n = e_img.size
    x = np.ones(n, np.int8)
    v, w = e_img - e_key, l_gs - l_img
    cap = n * loss_threshold - math.fsum(l_img.tolist())
    free = (w <= 0) & (v >= 0)
    x[free] = 0
    cap -= math.fsum(w[free].tolist())
    feasible = cap >= -1e-12
    items = np.flatnonzero(~free & (v > 0))
    if feasible and items.size and cap > 0:
        # savings v_t = (τσ²/g)(2^{I/τB} − 2^{S/τB}) of a Problem with the defaults: pick g_t to match v_t
        a_img = link.snr_exponent(link.IMAGE_BITS, link.SLOT_S, link.BANDWIDTH_HZ)
        a_key = link.snr_exponent(link.KEY_BITS, link.SLOT_S, link.BANDWIDTH_HZ)
        scale = link.SLOT_S * link.NOISE_W * (math.exp(a_img) - math.exp(a_key))
        problem = Problem(channel_gain=scale / v[items], gs_loss=w[items], loss_threshold=cap / items.size)
        schedule = solve(problem, "exact")
        x[items] = np.asarray(schedule.x, np.int8)
    energy = math.fsum(np.where(x == 1, e_img, e_key).tolist())
    loss = math.fsum(np.where(x == 1, l_img, l_gs).tolist()) / max(n, 1)
    return Hindsight(energy, int(x.sum()), loss, n, bool(feasible), x)
