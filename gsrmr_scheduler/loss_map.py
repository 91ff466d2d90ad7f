"""Loss map over robot poses: the MR loss L_t of the GS render where the robot is, learned online (pure Python/numpy).

Poses are (a_m, b_m, theta_rad) in ``map`` (θ = 0 faces +x); losses are MR losses against the camera's frame. The
grid, how it predicts, forgets and bounds a sample: docs/scheduling.md, "The loss map: grid, prediction, bounds".
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import math
from pathlib import Path

import numpy as np


@dataclass
class _Cell:
    mean: float
    count: int


@dataclass
class LossMap:
    """Grid of measured MR losses over (a_m, b_m, heading sector)."""

    cell_m: float = 0.25
    heading_bins: int = 8
    radius_m: float = 0.6
    prior: float = 0.05
    forgetting: float = 0.5
    cells: dict[tuple[int, int, int], _Cell] = field(default_factory=dict)
    outlier_factor: float = 20.0  # a sample counts at most this factor away from its cell's mean
    image_loss: float | None = None  # mean MR loss an image slot leaves (its JPEG), where it was measured
    sample_offset: float | None = None  # mean (server's loss sample − loss against the frame), where measured

    def __post_init__(self) -> None:
        if not (self.cell_m > 0 and math.isfinite(self.cell_m)):
            raise ValueError("loss map: cell_m must be > 0")
        if self.heading_bins < 1:
            raise ValueError("loss map: heading_bins must be >= 1")
        if not (0 < self.forgetting <= 1):
            raise ValueError("loss map: forgetting must be in (0, 1]")
        if not (self.prior >= 0 and math.isfinite(self.prior)):
            raise ValueError("loss map: prior must be a finite loss >= 0")
        if self.image_loss is not None and not (self.image_loss >= 0 and math.isfinite(self.image_loss)):
            raise ValueError("loss map: image_loss must be a finite loss >= 0")
        if self.sample_offset is not None and not (math.isfinite(self.sample_offset) and
                                                   abs(self.sample_offset) <= 1.0):
            raise ValueError("loss map: sample_offset must be a finite loss difference in [-1, 1]")
        if not (self.outlier_factor >= 1 and math.isfinite(self.outlier_factor)):
            raise ValueError("loss map: outlier_factor must be a finite factor >= 1")

    def key(self, a_m: float, b_m: float, theta_rad: float) -> tuple[int, int, int]:
        """Grid cell of a pose."""
        sector = 2 * math.pi / self.heading_bins
        h = int(math.floor(((theta_rad + 0.5 * sector) % (2 * math.pi)) / sector)) % self.heading_bins
        return (int(math.floor(a_m / self.cell_m)), int(math.floor(b_m / self.cell_m)), h)

    def add(self, a_m: float, b_m: float, theta_rad: float, loss: float) -> None:
        """Record a measured loss at a pose (non-finite values are ignored)."""
        if not all(math.isfinite(v) for v in (a_m, b_m, theta_rad, loss)) or loss < 0:
            return
        k = self.key(a_m, b_m, theta_rad)
        cell = self.cells.get(k)
        if cell is None:
            self.cells[k] = _Cell(loss, 1)
            return
        cell.count += 1
        w = max(1.0 / cell.count, self.forgetting)
        bounded = min(max(loss, cell.mean / self.outlier_factor), max(cell.mean, 1e-3) * self.outlier_factor)
        cell.mean += w * (bounded - cell.mean)

    def predict(self, a_m: float, b_m: float, theta_rad: float) -> float:
        """Predicted MR loss at a pose."""
        if not all(math.isfinite(v) for v in (a_m, b_m, theta_rad)):
            return self.prior
        k = self.key(a_m, b_m, theta_rad)
        cell = self.cells.get(k)
        if cell is not None:
            return cell.mean
        reach = int(math.ceil(self.radius_m / self.cell_m))
        num = den = 0.0
        for di in range(-reach, reach + 1):
            for dj in range(-reach, reach + 1):
                other = self.cells.get((k[0] + di, k[1] + dj, k[2]))
                if other is None:
                    continue
                dist = self.cell_m * math.hypot(di, dj)
                if dist > self.radius_m:
                    continue
                w = 1.0 / (dist + 1e-3)
                num += w * other.mean
                den += w
        return num / den if den > 0 else self.prior

    def predict_many(self, poses: np.ndarray) -> np.ndarray:
        """Predicted losses for an N×3 array of poses (a_m, b_m, theta_rad)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        return np.array([self.predict(*p) for p in poses], dtype=np.float64)

    def to_json(self) -> dict:
        """JSON-serialisable form."""
        out = {"cell_m": self.cell_m, "heading_bins": self.heading_bins, "radius_m": self.radius_m,
               "prior": self.prior, "forgetting": self.forgetting,
               "cells": [[*k, c.mean, c.count] for k, c in sorted(self.cells.items())]}
        if self.image_loss is not None:
            out["image_loss"] = self.image_loss
        if self.sample_offset is not None:
            out["sample_offset"] = self.sample_offset
        return out

    @classmethod
    def from_json(cls, data: dict) -> LossMap:
        """Inverse of :meth:`to_json`."""
        image_loss, offset = data.get("image_loss"), data.get("sample_offset")
        out = cls(float(data["cell_m"]), int(data["heading_bins"]), float(data["radius_m"]),
                  float(data["prior"]), float(data["forgetting"]),
                  image_loss=None if image_loss is None else float(image_loss),
                  sample_offset=None if offset is None else float(offset))
        for i, j, h, mean, count in data["cells"]:
            if math.isfinite(mean) and mean >= 0:
                out.cells[(int(i), int(j), int(h))] = _Cell(float(mean), int(count))
        return out

    def save(self, path: str | Path) -> None:
        """Write as JSON (atomically: temp file + rename)."""
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_json()))
        tmp.replace(path)

    @classmethod
    def load(cls, path: str | Path) -> LossMap:
        """Read a map written by :meth:`save`."""
        return cls.from_json(json.loads(Path(path).read_text()))
