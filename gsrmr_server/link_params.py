"""The uplink model as node parameters, shared by the robot (energy ledger) and the scheduler (plan).

Both nodes load ``config/link.yaml`` and call :meth:`LinkBudget.from_node_parameters`, so they agree on
B, σ², the path loss, the Rician K, the server position and the fading realisation of every slot:
g_k = one draw of :class:`gsrmr_server.scheduling.channel.ChannelModel` seeded by ``(channel_seed, k)``
(k the absolute slot index) at the robot–server distance. With the channel known to the scheduler in advance this is
the paper's perfect-CSI setting.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np

from gsrmr_server.scheduling.channel import ChannelModel
from gsrmr_server.scheduling.link import required_power_w


@dataclass(frozen=True)
class LinkBudget:
    """Uplink parameters in SI units (distances in metres in ``map``)."""

    bandwidth_hz: float = 1e6
    noise_w: float = 1e-9  # −60 dBm
    pathloss_db_at_1m: float = -30.0
    pathloss_exponent: float = 3.0
    rician_k: float = 1.0
    server_position_m: tuple[float, float] = (10.0, 0.0)
    channel_seed: int = 7
    min_distance_m: float = 1.0

    def distance_m(self, position_xy: np.ndarray | tuple[float, float] | None) -> float:
        """Robot–server distance (≥ ``min_distance_m``; the server position itself if unknown)."""
        if position_xy is None:
            return max(self.min_distance_m, math.hypot(*self.server_position_m))
        dx = float(position_xy[0]) - self.server_position_m[0]
        dy = float(position_xy[1]) - self.server_position_m[1]
        return max(self.min_distance_m, math.hypot(dx, dy))

    def gain(self, slot: int, position_xy: np.ndarray | tuple[float, float] | None) -> float:
        """Channel power gain g = |h|² of absolute slot ``slot`` at ``position_xy`` (robot x, y in map)."""
        model = ChannelModel(self.pathloss_db_at_1m, self.pathloss_exponent, self.rician_k,
                             seed=[self.channel_seed, int(slot)])  # type: ignore[arg-type]
        return float(model.gains(np.array([self.distance_m(position_xy)]))[0])

    def required_power_w(self, bits: float, gain: float, slot_s: float, bandwidth_hz: float,
                         noise_w: float) -> float:
        """Minimum power to carry ``bits`` in one slot (see :mod:`gsrmr_server.scheduling.link`)."""
        return float(required_power_w(bits, gain, slot_s, bandwidth_hz, noise_w))

    @classmethod
    def from_node_parameters(cls, node) -> LinkBudget:
        """Declare the link parameters on an rclpy node (descriptors, ranges) and build the model."""
        from gsrmr_common.ros_node import declare

        d = cls()
        bw = declare(node, "bandwidth_hz", d.bandwidth_hz, "Uplink bandwidth B [Hz]", min_value=1.0,
                     max_value=1e12, read_only=True)
        noise_dbm = declare(node, "noise_dbm", 10 * math.log10(d.noise_w * 1e3), "Noise power σ² [dBm]",
                            min_value=-250.0, max_value=100.0, read_only=True)
        pl = declare(node, "pathloss_db_at_1m", d.pathloss_db_at_1m, "Path loss ρ0 at 1 m [dB]",
                     min_value=-300.0, max_value=0.0, read_only=True)
        alpha = declare(node, "pathloss_exponent", d.pathloss_exponent, "Path-loss exponent α", min_value=0.0,
                        max_value=10.0, read_only=True)
        k = declare(node, "rician_k", d.rician_k, "Rician K-factor (LoS/NLoS power)", min_value=0.0,
                    max_value=1e6, read_only=True)
        server = list(declare(node, "server_position_m", list(d.server_position_m),
                              "Server (x, y) in map [m]", read_only=True))
        seed = declare(node, "channel_seed", d.channel_seed, "Seed of the per-slot fading realisation",
                       min_value=0, max_value=2**31 - 1, read_only=True)
        if len(server) != 2 or not all(math.isfinite(v) for v in server):
            raise ValueError("parameter server_position_m must be 2 finite numbers [x_m, y_m]")
        return cls(float(bw), 10 ** (noise_dbm / 10) / 1e3, float(pl), float(alpha), float(k),
                   (float(server[0]), float(server[1])), int(seed))
