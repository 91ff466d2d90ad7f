"""Which frames of a recording become training views: sharpness, blur rejection, spacing and thinning.

Pure numpy and OpenCV; every rule is deterministic (same input, same choice).

* **Sharpness** (:func:`laplacian_variance`): the variance of the Laplacian (3×3 aperture) of the frame's grey
  image (8-bit scale) — high for crisp edges, low for motion blur or defocus.
* **Blur** (:func:`blurred`): frame i is blurred when its sharpness is below ``ratio`` × the median sharpness of
  its neighbours, the up to ``window`` frames before and ``window`` after it in time order (itself excluded).
  The measure is relative because it depends on the scene; with fewer than two neighbours no frame is judged.
  ``ratio`` 0 turns the rule off.
* **Spacing** (:func:`spaced`): walking in time order, the first frame is kept, then a frame only when its
  camera moved at least ``min_translation_m`` from the last kept camera's position *or* turned at least
  ``min_rotation_deg`` from its orientation. Both 0 keep every frame.
* **Thinning** (:func:`thin_evenly`): at most ``max_frames`` of the survivors, at the evenly spread positions
  ``i·(n − 1)/(max_frames − 1)`` rounded half up, i = 0 … max_frames − 1 (the first and the last always among
  them).
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
    """For each frame (time order), whether it is blurred by the rule of the module docstring."""
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
