"""Which frames of a recording become training views (pure numpy and OpenCV; deterministic): sharpness
(:func:`laplacian_variance`), blur rejection (:func:`blurred`), spacing (:func:`spaced`) and even thinning
(:func:`thin_evenly`), by the rules of docs/dataset_tool.md, "Keyframes".
"""

from __future__ import annotations

from collections.abc import Sequence
import math

import cv2
import numpy as np

from gsrmr_common.tf_buffer import rotation_angle_rad


def laplacian_variance(rgb_or_grey: np.ndarray) -> float:
    """Variance of the Laplacian of the frame's grey image (``uint8`` RGB H×W×3, or grey H×W), in 8-bit units²."""
    img = np.asarray(rgb_or_grey)
    grey = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    return float(cv2.Laplacian(grey, cv2.CV_64F, ksize=1).var())


def blurred(sharpness: Sequence[float], window: int, ratio: float) -> list[bool]:
    """For each frame (time order), whether it is blurred: its sharpness below ``ratio`` × the median of its
    neighbours' (up to ``window`` frames on each side, itself excluded); not judged with fewer than two neighbours;
    ``ratio`` 0 turns the rule off."""
    values = np.asarray(sharpness, dtype=np.float64)
    out = [False] * len(values)
    if ratio <= 0.0 or window < 1:
        return out
    for i in range(len(values)):
        lo, hi = max(0, i - window), min(len(values), i + window + 1)
        neighbours = np.concatenate([values[lo:i], values[i + 1:hi]])
        if len(neighbours) >= 2:
            out[i] = bool(values[i] < ratio * float(np.median(neighbours)))
    return out


def spaced(camera_to_world: Sequence[np.ndarray], min_translation_m: float, min_rotation_deg: float) -> list[bool]:
    """For each camera pose (4×4 camera→world, time order), whether the spacing rule keeps it."""
    keep: list[bool] = []
    last: np.ndarray | None = None
    min_rotation_rad = math.radians(min_rotation_deg)
    for pose in camera_to_world:
        pose = np.asarray(pose, dtype=np.float64)
        if last is None:
            ok = True
        else:
            moved_m = float(np.linalg.norm(pose[:3, 3] - last[:3, 3]))
            turned_rad = rotation_angle_rad(last[:3, :3].T @ pose[:3, :3])
            ok = (min_translation_m <= 0.0 and min_rotation_deg <= 0.0) or moved_m >= min_translation_m > 0.0 \
                or turned_rad >= min_rotation_rad > 0.0
        keep.append(ok)
        if ok:
            last = pose
    return keep


def thin_evenly(count: int, max_frames: int | None) -> list[int]:
    """Indices (0 … count − 1, ascending) of at most ``max_frames`` evenly spread items (all when ``None``)."""
    if max_frames is None or count <= max_frames:
        return list(range(count))
    if max_frames < 1:
        return []
    if max_frames == 1:
        return [0]
    # round(i·(count − 1)/(max_frames − 1)) half up, in integers (exact)
    return sorted({(2 * i * (count - 1) + max_frames - 1) // (2 * (max_frames - 1)) for i in range(max_frames)})
