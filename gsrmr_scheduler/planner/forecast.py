"""L_t for the plan (pure): :class:`LossForecast` predicts future slots, estimates booked key slots and learns from each
loss sample, first corrected by the samples' JPEG bias (``sample_offset``).

Two sources: the burst model (:class:`~gsrmr_scheduler.loss_predictor.LossPredictor` over a frozen copy of the seed
map, with its learned margin: what a deployment plans with) or, with ``trust_loss_map``, the live loss map as it
stands (the oracle's). docs/scheduling.md, "The live loop", items 1, 2 and 7.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from gsrmr_common.pose2d import Pose2D
from gsrmr_scheduler.loss_map import LossMap
from gsrmr_scheduler.loss_predictor import LossPredictor

HISTORY_SLOTS = 1000  # predictions kept this long after the plan that made them


class SlotLossModel(Protocol):
    """What the burst model offers the planner (:class:`~gsrmr_scheduler.loss_predictor.LossPredictor`; a study
    may put the recorded truth in its place, :class:`gsrmr_sim.replay.TruthLossPredictor`)."""

    margin: float
    samples: int

    def observe(self, slot: int, pose: Pose2D, loss: float, predicted: float | None = None) -> None: ...

    def predict(self, slots: np.ndarray, poses: np.ndarray) -> np.ndarray: ...

    def estimate(self, slot: int, pose: Pose2D) -> float: ...

    def note_change(self, slot: int) -> None: ...


class LossForecast:
    """L_t predictions and estimates from the burst model, or from the loss map as it stands (``trust_loss_map``)."""

    def __init__(self, loss_map: LossMap, *, trust_loss_map: bool = False, burst_time_constant_slots: float = 25.0,
                 margin_quantile: float = 0.75, margin_window_samples: int = 30,
                 model: SlotLossModel | None = None, sample_offset: float = 0.0) -> None:
        if trust_loss_map and model is not None:
            raise ValueError("loss forecast: a loss model and trust_loss_map exclude each other")
        self.loss_map = loss_map  # keeps learning from the measured samples (saved for later runs)
        self.sample_offset = float(sample_offset)  # a loss sample minus the loss against the frame
        self._burst = {"burst_time_constant_slots": burst_time_constant_slots, "margin_quantile": margin_quantile,
                       "margin_window": margin_window_samples}
        self._own_model = not trust_loss_map and model is None
        # the burst model reads a frozen copy of the seed
        self.model: SlotLossModel | None = None if trust_loss_map else model or LossPredictor(
            LossMap.from_json(loss_map.to_json()), **self._burst)
        self._predicted: dict[int, float] = {}  # slot → what a plan predicted (no margin)
        self._measured = 0  # finite samples observed (trust_loss_map)

    def reseed(self, loss_map: LossMap) -> None:
        """Predict from a new seed map from now on (a new GS model's survey): the burst model restarts on a frozen
        copy of it; the samples measured so far went with the old map (they measured the old model)."""
        self.loss_map = loss_map
        if self._own_model:
            self.model = LossPredictor(LossMap.from_json(loss_map.to_json()), **self._burst)
        self._measured = 0

    def corrected(self, sample: float) -> float:
        """A server's loss sample as the loss against the camera's frame: ``sample − sample_offset``, floored at
        0 (a non-finite sample passes unchanged: the plausibility checks and observe refuse it)."""
        return max(sample - self.sample_offset, 0.0) if math.isfinite(sample) else sample

    @property
    def samples(self) -> int:
        """Measurements the prediction rests on (the burst model's, else every finite sample observed)."""
        return self.model.samples if self.model is not None else self._measured

    def predict(self, slots: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(L_t predicted at absolute ``slots`` and N×3 ``poses``, the same × the learned margin)."""
        if self.model is None:
            raw = self.loss_map.predict_many(poses)
            return raw, raw
        raw = self.model.predict(slots, poses)
        return raw, raw * self.model.margin

    def remember(self, first: int, predicted: np.ndarray, now_slot: int) -> None:
        """What a plan made at ``now_slot`` predicted for slots ``first …`` (forgetting very old slots)."""
        for i, value in enumerate(predicted):
            self._predicted[first + i] = float(value)
        for old in [k for k in self._predicted if k < now_slot - HISTORY_SLOTS]:
            del self._predicted[old]

    def predicted(self, slot: int) -> float | None:
        """What the latest plan covering ``slot`` predicted for it (no margin), or None."""
        return self._predicted.get(slot)

    def key_loss(self, slot: int, pose: Pose2D | None) -> float:
        """Estimated L a past key slot left: from the measurements around it at the pose the robot reported,
        the plan's prediction without a reported pose (the map's prior without either)."""
        if pose is None:
            return self._predicted.get(slot, self.loss_map.prior)
        if self.model is None:
            return self.loss_map.predict(*pose)
        return self.model.estimate(slot, pose)

    def note_change(self, slot: int) -> None:
        """The robot's scene-change test fired in ``slot`` (its ledger row): the burst model estimates the key slots
        around it as a step there (:meth:`~gsrmr_scheduler.loss_predictor.LossPredictor.note_change`)."""
        if self.model is not None:
            self.model.note_change(slot)

    def observe(self, slot: int, pose: Pose2D, loss: float) -> float | None:
        """An image slot's measured L_t at ``pose``; returns what the plan had predicted for it (or None)."""
        predicted = self._predicted.get(slot)
        if self.model is not None:
            self.model.observe(slot, pose, loss, predicted)
        elif math.isfinite(loss) and loss >= 0:
            self._measured += 1
        self.loss_map.add(*pose, loss)
        return predicted
