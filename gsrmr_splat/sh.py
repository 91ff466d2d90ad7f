"""Real spherical harmonics up to degree 3 with the 3DGS basis and signs (``utils/sh_utils.py``). Colour along the unit
direction d from the camera centre to the Gaussian mean (world frame): ``c = max(0, Σ_k sh[k]·Y_k(d) + 0.5)`` per
channel; coefficients N×K×3, K = (degree + 1)², ``sh[:, 0]`` the DC term (``f_dc`` in the .ply).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
      0.5462742152960396)
C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_coeffs(degree: int) -> int:
    """Number of SH coefficients per channel, (degree + 1)²."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    return (degree + 1) ** 2


def degree_from_coeffs(k: int) -> int:
    """Inverse of :func:`num_coeffs`; raises for a count that is not a square of 1..4."""
    for d in range(4):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"{k} SH coefficients per channel is not (d+1)² for a degree d in 0..3")


def rgb_to_sh0(rgb: np.ndarray) -> np.ndarray:
    """Flat colour in [0, 1] → DC coefficient ``(rgb − 0.5) / C0``."""
    return (np.asarray(rgb) - 0.5) / C0


def sh0_to_rgb(sh0: np.ndarray) -> np.ndarray:
    """DC coefficient → flat colour (without the max(0, ·) clamp)."""
    return np.asarray(sh0) * C0 + 0.5


def sh_basis(x, y, z, degree: int, lib) -> list:
    """The real SH basis functions Y_0 … Y_{(degree+1)²−1} at unit directions (x, y, z), computed with the
    array library ``lib`` (numpy here, torch in :mod:`~gsrmr_splat.diffrender`)."""
    out = [lib.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [C3[0] * y * (3.0 * xx - yy), C3[1] * xy * z, C3[2] * y * (4.0 * zz - xx - yy),
                C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), C3[4] * x * (4.0 * zz - xx - yy),
                C3[5] * z * (xx - yy), C3[6] * x * (xx - 3.0 * yy)]
    return out


def eval_sh_numpy(sh: np.ndarray, dirs: np.ndarray, degree: int) -> np.ndarray:
    """N×3 colours ``max(0, SH(d) + 0.5)`` from N×K×3 coefficients and N×3 unit directions."""
    k = num_coeffs(degree)
    if sh.shape[1] < k:
        raise ValueError(f"need {k} SH coefficients for degree {degree}, model has {sh.shape[1]}")
    basis = sh_basis(dirs[:, 0], dirs[:, 1], dirs[:, 2], degree, np)
    col = np.zeros((sh.shape[0], 3), dtype=sh.dtype)
    for i, b in enumerate(basis):
        col += b[:, None] * sh[:, i, :]
    return np.maximum(col + 0.5, 0.0)


@nb.njit(parallel=True, cache=True)
def eval_sh_kernel(sh, means, index, center, degree, out):
    """Numba :func:`eval_sh_numpy` for the Gaussians ``index``: out[j] = colour of Gaussian index[j]
    seen from ``center`` (dir = normalise(mean − center); a zero direction gives the DC colour)."""
    for j in nb.prange(index.shape[0]):
        i = index[j]
        x = float(means[i, 0]) - center[0]
        y = float(means[i, 1]) - center[1]
        z = float(means[i, 2]) - center[2]
        n = math.sqrt(x * x + y * y + z * z)
        if n > 0.0:
            x /= n
            y /= n
            z /= n
        b = np.empty(16)
        b[0] = C0
        if degree >= 1:
            b[1] = -C1 * y
            b[2] = C1 * z
            b[3] = -C1 * x
        if degree >= 2:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            b[4] = C2[0] * xy
            b[5] = C2[1] * yz
            b[6] = C2[2] * (2.0 * zz - xx - yy)
            b[7] = C2[3] * xz
            b[8] = C2[4] * (xx - yy)
            if degree >= 3:
                b[9] = C3[0] * y * (3.0 * xx - yy)
                b[10] = C3[1] * xy * z
                b[11] = C3[2] * y * (4.0 * zz - xx - yy)
                b[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
                b[13] = C3[4] * x * (4.0 * zz - xx - yy)
                b[14] = C3[5] * z * (xx - yy)
                b[15] = C3[6] * x * (xx - 3.0 * yy)
        k = (degree + 1) * (degree + 1)
        for c in range(3):
            acc = 0.0
            for m in range(k):
                acc += b[m] * sh[i, m, c]
            out[j, c] = max(acc + 0.5, 0.0)
