"""The uplink's carrying capacity as a cap on planned images (pure): :class:`LinkCap` turns the robot's ledger rows
(throughput estimate, held-back images, JPEG sizes: :mod:`gsrmr_robot.uplink_backlog`) and the server's loss samples
into the fraction of slots a plan may give an image (:meth:`LinkCap.image_cap`).
"""

from __future__ import annotations

from collections import deque
import math

import numpy as np

# ledger rows the uplink's carrying capacity is judged on (LinkCap.image_cap): 5 s of slots
LINK_WINDOW_SLOTS = 50
# images that must have been composed for the uplink to count as delivering them in their slots: the last
# DELIVERY_WINDOW_IMAGES the robot sent, older than DELIVERY_GRACE_SLOTS (the server's loss sample follows its
# slot by ~1 slot); fewer than MIN_DELIVERY_RATIO of them composed → the plan only probes (PROBE_IMAGE_FRACTION)
DELIVERY_WINDOW_IMAGES = 8
DELIVERY_GRACE_SLOTS = 10
MIN_DELIVERY_RATIO = 0.5
PROBE_IMAGE_FRACTION = 3 / LINK_WINDOW_SLOTS


class LinkCap:
    """The image fraction the uplink carries, from the robot's ledger and the server's loss samples."""

    def __init__(self, slot_s: float) -> None:
        if not (slot_s > 0 and math.isfinite(slot_s)):
            raise ValueError("link cap: slot_s must be > 0")
        self.slot_s = float(slot_s)
        # (slot, x, held_back, uplink_rate_bps, image_bits) of the last LINK_WINDOW_SLOTS ledger rows
        self._window: deque[tuple[int, int, int, float, float]] = deque(maxlen=LINK_WINDOW_SLOTS)
        self._sent_images: deque[int] = deque(maxlen=4 * DELIVERY_WINDOW_IMAGES)  # slots the robot sent an image in
        self._sampled_slots: deque[int] = deque(maxlen=1000)  # slots the server measured L_t in (image composed)

    def record(self, slot: int, x: int, held_back: int = 0, uplink_rate_bps: float = math.nan,
               image_bits: float = math.nan) -> None:
        """A ledger row: what the robot did in ``slot`` (1 = image), ``held_back`` = 1 when it sent the key for
        an asked-for image (its last one still queued), its throughput estimate and the frame's JPEG size."""
        self._window.append((int(slot), int(x), int(held_back), float(uplink_rate_bps), float(image_bits)))
        if x:
            self._sent_images.append(int(slot))

    def record_sample(self, slot: int) -> None:
        """The server measured L_t in ``slot``: it composed that slot's image in time."""
        self._sampled_slots.append(int(slot))

    def image_cap(self) -> float | None:
        """The fraction of slots that may plan an image because the uplink carries no more, or None (it carries
        at least one per slot): τ · R / b, with R the median of the robot's throughput estimates and b the median
        JPEG size over its last ``LINK_WINDOW_SLOTS`` ledger rows. R is what the link sustains for images: their
        bits over the time they were waiting (acknowledgement pending, or held back), so images that follow each
        other measure the share the other traffic leaves them, not one image's crossing at the link's whole rate
        (which read an image per slot on a link with room for 60 % of them). Slots the plan gives no image are
        not in that time: it measures the link, not the plan, so a cap does not ratchet itself down (a cap from
        the images the link carried would: fewer planned, fewer carried). When, on such a slow link, most recent
        images were not composed in their slot (:meth:`delivery_ratio` < ``MIN_DELIVERY_RATIO``: they arrive
        late), the cap is ``PROBE_IMAGE_FRACTION``: a few images keep measuring the link. Images lost to an
        outage do not count (the link is not slow once it is back)."""
        rates = [r for *_, r, _ in self._window if math.isfinite(r) and r > 0]
        sizes = [b for *_, b in self._window if math.isfinite(b) and b > 0]
        cap = self.slot_s * float(np.median(rates)) / float(np.median(sizes)) if rates and sizes else 1.0
        delivered = self.delivery_ratio()
        # only on a link measurably slower than an image per slot: images lost to an outage (the rate estimate
        # takes no sample from them) say nothing about the link once it is back
        if cap < 1.0 and delivered is not None and delivered < MIN_DELIVERY_RATIO:
            # the images the link carries arrive after their slot was composed (a link this slow takes longer
            # than the server waits): they cost energy and change nothing — only probe until they arrive again
            cap = min(cap, PROBE_IMAGE_FRACTION)
        return cap if cap < 1.0 else None

    def delivery_ratio(self) -> float | None:
        """Of the last ``DELIVERY_WINDOW_IMAGES`` images the robot sent (older than ``DELIVERY_GRACE_SLOTS``), the
        fraction the server composed in their slot (its loss sample came); None before the server has sent any
        sample (it may not measure) or with fewer than 2 such images."""
        if not self._sampled_slots or not self._window:
            return None
        newest = max(s for s, *_ in self._window)
        settled = [s for s in self._sent_images if s <= newest - DELIVERY_GRACE_SLOTS][-DELIVERY_WINDOW_IMAGES:]
        if len(settled) < 2:
            return None
        sampled = set(self._sampled_slots)
        return sum(s in sampled for s in settled) / len(settled)

    def images_held_back(self) -> int:
        """Images the robot held back in its last ``LINK_WINDOW_SLOTS`` ledger rows (its last one still queued)."""
        return sum(h for _, _, h, _, _ in self._window)


def cap_planned_images(x: np.ndarray, key_cost: np.ndarray, gains: np.ndarray, max_images: float) -> np.ndarray | None:
    """A plan's image/key choice ``x`` held to ``max_images`` images: the images kept are those saving the most
    loss per joule (key cost × gain); None when ``x`` already fits."""
    if x.sum() <= max_images:
        return None
    keep = np.argsort(-(key_cost * gains * x))[:int(max_images)]
    capped = np.zeros(len(x), np.int8)
    capped[keep] = x[keep]
    return capped
