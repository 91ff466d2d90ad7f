"""The Gaussian model (:class:`GaussianModel`: parameters before activation, world frame, metres) and the standard 3DGS
``.ply`` format that graphdeco-inria 3DGS, gsplat and nerfstudio read and write (:meth:`GaussianModel.save_ply`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyParseError

from gsrmr_splat.sh import degree_from_coeffs, num_coeffs, rgb_to_sh0


class PlyFormatError(ValueError):
    """A .ply file that is not a valid 3DGS Gaussian model."""


def opacity_logit(p: np.ndarray) -> np.ndarray:
    """The logit of opacities ``p`` (clipped to [1e-6, 1 − 1e-6]): what ``opacity_logits`` stores."""
    p = np.clip(p, 1e-6, 1.0 - 1e-6)
    return np.log(p / (1.0 - p))


@dataclass
class GaussianModel:
    """N anisotropic 3-D Gaussians with spherical-harmonic colour, parameters stored before activation.

    Every array is converted to contiguous float32 on construction; positions and sizes are in the world frame,
    in metres.

    Attributes:
        means: N×3 centres (metres).
        quats: N×4 rotations as (w, x, y, z) quaternions, not necessarily normalised (normalised on use).
        log_scales: N×3 natural logs of the standard deviations along the rotated axes (:attr:`scales`, metres).
        opacity_logits: N logits of the opacities (:attr:`opacities` = sigmoid(logit)).
        sh: N×K×3 SH colour coefficients per RGB channel, K = (degree + 1)² for degree 0..3, ``sh[:, 0]`` the DC
            term (colour conventions: :mod:`~gsrmr_splat.sh`).

    Raises:
        ValueError: ``sh`` is not N×K×3 with K one of 1, 4, 9, 16, or another array does not reshape to N rows.

    Example:
        ::

            points = np.array([[1.0, 0.0, 0.2], [1.5, 0.3, 0.2]])
            model = GaussianModel.from_points(points, [[0.8, 0.2, 0.2], [0.2, 0.8, 0.2]], scales_m=0.05)
            model.save_ply("two.ply")
            assert GaussianModel.load_ply("two.ply").num_gaussians == 2
    """

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        self.means = np.ascontiguousarray(self.means, dtype=np.float32).reshape(-1, 3)
        n = self.means.shape[0]
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32).reshape(n, 4)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32).reshape(n, 3)
        self.opacity_logits = np.ascontiguousarray(self.opacity_logits, dtype=np.float32).reshape(n)
        sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"sh must be N×K×3 with N={n}, got {sh.shape}")
        degree_from_coeffs(sh.shape[1])
        self.sh = sh

    @property
    def num_gaussians(self) -> int:
        """N."""
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num_gaussians

    @property
    def sh_degree(self) -> int:
        """SH degree 0..3 implied by K."""
        return degree_from_coeffs(self.sh.shape[1])

    @property
    def opacities(self) -> np.ndarray:
        """Activated opacities in (0, 1)."""
        return (1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))).astype(np.float32)

    @property
    def scales(self) -> np.ndarray:
        """Activated standard deviations (metres)."""
        return np.exp(self.log_scales)

    def check_finite(self) -> None:
        """Raise ValueError naming the first parameter array holding NaN or inf."""
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            arr = getattr(self, name)
            bad = ~np.isfinite(arr)
            if bad.any():
                idx = int(np.argwhere(bad.reshape(arr.shape[0], -1).any(axis=1))[0, 0])
                raise ValueError(f"Gaussian model: {name} holds NaN/inf (first at Gaussian {idx})")
        qn = np.linalg.norm(self.quats, axis=1)
        if self.num_gaussians and np.any(qn < 1e-12):
            raise ValueError("Gaussian model: a quaternion has zero norm")

    def subset(self, index: np.ndarray) -> GaussianModel:
        """A new model holding the selected Gaussians (boolean mask or indices)."""
        return GaussianModel(self.means[index], self.quats[index], self.log_scales[index],
                             self.opacity_logits[index], self.sh[index])

    def with_degree(self, degree: int) -> GaussianModel:
        """A copy with SH truncated or zero-padded to ``degree``."""
        k = num_coeffs(degree)
        sh = np.zeros((self.num_gaussians, k, 3), np.float32)
        m = min(k, self.sh.shape[1])
        sh[:, :m] = self.sh[:, :m]
        return GaussianModel(self.means, self.quats, self.log_scales, self.opacity_logits, sh)

    @classmethod
    def empty(cls, degree: int = 0) -> GaussianModel:
        """A model with no Gaussians (renders the background)."""
        k = num_coeffs(degree)
        return cls(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, k, 3)))

    @classmethod
    def from_points(cls, points_m: np.ndarray, colors_rgb: np.ndarray, *, scales_m: np.ndarray | float = 0.01,
                    quats_wxyz: np.ndarray | None = None, opacities: np.ndarray | float = 0.1,
                    degree: int = 0) -> GaussianModel:
        """Gaussians at ``points_m`` (N×3) with flat colours ``colors_rgb`` (N×3 in [0, 1] or uint8).

        ``scales_m`` (N×3, N or scalar) are standard deviations in metres; ``quats_wxyz`` default to
        identity; ``opacities`` in (0, 1); SH above degree 0 start at zero.
        """
        pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        n = pts.shape[0]
        col = np.asarray(colors_rgb)
        col = col.astype(np.float64) / 255.0 if col.dtype == np.uint8 else col.astype(np.float64)
        col = np.broadcast_to(col.reshape(-1, 3), (n, 3))
        sc = np.asarray(scales_m, dtype=np.float64)
        scales = np.broadcast_to(sc.reshape(-1, 1) if sc.ndim == 1 else sc, (n, 3))
        if np.any(scales <= 0):
            raise ValueError("from_points: scales must be > 0")
        quats = (np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) if quats_wxyz is None
                 else np.asarray(quats_wxyz, dtype=np.float64).reshape(n, 4))
        opac = np.broadcast_to(np.asarray(opacities, dtype=np.float64), (n,))
        sh = np.zeros((n, num_coeffs(degree), 3))
        sh[:, 0] = rgb_to_sh0(col)
        return cls(pts, quats, np.log(scales), opacity_logit(opac), sh)

    # ------------------------------------------------------------------ .ply IO
    def save_ply(self, path: str | Path) -> Path:
        """Write the standard 3DGS .ply: binary little endian, one ``vertex`` element of float32 properties.

        The properties, values before activation: ``x y z nx ny nz f_dc_0..2 f_rest_0..(3(K−1)−1) opacity
        scale_0..2 rot_0..3``, the normals zero and ``f_rest`` grouped by colour channel (all red coefficients
        1..K−1, then green, then blue): the layout graphdeco-inria 3DGS writes and gsplat and nerfstudio read.

        Args:
            path: The file to write; its folder is created.

        Returns:
            Path: ``path``.

        Raises:
            ValueError: A parameter holds NaN or inf, or a quaternion has zero norm (:meth:`check_finite`).

        Example:
            ::

                model = GaussianModel.from_points(np.zeros((1, 3)), [[0.5, 0.5, 0.5]])
                model.save_ply("out/one.ply")
        """
        self.check_finite()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        n, k = self.num_gaussians, self.sh.shape[1]
        names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
        names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        f_rest = self.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)  # channel-major
        cols = np.concatenate([self.means, np.zeros((n, 3), np.float32), self.sh[:, 0, :], f_rest,
                               self.opacity_logits[:, None], self.log_scales, self.quats], axis=1)
        data = np.empty(n, dtype=[(name, "f4") for name in names])
        for i, name in enumerate(names):
            data[name] = cols[:, i]
        PlyData([PlyElement.describe(data, "vertex")]).write(str(path))
        return path

    @classmethod
    def load_ply(cls, path: str | Path) -> GaussianModel:
        """Read a 3DGS .ply as graphdeco-inria 3DGS, gsplat and nerfstudio write it (layout: :meth:`save_ply`).

        Args:
            path: The .ply file.

        Returns:
            GaussianModel: The model; its SH degree (0..3) follows from the number of ``f_rest_*`` properties.

        Raises:
            FileNotFoundError: ``path`` does not exist.
            PlyFormatError: Not a readable .ply, no ``vertex`` element, missing or misnumbered 3DGS properties, an
                ``f_rest`` count of no SH degree, a NaN or inf value or a zero quaternion (the message names the
                property and the first bad vertex).

        Example:
            ::

                model = GaussianModel.load_ply("room.ply")
                print(model.num_gaussians, model.sh_degree)
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"no such .ply: {path}")
        try:
            ply = PlyData.read(str(path))
        except (PlyParseError, ValueError, EOFError, IndexError, TypeError) as exc:
            raise PlyFormatError(f"{path}: not a readable .ply file ({exc})") from exc
        if "vertex" not in [e.name for e in ply.elements]:
            raise PlyFormatError(f"{path}: no 'vertex' element")
        v = ply["vertex"].data
        fields = set(v.dtype.names or ())
        required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                    "rot_0", "rot_1", "rot_2", "rot_3"]
        missing = [f for f in required if f not in fields]
        if missing:
            raise PlyFormatError(f"{path}: missing 3DGS vertex properties {missing}")
        rest = sorted((f for f in fields if f.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
        if [int(f.split("_")[-1]) for f in rest] != list(range(len(rest))):
            raise PlyFormatError(f"{path}: f_rest_* properties are not numbered 0..{len(rest) - 1}")
        if len(rest) % 3:
            raise PlyFormatError(f"{path}: {len(rest)} f_rest properties is not a multiple of 3")
        try:
            degree = degree_from_coeffs(len(rest) // 3 + 1)
        except ValueError as exc:
            raise PlyFormatError(f"{path}: {exc}") from exc
        n = len(v)
        for name in [*required, *rest]:  # name the property and the vertex, not just the array
            bad = ~np.isfinite(np.asarray(v[name], dtype=np.float64))
            if bad.any():
                raise PlyFormatError(f"{path}: vertex property '{name}' holds NaN/inf (first at vertex "
                                     f"{int(np.argmax(bad))})")

        def col(name: str) -> np.ndarray:
            return np.asarray(v[name], dtype=np.float32)

        means = np.stack([col("x"), col("y"), col("z")], axis=1)
        k = num_coeffs(degree)
        sh = np.zeros((n, k, 3), np.float32)
        sh[:, 0] = np.stack([col(f"f_dc_{i}") for i in range(3)], axis=1)
        if rest:
            fr = np.stack([col(f) for f in rest], axis=1).reshape(n, 3, k - 1)
            sh[:, 1:] = fr.transpose(0, 2, 1)
        model = cls(means, np.stack([col(f"rot_{i}") for i in range(4)], axis=1),
                    np.stack([col(f"scale_{i}") for i in range(3)], axis=1), col("opacity"), sh)
        try:
            model.check_finite()
        except ValueError as exc:
            raise PlyFormatError(f"{path}: {exc}") from exc
        return model
