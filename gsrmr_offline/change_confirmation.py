"""What an update may learn from a received frame: a change seen in two rounds, never one seen once (pure NumPy plus the
renderer; no ROS). :func:`confirm_changes` keeps a changed cell only where a frame of another round confirms it and
replaces the others by the current model's render; the rule and why: docs/model_update.md, "3. Update". Units: colours
in [0, 1], distances in metres, angles in degrees, cameras in OpenCV axes (``DatasetFrame.camera``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
import math

import numpy as np

from gsrmr_common.nerfstudio import DatasetFrame
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render


@dataclass(frozen=True)
class ConfirmConfig:
    """How changes are found and confirmed (docs/model_update.md, "3. Update")."""

    cell_px: int = 8  # the cell size (pixels of the received frame)
    threshold: float = 0.08  # a cell is changed when its mean |received − render| exceeds this (colour in [0, 1])
    near_m: float = 0.3  # a confirming frame's camera centre is this close …
    near_deg: float = 30.0  # … and its optical axis this nearly the same
    dilate_cells: int = 1  # a carried cell centre may land this many cells from a changed cell

    def __post_init__(self) -> None:
        if self.cell_px < 1 or self.dilate_cells < 0:
            raise ValueError("confirm: cell_px ≥ 1 and dilate_cells ≥ 0")
        if not (math.isfinite(self.threshold) and self.threshold > 0):
            raise ValueError("confirm: threshold must be a finite number > 0")
        if not (self.near_m >= 0 and 0 <= self.near_deg <= 180):
            raise ValueError("confirm: near_m ≥ 0 and near_deg in [0, 180]")


@dataclass(frozen=True)
class Confirmation:
    """What :func:`confirm_changes` did: the training frames (unconfirmed cells replaced) and its counts."""

    frames: list[DatasetFrame]
    changed_cells: int  # over all frames
    confirmed_cells: int
    frames_with_changes: int
    cells: int  # all cells of all frames

    def summary(self) -> str:
        """One line for the update's log."""
        share = self.confirmed_cells / self.changed_cells if self.changed_cells else 1.0
        return (f"{self.changed_cells} of {self.cells} cells changed in {self.frames_with_changes} frames, "
                f"{self.confirmed_cells} confirmed by another round ({100 * share:.0f} %), the rest left to the "
                "current model")


