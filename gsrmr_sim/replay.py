"""Replay a recorded run through the online planner (pure; an offline study tool, never used live).

What is replayed (the live loop's information flow) and what is not (timing): docs/experiments.md, "Replaying a
recorded run"; the studies made with it: docs/scheduling.md.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass
import math
import time

import numpy as np

from gsrmr_common.pose2d import Pose2D
from gsrmr_robot.scene_change import ChangeProbe
from gsrmr_scheduler.planner import OnlinePlanner
from gsrmr_sim.hindsight import hindsight_optimum


@dataclass(frozen=True)
class RecordedSlot:
    """One slot of a recorded run: the world as it was, whatever the scheduler did."""

    slot: int
    pose: Pose2D  # (a_m, b_m, theta_rad) the robot reported, map frame
    gain: float  # channel power gain the radio measured (linear)
    energy_image_j: float
    energy_key_j: float
    image_truth_loss: float
    gs_truth_loss: float
    measured_gs_loss: float  # the L_t the server would measure if an image came
    scored: bool


def recorded_slots(rows: list[dict]) -> list[RecordedSlot]:
    """``slots.csv`` rows (:func:`gsrmr_server.recording.read_slots_csv`) → replayable slots; rows missing a
    hindsight value (a slot the server did not compose) are skipped."""
    need = ("channel_gain", "energy_image_j", "energy_key_j", "image_truth_loss", "gs_truth_loss", "pose_a_m")
    ok = [r for r in rows if all(r.get(c) is not None and r.get(c) != "" for c in need)]
    biases = [float(r["gs_loss"]) - float(r["gs_truth_loss"]) for r in ok if r.get("gs_loss") not in (None, "")]
    bias = float(np.median(biases)) if biases else 0.0
    out = []
    for r in ok:
        measured = r.get("gs_loss")
        measured = float(measured) if measured not in (None, "") else float(r["gs_truth_loss"]) + bias
        out.append(RecordedSlot(int(r["slot"]), (float(r["pose_a_m"]), float(r["pose_b_m"]),
                                                 float(r["pose_theta_rad"])),
                                float(r["channel_gain"]), float(r["energy_image_j"]), float(r["energy_key_j"]),
                                float(r["image_truth_loss"]), float(r["gs_truth_loss"]), measured,
                                bool(int(r.get("scored") or 0))))
    return out


@dataclass(frozen=True)
class ReplayResult:
    """What the replayed planner did and what it cost (scored slots only in the figures)."""

    x: np.ndarray  # per recorded slot, 1 = image
    energy_j: float
    mean_loss: float
    images: int
    energy_hindsight_j: float
    regret: float
    replans: int
    plan_time_s: float  # Σ over replans of the planner's wall time

    def row(self) -> dict:
        """Figures as a flat dict."""
        return {"energy_j": self.energy_j, "mean_loss": self.mean_loss, "images": self.images,
                "energy_hindsight_j": self.energy_hindsight_j, "regret": self.regret, "replans": self.replans,
                "plan_time_s": self.plan_time_s}


class TruthLossPredictor:
    """Hindsight bound for studies only: the recorded truth L of every slot in place of the burst model
    (``OnlinePlanner(config, route, loss_map, link, loss_model=TruthLossPredictor(slots))``). What the
    planner would do if it knew L_t exactly — never available live."""

    margin = 1.0
    level = 0.0
    burst_factor = 1.0
    samples = 1_000_000

    def __init__(self, slots: list[RecordedSlot], default: float = 0.05, *, as_sampled: bool = False) -> None:
        """``as_sampled``: each slot's L as the server's loss sample reads it (``measured_gs_loss``: against the
        decoded JPEG) instead of against the true frame."""
        self._truth = {s.slot: s.measured_gs_loss if as_sampled else s.gs_truth_loss for s in slots}
        self._default = default

    def observe(self, *_args, **_kwargs) -> None:
        """Measurements add nothing to the truth."""

    def predict(self, slots: np.ndarray, _poses: np.ndarray) -> np.ndarray:
        """The recorded truth of ``slots``."""
        return np.array([self._truth.get(int(k), self._default) for k in slots], np.float64)

    def estimate(self, slot: int, _pose: Pose2D) -> float:
        """The recorded truth of ``slot``."""
        return self._truth.get(int(slot), self._default)

    def note_change(self, _slot: int) -> None:
        """The truth needs no change slots."""


def replay(slots: list[RecordedSlot], planner: OnlinePlanner, *, loss_threshold: float, replan_every: int = 20,
           measurement_delay: int = 1, on_plan: Callable[[int, object], None] | None = None,
           observe_keys: bool = False, scene_changes: Collection[int] = (),
           change_probe: ChangeProbe | None = None,
           mean_gain: Callable[[Pose2D], float] | None = None) -> ReplayResult:
    """Play ``slots`` through ``planner`` (a fresh :class:`OnlinePlanner`); see the module docstring.
    ``observe_keys`` (a hindsight study, never live): the L_t forecast also learns every *key* slot's loss sample,
    as if each slot had been measured — what knowing the past exactly is worth. ``scene_changes``: the slots in
    which the run's robot found a scene change; with ``change_probe`` (fresh) and ``mean_gain`` (the expected
    gain at a reported pose) the robot's image for each is replayed."""
    if replan_every < 1 or measurement_delay < 0:
        raise ValueError("replay: replan_every ≥ 1 and measurement_delay ≥ 0")
    if scene_changes and (change_probe is None or mean_gain is None):
        raise ValueError("replay: scene_changes need a change_probe and a mean_gain")
    changes = frozenset(int(k) for k in scene_changes)
    x = np.zeros(len(slots), np.int8)
    pending: list[tuple[int, RecordedSlot, bool]] = []  # (index when it arrives, slot measured, an image slot)
    pose: Pose2D | None = None
    replan_due, replans, plan_time = True, 0, 0.0
    since_plan = 0
    for i, s in enumerate(slots):
        for item in [p for p in pending if p[0] <= i]:
            pending.remove(item)
            m = item[1]
            if item[2]:
                if planner.observe(m.slot, *m.pose, m.measured_gs_loss):
                    replan_due = True
            else:  # observe_keys: the forecast learns the key slot's L (no ledger, link or drift effect)
                planner.forecast.observe(m.slot, m.pose, planner.forecast.corrected(m.measured_gs_loss))
        if replan_due or since_plan >= replan_every or planner.active is None:
            t0 = time.perf_counter()
            result = planner.plan(s.slot - 1, pose)
            plan_time += time.perf_counter() - t0
            replans += 1
            planner.clear_drift()
            replan_due, since_plan = False, 0
            if on_plan is not None:
                on_plan(i, result)
        since_plan += 1
        sched = planner.active
        entry = sched.lookup(s.slot) if sched is not None else None
        threshold = sched.threshold(s.slot) if sched is not None else None
        if threshold is not None and math.isfinite(s.gain):
            x[i] = int(s.gain >= threshold)
        else:
            x[i] = int(entry[0]) if entry is not None else 1
        if change_probe is not None and changes:
            if s.slot in changes:
                change_probe.changed(s.slot)
            if x[i] == 0 and entry is not None and change_probe.wants_image(s.slot, s.gain, mean_gain(s.pose)):
                x[i] = 1
            if x[i]:
                change_probe.image_sent()
        pose = s.pose
        planner.record_pose(s.slot, *s.pose)
        planner.record_action(s.slot, int(x[i]), scene_change=int(s.slot in changes))
        if x[i] or observe_keys:
            pending.append((i + measurement_delay, s, bool(x[i])))
    scored = np.array([s.scored for s in slots], bool)
    e_img = np.array([s.energy_image_j for s in slots])
    e_key = np.array([s.energy_key_j for s in slots])
    l_img = np.array([s.image_truth_loss for s in slots])
    l_gs = np.array([s.gs_truth_loss for s in slots])
    energy = np.where(x == 1, e_img, e_key)[scored]
    loss = np.where(x == 1, l_img, l_gs)[scored]
    best = hindsight_optimum(e_img[scored], e_key[scored], l_img[scored], l_gs[scored], loss_threshold)
    total = math.fsum(energy.tolist())
    return ReplayResult(x, total, float(loss.mean()) if loss.size else math.nan, int(x[scored].sum()), best.energy_j,
                        total / best.energy_j if best.energy_j > 0 else math.nan, replans, plan_time)
