"""The GSCLO problem P_GS (paper Sec. III) and the schedule every method returns (pure, no rclpy).

:class:`Problem` states P_GS and its units; the knapsack view and the log-domain rules: docs/scheduling.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
import math
from typing import Any

import numpy as np

from gsrmr_common import link_model as link
from gsrmr_common.wire import Delivery

#: Per-slot delivery outcome labels (the wire contract's :class:`~gsrmr_common.wire.Delivery`).
IMAGE, KEY, NONE = Delivery.IMAGE, Delivery.KEY, Delivery.NONE


class ProblemError(ValueError):
    """Invalid problem input; ``field`` names the offending input key."""

    def __init__(self, field_name: str, message: str) -> None:
        super().__init__(f"{field_name}: {message}")
        self.field = field_name


def _positive(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ProblemError(name, f"must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ProblemError(name, f"must be a positive finite number, got {value!r}")
    return v


def _array(name: str, value: Any) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ProblemError(name, "must be a list of numbers") from None
    if arr.ndim != 1 or arr.size == 0:
        raise ProblemError(name, "must be a non-empty 1-D list of numbers")
    if not np.all(np.isfinite(arr)):
        raise ProblemError(name, f"contains NaN or inf (first at index {int(np.argmin(np.isfinite(arr)))})")
    if np.any(arr < 0):
        raise ProblemError(name, f"contains a negative value (first at index {int(np.argmax(arr < 0))})")
    return arr


@dataclass
class Problem:
    """One P_GS instance: T slots of τ = ``slot_s`` seconds, validated on construction.

    In slot t, ``x_t = 1`` uploads an image of I = ``image_bits``, ``x_t = 0`` a pose key of S = ``pose_bits``, at a
    power p_t (W). P_GS minimises the energy τ·Σ p_t (J) subject to τ·B·log2(1 + g_t·p_t/σ²) ≥ x_t·I + (1 − x_t)·S,
    Σ L_t·(1 − x_t) ≤ T·L_th, p ≥ 0 and x ∈ {0, 1} (docs/scheduling.md, "Units and conventions").

    Args:
        channel_gain: g_t per slot: the dimensionless power gain ``|h_t|²`` (T values ≥ 0).
        gs_loss: L_t per slot: the MR loss added when slot t is composed from the GS render instead of the image
            (dimensionless, the scale of ``loss_threshold``; T values ≥ 0).
        loss_threshold: L_th, the mean MR loss per slot allowed (≥ 0).
        slot_s: τ, the slot length (s).
        image_bits: I, the image's payload (bits; more than ``pose_bits``).
        pose_bits: S, the pose key's payload (bits).
        bandwidth_hz: B, the bandwidth (Hz).
        noise_w: σ², the noise and interference power (W).
        energy_budget_j: the energy (J) the rate-allocation baselines ``maxrate`` and ``fairness`` spend; None:
            another method's energy (:func:`gsrmr_scheduler.solve.solve`, ``budget_from``).

    Raises:
        ProblemError: an input that is not a finite number (or list of them) in its range, gain and loss lists of
            different lengths, or ``image_bits`` ≤ ``pose_bits``; its ``field`` names the input.

    Example:
        Three slots; a key instead of an image saves :attr:`saving_j` joules per slot::

            problem = Problem(channel_gain=[2e-6, 5e-7, 1e-6], gs_loss=[0.02, 0.05, 0.01], loss_threshold=0.02)
            problem.saving_j, problem.loss_budget  # J per slot; T·L_th = 0.06
    """

    channel_gain: np.ndarray
    gs_loss: np.ndarray
    loss_threshold: float
    slot_s: float = link.SLOT_S
    image_bits: float = link.IMAGE_BITS
    pose_bits: float = link.KEY_BITS
    bandwidth_hz: float = link.BANDWIDTH_HZ
    noise_w: float = link.NOISE_W
    energy_budget_j: float | None = None

    def __post_init__(self) -> None:
        self.slot_s = _positive("slot_s", self.slot_s)
        self.image_bits = _positive("image_bits", self.image_bits)
        self.pose_bits = _positive("pose_bits", self.pose_bits)
        if self.image_bits <= self.pose_bits:
            raise ProblemError("image_bits", "must exceed pose_bits (an image is larger than a pose key)")
        self.bandwidth_hz = _positive("bandwidth_hz", self.bandwidth_hz)
        self.noise_w = _positive("noise_w", self.noise_w)
        self.channel_gain = _array("channel_gain", self.channel_gain)
        self.gs_loss = _array("gs_loss", self.gs_loss)
        if self.channel_gain.size != self.gs_loss.size:
            raise ProblemError("gs_loss", f"has {self.gs_loss.size} values but channel_gain has "
                               f"{self.channel_gain.size}")
        try:
            lth = float(self.loss_threshold)
        except (TypeError, ValueError):
            raise ProblemError("loss_threshold", "must be a number") from None
        if not math.isfinite(lth) or lth < 0:
            raise ProblemError("loss_threshold", f"must be a finite number >= 0, got {self.loss_threshold!r}")
        self.loss_threshold = lth
        if self.energy_budget_j is not None:
            try:
                eb = float(self.energy_budget_j)
            except (TypeError, ValueError):
                raise ProblemError("energy_budget_j", "must be a number") from None
            if not math.isfinite(eb) or eb < 0:
                raise ProblemError("energy_budget_j", f"must be a finite number >= 0, got {self.energy_budget_j!r}")
            self.energy_budget_j = eb

    # ---- construction -------------------------------------------------------------------------
    REQUIRED = ("slot_s", "image_bits", "pose_bits", "bandwidth_hz", "noise_w", "channel_gain", "gs_loss",
                "loss_threshold")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Problem:
        """Build from the CLI/JSON keys; raises :class:`ProblemError` naming the first bad key."""
        if not isinstance(data, dict):
            raise ProblemError("problem", "must be a JSON object")
        for key in cls.REQUIRED:
            if key not in data:
                raise ProblemError(key, "missing")
        for key in data:
            if key not in (*cls.REQUIRED, "energy_budget_j"):
                raise ProblemError(key, "unknown key")
        for key in ("channel_gain", "gs_loss"):
            if not isinstance(data[key], list | tuple):
                raise ProblemError(key, "must be a list of numbers")
            if any(isinstance(v, bool) or not isinstance(v, int | float) for v in data[key]):
                raise ProblemError(key, "must contain only numbers")
        for key in ("slot_s", "image_bits", "pose_bits", "bandwidth_hz", "noise_w", "loss_threshold"):
            if isinstance(data[key], bool) or not isinstance(data[key], int | float):
                raise ProblemError(key, f"must be a number, got {data[key]!r}")
        return cls(channel_gain=data["channel_gain"], gs_loss=data["gs_loss"],
                   loss_threshold=data["loss_threshold"], slot_s=data["slot_s"], image_bits=data["image_bits"],
                   pose_bits=data["pose_bits"], bandwidth_hz=data["bandwidth_hz"], noise_w=data["noise_w"],
                   energy_budget_j=data.get("energy_budget_j"))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict with the CLI keys."""
        out: dict[str, Any] = {k: getattr(self, k) for k in self.REQUIRED}
        out["channel_gain"] = self.channel_gain.tolist()
        out["gs_loss"] = self.gs_loss.tolist()
        if self.energy_budget_j is not None:
            out["energy_budget_j"] = self.energy_budget_j
        return out

    # ---- derived quantities ---------------------------------------------------------------------
    @property
    def slots(self) -> int:
        """Number of slots T."""
        return int(self.gs_loss.size)

    @property
    def loss_budget(self) -> float:
        """Right-hand side of the loss constraint in sum form: ``T·L_th``."""
        return self.slots * self.loss_threshold

    @cached_property
    def log_energy_image_j(self) -> np.ndarray:
        """ln of the per-slot energy (J) of an image slot, ``ln(τ·p_img)``; +inf on a dead channel."""
        return math.log(self.slot_s) + np.asarray(link.log_required_power_w(
            self.image_bits, self.channel_gain, self.slot_s, self.bandwidth_hz, self.noise_w))

    @cached_property
    def log_energy_key_j(self) -> np.ndarray:
        """ln of the per-slot energy (J) of a pose-key slot."""
        return math.log(self.slot_s) + np.asarray(link.log_required_power_w(
            self.pose_bits, self.channel_gain, self.slot_s, self.bandwidth_hz, self.noise_w))

    @cached_property
    def _log_cap(self) -> float:
        # A slot's energy is kept only if T of them still sum to a finite float64 (≤ 1e300 J).
        return link.LOG_FLOAT_MAX - math.log(self.slots)

    @cached_property
    def image_ok(self) -> np.ndarray:
        """Slots that can carry an image with a representable power (False: must be a key or nothing)."""
        a_img = link.snr_exponent(self.image_bits, self.slot_s, self.bandwidth_hz)
        return (self.channel_gain > 0) & (a_img < 700.0) & (self.log_energy_image_j <= self._log_cap)

    @cached_property
    def key_ok(self) -> np.ndarray:
        """Slots that can carry a pose key with a representable power."""
        a_key = link.snr_exponent(self.pose_bits, self.slot_s, self.bandwidth_hz)
        return (self.channel_gain > 0) & (a_key < 700.0) & (self.log_energy_key_j <= self._log_cap)

    @cached_property
    def energy_image_j(self) -> np.ndarray:
        """Per-slot image energy τ·p_img (J); 0 where :attr:`image_ok` is False (never used there)."""
        return np.where(self.image_ok, np.exp(np.where(self.image_ok, self.log_energy_image_j, 0.0)), 0.0)

    @cached_property
    def energy_key_j(self) -> np.ndarray:
        """Per-slot key energy τ·p_key (J); 0 where :attr:`key_ok` is False."""
        return np.where(self.key_ok, np.exp(np.where(self.key_ok, self.log_energy_key_j, 0.0)), 0.0)

    @cached_property
    def saving_j(self) -> np.ndarray:
        """Energy saved by a key instead of an image, ``τ(σ²/g)(2^{I/τB} − 2^{S/τB})`` (J, > 0 where both ok).

        Computed as ``E_key·(e^{a_I} − e^{a_S})/(e^{a_S} − 1)`` in the log domain, no cancellation.
        """
        a_i = link.snr_exponent(self.image_bits, self.slot_s, self.bandwidth_hz)
        a_s = link.snr_exponent(self.pose_bits, self.slot_s, self.bandwidth_hz)
        # τσ²/g · e^{a_S} · expm1(a_I − a_S)
        log_c = math.log(self.slot_s * self.noise_w) - np.log(np.where(self.channel_gain > 0, self.channel_gain, 1.0))
        log_v = log_c + a_s + float(link.log_expm1(a_i - a_s))
        ok = self.image_ok & self.key_ok
        return np.where(ok, np.exp(np.where(ok, log_v, 0.0)), 0.0)

    def power_w(self, x: np.ndarray) -> np.ndarray:
        """Closed-form minimum power per slot for binary ``x`` (0 where the slot cannot carry its payload)."""
        x = np.asarray(x)
        e = np.where(x == 1, self.energy_image_j, self.energy_key_j)
        return e / self.slot_s

    def loss_sum(self, x: np.ndarray) -> float:
        """``Σ L_t·(1 − x_t)`` (exactly rounded sum)."""
        x = np.asarray(x)
        return math.fsum(self.gs_loss[x == 0].tolist())

    def budget_ok(self, x: np.ndarray) -> bool:
        """Whether binary ``x`` meets ``Σ L_t(1−x_t) ≤ T·L_th`` (the single feasibility test everyone uses)."""
        return self.loss_sum(x) <= self.loss_budget