def _cells(image_hw: np.ndarray, cell_px: int) -> np.ndarray:
    """Mean of an H×W array over ``cell_px`` blocks (edge blocks partial): ceil(H/c) × ceil(W/c)."""
    h, w = image_hw.shape
    hc, wc = -(-h // cell_px), -(-w // cell_px)
    padded = np.full((hc * cell_px, wc * cell_px), np.nan, np.float64)
    padded[:h, :w] = image_hw
    return np.nanmean(padded.reshape(hc, cell_px, wc, cell_px), axis=(1, 3))


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    """Binary dilation of a 2-D mask by a (2k + 1)² square."""
    if k <= 0:
        return mask.copy()
    out = np.zeros_like(mask)
    h, w = mask.shape
    padded = np.pad(mask, k)
    for dy in range(2 * k + 1):
        for dx in range(2 * k + 1):
            out |= padded[dy:dy + h, dx:dx + w]
    return out


def _near(frames: Sequence[DatasetFrame], near_m: float, near_deg: float) -> np.ndarray:
    """N×N: camera centres within ``near_m`` and optical axes within ``near_deg``."""
    centres = np.array([f.camera.center_world for f in frames])
    axes = np.array([f.camera.camera_to_world[:3, 2] for f in frames])
    close = np.linalg.norm(centres[:, None] - centres[None], axis=2) <= near_m
    return close & (axes @ axes.T >= math.cos(math.radians(near_deg)))


def confirm_changes(model: GaussianModel, frames: Sequence[DatasetFrame], rounds: Sequence[int],
                    background: Sequence[float], config: ConfirmConfig | None = None) -> Confirmation:
    """``frames`` (received, training) with every changed cell no frame of another round confirms replaced by
    ``model``'s render (docs/model_update.md, "3. Update"). ``rounds[i]``: the round frame ``i`` was received in.
    ``background``: the colour the model is rendered over (the composer's)."""
    cfg = config or ConfirmConfig()
    frames = list(frames)
    if len(rounds) != len(frames):
        raise ValueError(f"confirm: {len(frames)} frames but {len(rounds)} round indices")
    if not frames:
        return Confirmation([], 0, 0, 0, 0)
    bg = np.asarray(background, np.float32)
    renders, depths, changed = [], [], []
    for f in frames:
        out = render(model, f.camera, background=bg)
        rgb = np.clip(out.rgb, 0.0, 1.0)
        renders.append(rgb)
        depths.append(out.depth)
        diff = np.mean(np.abs(np.asarray(f.image, np.float32) - rgb), axis=2)
        changed.append(_cells(diff, cfg.cell_px) > cfg.threshold)
    reach = [_dilate(c, cfg.dilate_cells) for c in changed]
    near = _near(frames, cfg.near_m, cfg.near_deg)
    round_of = np.asarray(rounds)
    out_frames: list[DatasetFrame] = []
    changed_n = confirmed_n = with_changes = cells_n = 0
    for i, f in enumerate(frames):
        c = changed[i]
        cells_n += c.size
        if not c.any():
            out_frames.append(f)
            continue
        with_changes += 1
        ys, xs = np.nonzero(c)
        confirmed = np.zeros(ys.size, bool)
        others = np.nonzero(near[i] & (round_of != round_of[i]))[0]
        if others.size:
            centres = _cell_centres_world(f, depths[i], ys, xs, cfg.cell_px)
            for j in others:
                g = frames[j]
                uv, z = g.camera.project(centres)
                with np.errstate(invalid="ignore"):
                    cx, cy = np.floor(uv[:, 0] / cfg.cell_px), np.floor(uv[:, 1] / cfg.cell_px)
                ok = (z > 0) & np.isfinite(cx) & np.isfinite(cy)
                hc, wc = reach[j].shape
                ok &= (cx >= 0) & (cx < wc) & (cy >= 0) & (cy < hc)
                hit = np.zeros(ys.size, bool)
                hit[ok] = reach[j][cy[ok].astype(int), cx[ok].astype(int)]
                confirmed |= hit
        changed_n += ys.size
        confirmed_n += int(confirmed.sum())
        if confirmed.all():
            out_frames.append(f)
            continue
        unconfirmed = np.zeros_like(c)
        unconfirmed[ys[~confirmed], xs[~confirmed]] = True
        unconfirmed = _dilate(unconfirmed, 1) & ~_confirmed_mask(c.shape, ys[confirmed], xs[confirmed])
        pixels = np.kron(unconfirmed, np.ones((cfg.cell_px, cfg.cell_px), bool))[:f.camera.height, :f.camera.width]
        image = np.where(pixels[..., None], renders[i], np.asarray(f.image, np.float32)).astype(np.float32)
        out_frames.append(DatasetFrame(f.camera, image, f.depth_m, f.pose, f.file_path))
    return Confirmation(out_frames, changed_n, confirmed_n, with_changes, cells_n)


def _confirmed_mask(shape: tuple[int, int], ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    mask = np.zeros(shape, bool)
    mask[ys, xs] = True
    return mask


def _cell_centres_world(frame: DatasetFrame, depth_m: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                        cell_px: int) -> np.ndarray:
    """World points of the cells' centre pixels at the model's depth there (cells where the model has no depth:
    the median depth of the frame, else 2 m)."""
    cam = frame.camera
    k = cam.intrinsics
    py = np.minimum(ys * cell_px + cell_px // 2, cam.height - 1)
    px = np.minimum(xs * cell_px + cell_px // 2, cam.width - 1)
    z = depth_m[py, px].astype(np.float64)
    valid = depth_m[depth_m > 0]
    fallback = float(np.median(valid)) if valid.size else 2.0
    z = np.where(z > 0, z, fallback)
    x_cam = (px + 0.5 - k.cx) / k.fx * z
    y_cam = (py + 0.5 - k.cy) / k.fy * z
    pts_cam = np.stack([x_cam, y_cam, z], axis=1)
    c2w = cam.camera_to_world
    return pts_cam @ c2w[:3, :3].T + c2w[:3, 3]
