"""Seeded Rician uplink channel of the paper (Sec. V, eq. (ht)); pure numpy.

``h_t = sqrt(ρ0·d_t^−α)·( sqrt(K/(1+K))·exp(−jπ·sin ψ_t) + sqrt(1/(1+K))·g_t^NLOS )`` with ``ψ_t ~ U(−π, π)``,
``g^NLOS ~ CN(0, 1)``; the gain used by the scheduler is ``|h_t|²`` (dimensionless). ``d_t`` is the
robot–server distance in metres (map frame, any consistent planar or 3-D coordinates).
Paper defaults: ρ0 = −30 dB at 1 m, α = 3, K = 1, d ≈ 10 m.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

# The paper's channel statistics (Section V): the defaults of every model of the uplink channel.
PATHLOSS_DB_AT_1M = -30.0  # ρ0
PATHLOSS_EXPONENT = 3.0  # α
RICIAN_K = 1.0  # K (LoS/NLoS power)


@dataclass
class ChannelModel:
    """Rician fading with distance path loss; ``seed`` makes every draw reproducible."""

    rho0_db: float = PATHLOSS_DB_AT_1M
    alpha: float = PATHLOSS_EXPONENT
    k_factor: float = RICIAN_K
    seed: int | None = 0
    rng: np.random.Generator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not math.isfinite(self.rho0_db):
            raise ValueError("rho0_db must be finite")
        if not (math.isfinite(self.alpha) and self.alpha >= 0):
            raise ValueError("alpha must be a finite number >= 0")
        if not (math.isfinite(self.k_factor) and self.k_factor >= 0):
            raise ValueError("k_factor must be a finite number >= 0")
        self.rng = np.random.default_rng(self.seed)

    def pathloss(self, distances_m: np.ndarray) -> np.ndarray:
        """Large-scale power gain ``ρ0·d^−α`` (dimensionless)."""
        d = np.asarray(distances_m, dtype=np.float64)
        if np.any(~np.isfinite(d)) or np.any(d <= 0):
            raise ValueError("distances_m must be finite and > 0")
        return 10.0 ** (self.rho0_db / 10.0) * d ** (-self.alpha)

    def coefficients(self, distances_m: np.ndarray) -> np.ndarray:
        """Complex channel coefficients h_t (complex128), one draw per distance."""
        pl = self.pathloss(distances_m)
        n = pl.size
        psi = self.rng.uniform(-math.pi, math.pi, n)
        los = np.exp(-1j * math.pi * np.sin(psi))
        nlos = (self.rng.standard_normal(n) + 1j * self.rng.standard_normal(n)) / math.sqrt(2.0)
        k = self.k_factor
        small = math.sqrt(k / (1 + k)) * los + math.sqrt(1 / (1 + k)) * nlos
        return np.sqrt(pl).reshape(np.shape(distances_m)) * small.reshape(np.shape(distances_m))

    def gains(self, distances_m: np.ndarray) -> np.ndarray:
        """Channel power gains ``|h_t|²`` (float64) for a sequence of robot–server distances (m)."""
        return np.abs(self.coefficients(distances_m)) ** 2

    def gains_from_positions(self, positions_m: np.ndarray, server_m: np.ndarray) -> np.ndarray:
        """Gains for robot positions (N×2 or N×3, metres) and one server position in the same frame."""
        pos = np.atleast_2d(np.asarray(positions_m, dtype=np.float64))
        srv = np.asarray(server_m, dtype=np.float64)
        if pos.shape[1] != srv.shape[-1]:
            raise ValueError("positions_m and server_m must have the same dimension (2 or 3)")
        return self.gains(np.linalg.norm(pos - srv, axis=1))


def rician_power_samples(k_factor: float, n: int = 4096, seed: int = 0) -> np.ndarray:
    """Sorted draws of the Rician small-scale power |h|² (factor ``k_factor``), normalised to mean 1 — the
    channel model above at unit path loss (the server's in-slot rule prices its fades on them)."""
    p = np.sort(ChannelModel(rho0_db=0.0, alpha=0.0, k_factor=float(k_factor), seed=seed).gains(np.ones(n)))
    return p / p.mean()


def paper_route_distances(slots: int, server_m: tuple[float, float] = (10.0, 0.0), radius_m: float = 1.5) -> np.ndarray:
    """Robot–server distances (m) for a robot lapping a circle of ``radius_m`` about the map origin once in
    ``slots`` slots, the server at ``server_m`` (the paper's ~10 m sandbox geometry)."""
    ang = 2 * math.pi * np.arange(slots) / max(slots, 1)
    pos = np.stack([radius_m * np.cos(ang), radius_m * np.sin(ang)], axis=1)
    return np.linalg.norm(pos - np.asarray(server_m), axis=1)