@dataclass
class Schedule:
    """The result of one method: per-slot decision and power, and diagnostics.

    Args:
        method: the method's name (a key of :data:`gsrmr_scheduler.solve.METHODS`).
        x: per slot 1 = image, 0 = pose key (int8, T values).
        power_w: the transmit power allocated per slot (W, float64; 0 W where the slot delivers nothing).
        energy_j: the energy τ·Σ p_t (J).
        mean_loss: (1/T)·Σ of the MR loss the slots leave: L_t for a key, 0 for an image, an undelivered slot as
            the method charges it (dimensionless).
        feasible: every slot delivers what x says and the loss budget holds (``maxrate`` and ``fairness``: the
            mean loss ≤ L_th and the energy within their budget).
        solve_time_s: the solve's wall-clock time (s).
        iterations: what the method counts as its iterations or steps.
        history: per-iteration records (``apo``), else None.
        optimality_gap: ``exact`` only: the certified relative energy gap (E − E_lb)/E_lb (0: optimal); else None.
        delivered: per slot ``"image"``, ``"key"`` or ``"none"``.
        notes: one-line remarks (why infeasible, a repair, where the budget came from).
        extras: method-specific values (``apo``'s ``paper`` result, ``exact``'s ``energy_lower_bound_j`` …).

    Example:
        ::

            sched = solve(problem, "exact")  # gsrmr_scheduler.solve.solve
            sched.x, sched.power_w, sched.energy_j
            json.dumps(sched.to_json())      # the CLI's output
    """

    method: str
    x: np.ndarray
    power_w: np.ndarray
    energy_j: float
    mean_loss: float
    feasible: bool
    solve_time_s: float = 0.0
    iterations: int = 0
    history: list[dict[str, Any]] | None = None
    optimality_gap: float | None = None
    delivered: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    extras: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict: the CLI's output keys (docs/scheduling.md, "CLI")."""
        return {
            "method": self.method,
            "x": [int(v) for v in self.x],
            "power_w": [float(v) for v in self.power_w],
            "energy_j": float(self.energy_j),
            "mean_loss": float(self.mean_loss),
            "feasible": bool(self.feasible),
            "solve_time_s": float(self.solve_time_s),
            "iterations": int(self.iterations),
            "history": self.history,
            "optimality_gap": None if self.optimality_gap is None else float(self.optimality_gap),
            "delivered": list(self.delivered),
            "notes": list(self.notes),
            "extras": {k: (float(v) if isinstance(v, np.floating) else v) for k, v in self.extras.items()},
        }


