"""The project's shared test data, found through ``$GSRMR_DATA_DIR`` (the Makefile points it at
``../shared/data`` where that exists): the garden scene of Mip-NeRF 360 (``test_garden.npz``: coloured points and
3 real cameras), as gsplat's tests use it."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gsrmr_common.camera import Camera, Intrinsics
from gsrmr_splat.model import GaussianModel, opacity_logit
from gsrmr_splat.sh import num_coeffs, rgb_to_sh0

DATA_DIR_ENV = "GSRMR_DATA_DIR"
GARDEN_NPZ = "test_garden.npz"
GARDEN_SEED = 42
GARDEN_BOUND_M = 2.0


def data_file(name: str) -> Path:
    """The shared data file ``name`` in ``$GSRMR_DATA_DIR``.

    Raises:
        FileNotFoundError: the variable is unset or the file is not in that folder.
    """
    folder = os.environ.get(DATA_DIR_ENV)
    if not folder:
        raise FileNotFoundError(f"{name}: set {DATA_DIR_ENV} to the folder of the shared data (make does)")
    path = Path(folder) / name
    if not path.is_file():
        raise FileNotFoundError(f"{name} is not in {DATA_DIR_ENV}={folder}")
    return path


def load_garden(path: str | Path | None = None) -> tuple[np.ndarray, np.ndarray, list[Camera]]:
    """The garden test data.

    Returns:
        N×3 points [m], N×3 uint8 colours, the 3 real 648×420 cameras (OpenCV axes, world → camera).
    """
    data = np.load(str(path or data_file(GARDEN_NPZ)))
    width, height = int(data["width"]), int(data["height"])
    cams = [Camera(Intrinsics.from_k(k, width, height), vm.astype(np.float64))
            for k, vm in zip(data["Ks"], data["viewmats"], strict=True)]
    return data["means3d"].astype(np.float32), data["colors"], cams


def garden_model(path: str | Path | None = None, seed: int = GARDEN_SEED, degree: int = 0) -> GaussianModel:
    """The garden test model, as gsplat's tests build it, with a fixed seed.

    Points inside [−2, 2]³; scales ~ U(0, 0.02) m; random unit quaternions (normalised Gaussian
    4-vectors); opacities ~ U(0, 1); colours from the points (SH degree 0; higher degrees padded
    with zeros).
    """
    pts, colors, _ = load_garden(path)
    keep = np.all(np.abs(pts) <= GARDEN_BOUND_M, axis=1)
    pts, colors = pts[keep], colors[keep]
    rng = np.random.default_rng(seed)
    n = pts.shape[0]
    scales = rng.uniform(0.0, 0.02, size=(n, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    opac = rng.uniform(0.0, 1.0, size=n)
    sh = np.zeros((n, num_coeffs(degree), 3))
    sh[:, 0] = rgb_to_sh0(colors.astype(np.float64) / 255.0)
    return GaussianModel(pts, quats, np.log(np.maximum(scales, 1e-7)), opacity_logit(opac), sh)
