"""The in-slot rule's prices for a plan (pure): per-slot gain thresholds, exploration and probing, the link's cap.

With the in-slot rule the robot sends an image in slot t only when the gain its radio measures reaches g*_t
(:mod:`gsrmr_scheduler.slot_price`: a price λ on the loss budget, set so that the rule's expected loss meets it).
:class:`InSlotPricing` adds what keeps the measurements coming and what the uplink allows:

* exploration: an image at least when the slot's fade is in the best ``explore_image_fraction`` of fades; in the
  better half until the L_t predictor holds ``startup_explore_samples`` measurements (the seed map may be far off);
* probing: ``probe_gap_slots`` after the last image the bound has ramped up to the median fade (any fade at or
  above it sends an image), so that a burst of L_t is not missed for long;
* the link's cap: the rule's expected images held to what the uplink carries
  (:func:`~gsrmr_scheduler.slot_price.cap_expected_images`, which raises the price).
"""

from __future__ import annotations

import numpy as np

from gsrmr_scheduler.slot_price import cap_expected_images, gain_thresholds, rician_power_samples


class InSlotPricing:
    """Gain thresholds per slot for the in-slot rule (see the module docstring)."""

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
