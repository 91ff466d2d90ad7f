"""The server's render intrinsics from the robot's ``uplink/camera_info`` (pure, no ROS): the adopt/refuse policy.

The first usable calibration starts the server's slot clock; a new one is adopted (from the next slot on) and
logged with how it differs; an unusable one (distortion, skew, no K: the pinhole renderer cannot match it) is
refused — one WARN per distinct problem — and the last usable one kept. :class:`RenderIntrinsics` holds that
state and says what to log; the node only converts the message and writes the log line.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from gsrmr_common.camera import Intrinsics

WAITING = "waiting for camera_info"


def describe(k: Intrinsics) -> str:
    """``W×H fx=… fy=… cx=… cy=…`` (pixels; OpenCV pixel centres, see :mod:`gsrmr_common.camera`)."""
    return f"{k.width}×{k.height} fx={k.fx:.3f} fy={k.fy:.3f} cx={k.cx:.3f} cy={k.cy:.3f}"


def intrinsics_mismatch(got: Intrinsics, want: Intrinsics, tol_px: float = 1e-3) -> str | None:
    """How ``got`` differs from ``want`` (image size exactly, fx, fy, cx, cy within ``tol_px`` pixels), or None."""
    if (got.width, got.height) != (want.width, want.height):
        return f"size {got.width}×{got.height} != {want.width}×{want.height}"
    diffs = [f"{name} {getattr(got, name):.3f} != {getattr(want, name):.3f}" for name in ("fx", "fy", "cx", "cy")
             if abs(getattr(got, name) - getattr(want, name)) > tol_px]
    return ", ".join(diffs) or None


@dataclass(frozen=True)
class LogLine:
    """A line the node logs: ``level`` is ``info`` or ``warning``."""

    level: str
    text: str

    def log_to(self, logger: Any) -> None:
        """Log the line on an rclpy logger at its level (rclpy: one severity per call site, hence two)."""
        if self.level == "warning":
            logger.warning(self.text)
        else:
            logger.info(self.text)


class RenderIntrinsics:
    """The intrinsics to render with and the status of the last ``camera_info`` (see the module docstring)."""

    def __init__(self) -> None:
        self.intrinsics: Intrinsics | None = None  # none until the first usable calibration
        self.status = WAITING  # describe() of the last usable one, or "unusable: <why>"
        self._warned: str | None = None  # the last problem a WARN was logged for

    def offer(self, got: Intrinsics | None, problem: str | None = None) -> LogLine | None:
        """A calibration arrived: ``got`` when usable, else ``problem`` (why not). What to log, if anything."""
        if got is None:
            self.status = f"unusable: {problem}"
            if problem == self._warned:
                return None
            self._warned = problem
            kept = "no intrinsics yet" if self.intrinsics is None else "keeping " + describe(self.intrinsics)
            return LogLine("warning", f"camera_info from the robot refused ({kept}): {problem}")
        previous, self.status = self.intrinsics, describe(got)
        if got == previous:
            return None
        self.intrinsics = got
        change = "" if previous is None else f" (was {describe(previous)}: {intrinsics_mismatch(got, previous)})"
        return LogLine("info", f"render intrinsics from camera_info: {describe(got)}{change}")

    def problems(self) -> list[str]:
        """What ``/diagnostics`` warns about: no intrinsics yet, the last calibration refused."""
        out = [WAITING] if self.intrinsics is None else []
        if self.status.startswith("unusable"):
            out.append("camera_info refused")
        return out
