"""The in-slot rule's prices for a plan (pure): :class:`InSlotPricing` turns the price on the loss budget
(:mod:`gsrmr_scheduler.slot_price`) into per-slot gain thresholds, with exploration, probing and the link's cap on the
expected images (docs/scheduling.md, "The live loop", item 5).
"""

from __future__ import annotations

import numpy as np

from gsrmr_scheduler.slot_price import cap_expected_images, gain_thresholds, rician_power_samples


class InSlotPricing:
    """Gain thresholds per slot for the in-slot rule, with exploration, probing and the link's cap."""

    def __init__(self, rician_k: float, *, explore_image_fraction: float = 0.0, probe_gap_slots: int = 0,
                 startup_explore_samples: int = 0) -> None:
        if not 0.0 <= explore_image_fraction <= 1.0:
            raise ValueError("in-slot pricing: explore_image_fraction must be in [0, 1]")
        if probe_gap_slots < 0 or startup_explore_samples < 0:
            raise ValueError("in-slot pricing: probe_gap_slots and startup_explore_samples must be >= 0")
        self.fading = rician_power_samples(rician_k)  # sorted |h|² draws (mean 1): the fades the rule prices
        self.explore_image_fraction = float(explore_image_fraction)
        self.probe_gap_slots = int(probe_gap_slots)
        self.startup_explore_samples = int(startup_explore_samples)
        self.last_image_slot: int | None = None  # the newest slot the robot sent an image in

    def record_image(self, slot: int) -> None:
        """The robot sent an image in ``slot`` (its ledger): the probing clock restarts there."""
        if self.last_image_slot is None or slot > self.last_image_slot:
            self.last_image_slot = slot

    def explore(self, slots: np.ndarray, samples_held: int) -> np.ndarray:
        """Per-slot exploration fraction for absolute ``slots`` while the L_t predictor holds ``samples_held``
        measurements: an image at least when the slot's fade is in that best fraction of fades."""
        explore = np.full(slots.shape, self.explore_image_fraction)
        if samples_held < self.startup_explore_samples:  # the seed map may be far off: measure first
            explore = np.maximum(explore, 0.5)
        if self.probe_gap_slots > 0:  # no image for a while: accept ever poorer fades, up to the median one
            last = self.last_image_slot if self.last_image_slot is not None else int(slots[0]) - 1
            explore = np.maximum(explore, 0.5 * np.minimum(1.0, (slots - last) / self.probe_gap_slots))
        return explore

    def thresholds(self, mean_gain: np.ndarray, key_cost: np.ndarray, loss_cap: float, explore: np.ndarray,
                   coeff_j: float, max_images: float | None = None) -> tuple[np.ndarray, float]:
        """(g*_t per slot, λ) for slots of mean gain ``mean_gain`` whose key leaves ``key_cost`` more loss than an
        image, under the loss budget ``loss_cap`` (Σ over the slots), with the exploration fractions
        ``explore`` and the saving coefficient ``coeff_j`` (:func:`~gsrmr_scheduler.slot_price.saving_coefficient_j`);
        ``max_images``: the link's cap on the rule's expected images (None: no cap)."""
        thresholds, price, _ = gain_thresholds(mean_gain, key_cost, loss_cap, coeff_j, self.fading, explore)
        if max_images is not None:  # the link carries fewer images than the budget asks: the best of them
            thresholds, scale = cap_expected_images(thresholds, mean_gain, self.fading, max_images)
            price *= scale
        return thresholds, price