def infeasibility_reason(problem: Problem) -> str | None:
    """Why no binary schedule can meet P_GS (None when one exists)."""
    dead = ~problem.key_ok
    if np.any(dead):
        t = int(np.argmax(dead))
        return (f"{int(dead.sum())} slot(s) cannot carry even a pose key (first t={t}: gain "
                f"{problem.channel_gain[t]:.3g}, power not representable)")
    forced = ~problem.image_ok
    forced_loss = math.fsum(problem.gs_loss[forced].tolist())
    if forced_loss > problem.loss_budget:
        return (f"{int(forced.sum())} slot(s) cannot carry an image (2^(I/(tau*B)) or the power overflows "
                f"float64) and their GS loss {forced_loss:.6g} exceeds the budget T*L_th = {problem.loss_budget:.6g}")
    return None


def schedule_from_x(problem: Problem, x: np.ndarray, method: str, **kwargs: Any) -> Schedule:
    """Binary schedule with closed-form powers; slots that cannot carry their payload get 0 W and ``none``.

    ``feasible`` is True only if every slot delivers what ``x`` says and the loss budget holds.
    Undelivered slots are charged their GS loss ``L_t`` (as a key would be) in ``mean_loss``.
    """
    x = np.asarray(x, dtype=np.int8).copy()
    ok = np.where(x == 1, problem.image_ok, problem.key_ok)
    power = np.where(ok, problem.power_w(x), 0.0)
    delivered = np.where(~ok, NONE, np.where(x == 1, IMAGE, KEY))
    loss = problem.loss_sum(x) + math.fsum(problem.gs_loss[(~ok) & (x == 1)].tolist())
    notes = list(kwargs.pop("notes", []))
    feasible = bool(np.all(ok)) and problem.budget_ok(x)
    if not np.all(ok):
        notes.append(f"{int((~ok).sum())} slot(s) cannot carry their scheduled payload (power not representable "
                     "or gain 0); they get 0 W and deliver nothing")
    if not problem.budget_ok(x):
        notes.append("loss budget violated")
    return Schedule(method=method, x=x, power_w=power.astype(np.float64), energy_j=link.energy_j(power, problem.slot_s),
                    mean_loss=loss / problem.slots, feasible=feasible, delivered=delivered.tolist(), notes=notes,
                    **kwargs)
