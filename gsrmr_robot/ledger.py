"""The robot's uplink energy ledger (pure): what each slot actually sent and what it cost (:class:`EnergyLedger`).

Power ``p = (σ²/g)·(2^{bits/(τB)} − 1)`` [W] and energy ``τ·p`` [J] at the slot's channel gain g, by the link model
(:mod:`gsrmr_common.link_model`); the row's fields: :class:`gsrmr_common.wire.LedgerRow`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict
import math

from gsrmr_common.wire import POSE_KEY_BITS, LedgerRow

# required_power_w(bits, gain, slot_s, bandwidth_hz, noise_w) -> watts (inf if impossible)
PowerFunction = Callable[[float, float, float, float, float], float]


class EnergyLedger:
    """Accumulates :class:`LedgerRow` totals; thread-compatible (callers serialise access).

    A slot's bits are the JPEG bytes × 8 plus the 192-bit pose key, or the key alone. Each slot also prices the
    upload-all reference (RoboMR: the same frame's JPEG every slot, no key), so the energy ratio is measured on the
    frames of this run, not on a nominal image size. A slot whose bits no finite power can carry
    (2^{bits/(τB)} overflows) is recorded with ``energy_j = inf`` and counted in ``undeliverable``; the totals leave
    it out and stay finite.
    """

    def __init__(self, required_power_w: PowerFunction, slot_s: float, bandwidth_hz: float,
                 noise_w: float) -> None:
        self._power = required_power_w
        self.slot_s, self.bandwidth_hz, self.noise_w = slot_s, bandwidth_hz, noise_w
        self.slots = self.images = self.keys_only = self.undeliverable = self.held_back = 0
        self.bits_sent = 0
        self.energy_j = 0.0
        self.upload_all_energy_j = 0.0

    def _energy(self, bits: int, gain: float) -> tuple[float, float]:
        if bits <= 0:
            return 0.0, 0.0
        power = self._power(float(bits), gain, self.slot_s, self.bandwidth_hz, self.noise_w)
        return power, self.slot_s * power

    def record(self, slot: int, x: int, scheduled_power_w: float, jpeg_bytes: int | None, gain: float,
               reference_jpeg_bytes: int | None, frame_stamp_s: float = float("nan"),
               round_slot: int = -1, held_back: int = 0, uplink_rate_bps: float = float("nan"),
               scene_change: int = 0, correction_seq: int = 0) -> LedgerRow:
        """Record one slot. ``jpeg_bytes`` is None for a key-only slot; ``reference_jpeg_bytes`` is the
        size this slot's frame has (or would have) as a JPEG, for the upload-all reference; ``scene_change`` 1
        when the robot's scene-change test fired on this slot's frame."""
        bits = POSE_KEY_BITS + (8 * jpeg_bytes if jpeg_bytes is not None else 0)
        power_w, energy_j = self._energy(bits, gain)
        ref_bits = 8 * reference_jpeg_bytes if reference_jpeg_bytes else 0
        _, ref_energy_j = self._energy(ref_bits, gain)
        row = LedgerRow(slot, int(x), float(scheduled_power_w), bits, float(gain), power_w, energy_j,
                        ref_bits, ref_energy_j, float(frame_stamp_s), int(round_slot), int(held_back),
                        float(uplink_rate_bps), int(scene_change), int(correction_seq))
        self.slots += 1
        self.images += int(jpeg_bytes is not None)
        self.keys_only += int(jpeg_bytes is None)
        self.held_back += int(held_back)
        self.bits_sent += bits
        if math.isfinite(energy_j):
            self.energy_j += energy_j
        else:
            self.undeliverable += 1
        if math.isfinite(ref_energy_j):
            self.upload_all_energy_j += ref_energy_j
        return row

    def totals(self) -> dict[str, float]:
        """Totals for diagnostics and the run summary."""
        ratio = self.upload_all_energy_j / self.energy_j if self.energy_j > 0 else float("nan")
        return {"slots": self.slots, "images_sent": self.images, "keys_only": self.keys_only,
                "bits_sent": self.bits_sent, "energy_j": self.energy_j,
                "energy_upload_all_j": self.upload_all_energy_j, "energy_ratio_vs_upload_all": ratio,
                "undeliverable": self.undeliverable, "images_held_back": self.held_back}

    @staticmethod
    def row_dict(row: LedgerRow) -> dict:
        """A row as a plain dict."""
        return asdict(row)
