"""The uplink's parameters as ``config/link.yaml`` names them, and the :class:`LinkBudget` they describe (pure, no ROS).

:class:`LinkParameters` is the one table of those names, defaults, descriptions and ranges; every reader goes through
it (docs/architecture.md, "One pipeline each": the channel).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

from gsrmr_common.link_model import LinkBudget
from gsrmr_common.node_params import NodeParameters, ros_parameter


def dbm_to_w(power_dbm: float) -> float:
    """Power in dBm → watts."""
    return 10 ** (power_dbm / 10) / 1e3


def w_to_dbm(power_w: float) -> float:
    """Power in watts → dBm."""
    return 10 * math.log10(power_w * 1e3)


_DEFAULT = LinkBudget()


@dataclass(frozen=True)
class LinkParameters(NodeParameters):
    """The parameters of ``config/link.yaml`` (loaded into the robot, the scheduler, the server and the
    simulated radio: they cannot disagree), all read-only; defaults are :class:`LinkBudget`'s."""

    bandwidth_hz: float = ros_parameter(_DEFAULT.bandwidth_hz, "Uplink bandwidth B [Hz]", min_value=1.0,
                                        max_value=1e12, read_only=True)
    noise_dbm: float = ros_parameter(w_to_dbm(_DEFAULT.noise_w), "Noise power σ² [dBm]", min_value=-250.0,
                                     max_value=100.0, read_only=True)
    pathloss_db_at_1m: float = ros_parameter(_DEFAULT.pathloss_db_at_1m, "Path loss ρ0 at 1 m [dB]",
                                             min_value=-300.0, max_value=0.0, read_only=True)
    pathloss_exponent: float = ros_parameter(_DEFAULT.pathloss_exponent, "Path-loss exponent α", min_value=0.0,
                                             max_value=10.0, read_only=True)
    rician_k: float = ros_parameter(_DEFAULT.rician_k, "Rician K-factor (LoS/NLoS power)", min_value=0.0,
                                    max_value=1e6, read_only=True)
    server_position_m: tuple[float, ...] = ros_parameter(_DEFAULT.server_position_m, "Server (x, y) in map [m]",
                                                         read_only=True)
    channel_seed: int = ros_parameter(_DEFAULT.channel_seed, "Seed of the per-slot fading realisation",
                                      min_value=0, max_value=2**31 - 1, read_only=True)

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """``server_position_m`` is 2 finite numbers."""
        if name == "server_position_m" and (len(value) != 2 or not all(math.isfinite(v) for v in value)):
            return "server_position_m must be 2 finite numbers [x_m, y_m]"
        return None

    def budget(self) -> LinkBudget:
        """The :class:`LinkBudget` these parameters describe (SI units)."""
        x_m, y_m = self.server_position_m
        return LinkBudget(self.bandwidth_hz, dbm_to_w(self.noise_dbm), self.pathloss_db_at_1m,
                          self.pathloss_exponent, self.rician_k, (x_m, y_m), self.channel_seed)
