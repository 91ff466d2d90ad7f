"""Similarity alignment of a model trained elsewhere into the robot's ``map`` frame: ``x_map = s·R·x_model + t`` fitted
to the camera centres (Umeyama inside RANSAC) and applied to every Gaussian (:func:`transform_model`). Camera poses here
are 4×4 camera→world with OpenCV camera axes (:mod:`gsrmr_common.camera`). Pure numpy/scipy. Design: docs/splatting.md,
"Aligning a model trained elsewhere".
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
import itertools
import math

import numpy as np
from scipy.spatial.transform import Rotation

from gsrmr_splat.model import GaussianModel
from gsrmr_splat.sh import sh_basis

# Point sets whose second principal spread is below this fraction of the first are collinear: the rotation
# about their line is undetermined.
COLLINEAR_RATIO = 1e-6
# threshold_m=None: inliers lie within this fraction of the map-frame camera centres' median distance from
# their median (the rule of :func:`default_threshold_m`).
DEFAULT_THRESHOLD_FRACTION = 0.05
ORTHONORMAL_TOL = 1e-6
# RANSAC stops once an all-inlier minimal sample was drawn with probability ≥ 1 − MISS_PROB (given the best
# inlier fraction so far), but never before MIN_RANDOM_SAMPLES random samples.
MISS_PROB = 1e-3
MIN_RANDOM_SAMPLES = 100
# Directions on which each degree's SH rotation matrix is fitted (Fibonacci sphere; 2l+1 ≤ 7 unknowns each).
_SH_FIT_DIRECTIONS = 64


def _fibonacci_sphere(n: int) -> np.ndarray:
    """n well-spread unit vectors (n×3)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _as_points(points: np.ndarray, what: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{what}: expected N×3 points, got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{what}: points hold NaN/inf")
    return pts


def _as_rotations(rotations: np.ndarray, n: int, what: str) -> np.ndarray:
    rots = np.asarray(rotations, dtype=np.float64)
    if rots.shape != (n, 3, 3) or not np.all(np.isfinite(rots)):
        raise ValueError(f"{what}: expected {n} finite 3×3 rotations, got shape {rots.shape}")
    return rots


def rotation_angle_deg(rotations: np.ndarray) -> np.ndarray:
    """Angle in degrees of each rotation matrix (…×3×3): atan2(sin, cos) from its skew part and its trace,
    accurate for small angles too (arccos of the trace alone loses half the digits near 0)."""
    rots = np.asarray(rotations, dtype=np.float64)
    cos = (np.trace(rots, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack([rots[..., 2, 1] - rots[..., 1, 2], rots[..., 0, 2] - rots[..., 2, 0],
                     rots[..., 1, 0] - rots[..., 0, 1]], axis=-1)
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), cos))


@dataclass(frozen=True, eq=False)
class Similarity:
    """``x' = scale·rotation·x + translation``: a uniform scale > 0, a proper rotation (3×3, det +1), a
    translation (3, in the target frame's units — metres for ``map``). Arrays are stored read-only float64."""

    scale: float
    rotation: np.ndarray = field(repr=False)
    translation: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        scale = float(self.scale)
        rot = np.array(self.rotation, dtype=np.float64)
        trans = np.array(self.translation, dtype=np.float64).reshape(-1)
        if not math.isfinite(scale) or scale <= 0.0:
            raise ValueError(f"Similarity: scale must be finite and > 0, got {self.scale}")
        if rot.shape != (3, 3) or not np.all(np.isfinite(rot)):
            raise ValueError(f"Similarity: rotation must be a finite 3×3 matrix, got shape {rot.shape}")
        if not np.allclose(rot @ rot.T, np.eye(3), atol=ORTHONORMAL_TOL) or np.linalg.det(rot) <= 0.0:
            raise ValueError("Similarity: rotation must be orthonormal with determinant +1 (no reflection)")
        if trans.shape != (3,) or not np.all(np.isfinite(trans)):
            raise ValueError(f"Similarity: translation must be 3 finite numbers, got {self.translation!r}")
        rot.setflags(write=False)
        trans.setflags(write=False)
        object.__setattr__(self, "scale", scale)
        object.__setattr__(self, "rotation", rot)
        object.__setattr__(self, "translation", trans)

    @classmethod
    def identity(cls) -> Similarity:
        """s = 1, R = I, t = 0."""
        return cls(1.0, np.eye(3), np.zeros(3))

    def matrix(self) -> np.ndarray:
        """4×4 homogeneous matrix [s·R | t; 0 0 0 1]."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def inverse(self) -> Similarity:
        """The similarity undoing this one: x = (1/s)·Rᵀ·(x' − t)."""
        rot_t = self.rotation.T
        return Similarity(1.0 / self.scale, rot_t, -(rot_t @ self.translation) / self.scale)

    def compose(self, first: Similarity) -> Similarity:
        """``self ∘ first``: apply ``first``, then ``self``."""
        return Similarity(self.scale * first.scale, self.rotation @ first.rotation,
                          self.scale * (self.rotation @ first.translation) + self.translation)

    def apply_points(self, points: np.ndarray) -> np.ndarray:
        """N×3 points → N×3 transformed points (float64)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.scale * (pts @ self.rotation.T) + self.translation

    def apply_camera_to_world(self, camera_to_world: np.ndarray) -> np.ndarray:
        """A 4×4 camera→world pose (…×4×4 too) → the same camera in the target frame: rotation R·R_c (the
        scale does not enter a camera's axes), centre s·R·c + t."""
        c2w = np.asarray(camera_to_world, dtype=np.float64)
        out = np.array(c2w, copy=True)
        out[..., :3, :3] = self.rotation @ c2w[..., :3, :3]
        out[..., :3, 3] = self.scale * (c2w[..., :3, 3] @ self.rotation.T) + self.translation
        return out

    def to_dict(self) -> dict:
        """JSON-ready: ``scale``, ``rotation`` (3×3 rows), ``translation`` and the 4×4 ``matrix``."""
        return {"scale": self.scale, "rotation": self.rotation.tolist(), "translation": self.translation.tolist(),
                "matrix": self.matrix().tolist()}


def spread_ratio(points: np.ndarray) -> float:
    """Second over first principal spread of N×3 points (0 for collinear or coincident points, 1 for an
    isotropic cloud in at least a plane): how well the points pin a rotation down."""
    pts = _as_points(points, "spread_ratio")
    sv = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return float(sv[1] / sv[0]) if sv[0] > 0.0 else 0.0


def _check_not_degenerate(points: np.ndarray, what: str) -> None:
    if points.shape[0] < 3:
        raise ValueError(f"{what}: a similarity needs at least 3 point pairs, got {points.shape[0]}")
    if spread_ratio(points) <= COLLINEAR_RATIO:
        raise ValueError(f"{what}: the points are collinear or coincident (spread ratio "
                         f"{spread_ratio(points):.1e}): the rotation about their line is undetermined; "
                         "use cameras that are not all on one straight line")


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity with ``dst ≈ s·R·src + t`` (Umeyama 1991, with scale).

    ``src``, ``dst``: N×3 corresponding points (N ≥ 3, not collinear: ValueError otherwise). The rotation is
    proper (det +1) even when the best orthogonal fit would be a reflection (Umeyama's sign correction);
    coplanar points are fine. Minimises Σ‖dst_i − (s·R·src_i + t)‖², residuals in ``dst``'s units.
    """
    src = _as_points(src, "umeyama src")
    dst = _as_points(dst, "umeyama dst")
    if src.shape != dst.shape:
        raise ValueError(f"umeyama: src {src.shape} and dst {dst.shape} differ in shape")
    _check_not_degenerate(src, "umeyama src")
    _check_not_degenerate(dst, "umeyama dst")
    n = src.shape[0]
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    cov = dst_c.T @ src_c / n
    u, d, vt = np.linalg.svd(cov)
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0.0:
        sign[2] = -1.0
    rot = u @ np.diag(sign) @ vt
    var_src = float(np.sum(src_c * src_c)) / n
    scale = float(np.sum(d * sign)) / var_src
    if not scale > 0.0:
        raise ValueError("umeyama: the point sets do not correspond (non-positive scale): check the pairing")
    return Similarity(scale, rot, mu_dst - scale * (rot @ mu_src))


def default_threshold_m(dst: np.ndarray) -> float:
    """The RANSAC inlier distance when none is given: :data:`DEFAULT_THRESHOLD_FRACTION` (5 %) of the median
    distance of the ``dst`` (map-frame) camera centres from their coordinate-wise median — a robust measure of
    the route's extent, in ``dst``'s units (metres for ``map``)."""
    pts = _as_points(dst, "default_threshold_m")
    spread = float(np.median(np.linalg.norm(pts - np.median(pts, axis=0), axis=1)))
    if not spread > 0.0:
        raise ValueError("the map-frame camera centres all coincide: no scale or rotation can be estimated")
    return DEFAULT_THRESHOLD_FRACTION * spread


@dataclass(frozen=True, eq=False)
class RansacFit:
    """Result of :func:`ransac_umeyama`: the similarity refitted on the inliers, the inlier mask (N bool),
    the distance threshold used (``dst`` units) and the number of minimal samples tried."""

    similarity: Similarity
    inliers: np.ndarray = field(repr=False)
    threshold_m: float
    samples_tried: int


def _inlier_mask(sim: Similarity, src: np.ndarray, dst: np.ndarray, threshold_m: float,
                 rotation_pair: tuple[np.ndarray, np.ndarray] | None, rotation_threshold_deg: float | None
                 ) -> tuple[np.ndarray, float]:
    """(inlier mask, sum of the inliers' squared centre errors) of ``sim`` on the pairs."""
    err = np.linalg.norm(sim.apply_points(src) - dst, axis=1)
    mask = err <= threshold_m
    if rotation_pair is not None and rotation_threshold_deg is not None:
        mask &= rotation_errors_deg(sim, *rotation_pair) <= rotation_threshold_deg
    return mask, float(np.sum(err[mask] ** 2))


def _minimal_samples(n: int, iterations: int, rng: np.random.Generator) -> tuple[bool, Iterator[np.ndarray]]:
    """(exhaustive, samples): every triple when there are at most ``iterations`` of them (deterministic), else
    ``iterations`` random triples of distinct indices."""
    if math.comb(n, 3) <= iterations:
        return True, (np.array(t) for t in itertools.combinations(range(n), 3))
    return False, (rng.choice(n, size=3, replace=False) for _ in range(iterations))


def _samples_needed(inlier_fraction: float) -> float:
    """Random minimal samples after which an all-inlier one was drawn with probability ≥ 1 − :data:`MISS_PROB`."""
    w3 = inlier_fraction ** 3
    if w3 >= 1.0:
        return 1.0
    if w3 <= 0.0:
        return math.inf
    return math.log(MISS_PROB) / math.log1p(-w3)


def ransac_umeyama(src: np.ndarray, dst: np.ndarray, *, threshold_m: float | None = None, iterations: int = 2000,
                   seed: int = 0, min_inliers: int | None = None, src_rotations: np.ndarray | None = None,
                   dst_rotations: np.ndarray | None = None, rotation_threshold_deg: float | None = None
                   ) -> RansacFit:
    """Robust :func:`umeyama`: ``dst ≈ s·R·src + t`` with some pairs grossly wrong (mis-registered images).

    Minimal samples of 3 pairs each give a similarity (collinear samples are skipped): every triple when
    there are no more than ``iterations`` of them, else random triples from ``numpy.random.default_rng(seed)``
    (deterministic for a seed) until ``iterations`` were drawn or — after at least 100 — an all-inlier sample
    was drawn with probability ≥ 0.999 given the best inlier fraction so far (the standard RANSAC bound).
    A pair is an inlier of a similarity when its transformed ``src`` point lies within ``threshold_m`` of its
    ``dst`` point (distance in ``dst``'s frame and units) and, when ``rotation_threshold_deg`` is given with
    both rotation sets (N×3×3 camera→world rotations), the camera orientations agree within that angle
    (:func:`rotation_errors_deg`). The sample with the most
    inliers (ties: smallest sum of squared inlier errors) wins; the similarity is refitted on its inliers
    and the inlier set recomputed until it no longer changes (at most 10 rounds).

    ``threshold_m=None`` takes :func:`default_threshold_m`: 5 % of the median distance of the ``dst``
    centres from their median. ``min_inliers=None`` requires a majority, max(3, ⌈N/2⌉). ValueError when
    there are fewer than 3 pairs, the points are degenerate, or no sample reaches ``min_inliers``.
    """
    src = _as_points(src, "ransac_umeyama src")
    dst = _as_points(dst, "ransac_umeyama dst")
    if src.shape != dst.shape:
        raise ValueError(f"ransac_umeyama: src {src.shape} and dst {dst.shape} differ in shape")
    n = src.shape[0]
    if n < 3:
        raise ValueError(f"a similarity needs at least 3 pairs of camera centres, got {n}")
    if iterations < 1:
        raise ValueError(f"ransac_umeyama: iterations must be ≥ 1, got {iterations}")
    _check_not_degenerate(src, "model-frame camera centres")
    _check_not_degenerate(dst, "map-frame camera centres")
    threshold = default_threshold_m(dst) if threshold_m is None else float(threshold_m)
    if not (math.isfinite(threshold) and threshold > 0.0):
        raise ValueError(f"ransac_umeyama: threshold_m must be finite and > 0, got {threshold_m}")
    need = max(3, math.ceil(n / 2)) if min_inliers is None else int(min_inliers)
    if need < 3:
        raise ValueError(f"ransac_umeyama: min_inliers must be ≥ 3, got {min_inliers}")
    rotation_pair = None
    if src_rotations is not None and dst_rotations is not None:
        rotation_pair = (_as_rotations(src_rotations, n, "src_rotations"),
                         _as_rotations(dst_rotations, n, "dst_rotations"))
    rng = np.random.default_rng(seed)
    exhaustive, samples = _minimal_samples(n, iterations, rng)
    best_key: tuple[int, float] | None = None
    best_mask = np.zeros(n, bool)
    tried = 0
    for sample in samples:
        tried += 1
        try:
            sim = umeyama(src[sample], dst[sample])
        except ValueError:  # a collinear triple
            continue
        mask, sq = _inlier_mask(sim, src, dst, threshold, rotation_pair, rotation_threshold_deg)
        key = (int(mask.sum()), -sq)
        if best_key is None or key > best_key:
            best_key, best_mask = key, mask
        if (not exhaustive and tried >= MIN_RANDOM_SAMPLES and best_key[0] >= need
                and tried >= _samples_needed(best_key[0] / n)):
            break
    if best_key is None or best_key[0] < need:
        found = 0 if best_key is None else best_key[0]
        raise ValueError(f"only {found} of {n} camera pairs agree on one similarity within {threshold:.4g} m "
                         f"(need {need}): raise the threshold, or check that the names pair the same images")
    mask = best_mask
    sim = umeyama(src[mask], dst[mask])
    for _ in range(10):
        new_mask, _ = _inlier_mask(sim, src, dst, threshold, rotation_pair, rotation_threshold_deg)
        if np.array_equal(new_mask, mask) or new_mask.sum() < need:
            break
        try:
            new_sim = umeyama(src[new_mask], dst[new_mask])
        except ValueError:
            break
        mask, sim = new_mask, new_sim
    mask.setflags(write=False)
    return RansacFit(sim, mask, threshold, tried)


def rotation_errors_deg(sim: Similarity, src_rotations: np.ndarray, dst_rotations: np.ndarray) -> np.ndarray:
    """Per pair, the angle (degrees) between the ``dst`` camera's orientation and the ``src`` camera's carried
    by ``sim``: angle of R_dstᵀ·R·R_src (N×3×3 camera→world rotations, OpenCV axes on both sides)."""
    src_r = np.asarray(src_rotations, dtype=np.float64)
    dst_r = np.asarray(dst_rotations, dtype=np.float64)
    return rotation_angle_deg(np.swapaxes(dst_r, -1, -2) @ sim.rotation @ src_r)


@dataclass(frozen=True, eq=False)
class AlignmentReport:
    """How a model's cameras were aligned to the map's.

    ``pairs``: images found in both pose sets; ``inliers``: pairs the similarity explains (the rest are
    ``outlier_names``); centre errors are ‖s·R·c_model + t − c_map‖ over the inliers, in metres in the
    ``map`` frame; rotation errors (degrees) compare the map cameras' orientations with the model cameras'
    rotated by R, over the inliers. ``spread_ratio`` is the map-frame inlier centres' second over first
    principal spread (near 0: nearly collinear, the roll about the route is poorly determined).
    """

    pairs: int
    inliers: int
    threshold_m: float
    rms_center_error_m: float
    max_center_error_m: float
    rms_rotation_error_deg: float
    max_rotation_error_deg: float
    spread_ratio: float
    similarity: Similarity
    outlier_names: tuple[str, ...] = ()

    def to_dict(self) -> dict:
        """JSON-ready dict of every field; the similarity as :meth:`Similarity.to_dict`."""
        return {"pairs": self.pairs, "inliers": self.inliers, "threshold_m": self.threshold_m,
                "rms_center_error_m": self.rms_center_error_m, "max_center_error_m": self.max_center_error_m,
                "rms_rotation_error_deg": self.rms_rotation_error_deg,
                "max_rotation_error_deg": self.max_rotation_error_deg, "spread_ratio": self.spread_ratio,
                "similarity": self.similarity.to_dict(), "outlier_names": list(self.outlier_names)}

    def summary(self) -> str:
        """One line: pairs, inliers, scale, RMS centre error, rotation error."""
        return (f"{self.pairs} pairs, {self.inliers} inliers (threshold {self.threshold_m:.3g} m), scale "
                f"{self.similarity.scale:.6g}, RMS centre error {self.rms_center_error_m:.4f} m (max "
                f"{self.max_center_error_m:.4f} m), rotation error RMS {self.rms_rotation_error_deg:.2f}° "
                f"(max {self.max_rotation_error_deg:.2f}°)")


def _examples(names, k: int = 4) -> str:
    names = sorted(names)
    more = f", … ({len(names)} in all)" if len(names) > k else ""
    return ", ".join(repr(n) for n in names[:k]) + more if names else "(none)"


def align_poses(model_poses: Mapping[str, np.ndarray], map_poses: Mapping[str, np.ndarray], *,
                threshold_m: float | None = None, iterations: int = 2000, seed: int = 0,
                min_inliers: int | None = None, rotation_threshold_deg: float | None = None) -> AlignmentReport:
    """Pair two sets of camera poses by name and estimate ``x_map = s·R·x_model + t`` from the centres.

    ``model_poses`` / ``map_poses``: name → 4×4 camera→world (OpenCV axes), the names already reduced to
    one key per image (:func:`~gsrmr_splat.external_poses.image_key`). The fit is
    :func:`ransac_umeyama` on the paired centres (its ``threshold_m`` rule, ``seed``, ``min_inliers``); the
    camera rotations give the rotation residuals and, with ``rotation_threshold_deg``, take part in the inlier
    test. ValueError (naming what is wrong) when no name pairs, fewer than 3 pairs, degenerate geometry or no
    consensus.
    """
    common = sorted(set(model_poses) & set(map_poses))
    if not common:
        raise ValueError(f"no image name is in both pose sets: model side has {_examples(model_poses)}, "
                         f"map side has {_examples(map_poses)}; the names must match (basename without "
                         "extension)")
    if len(common) < 3:
        raise ValueError(f"only {len(common)} image(s) are in both pose sets ({_examples(common)}): a similarity "
                         "needs at least 3 (better 10 or more) cameras seen on both sides")
    model_c2w = np.stack([np.asarray(model_poses[k], dtype=np.float64).reshape(4, 4) for k in common])
    map_c2w = np.stack([np.asarray(map_poses[k], dtype=np.float64).reshape(4, 4) for k in common])
    src, dst = model_c2w[:, :3, 3], map_c2w[:, :3, 3]
    fit = ransac_umeyama(src, dst, threshold_m=threshold_m, iterations=iterations, seed=seed,
                         min_inliers=min_inliers, src_rotations=model_c2w[:, :3, :3],
                         dst_rotations=map_c2w[:, :3, :3], rotation_threshold_deg=rotation_threshold_deg)
    sim, mask = fit.similarity, fit.inliers
    center_err = np.linalg.norm(sim.apply_points(src[mask]) - dst[mask], axis=1)
    rot_err = rotation_errors_deg(sim, model_c2w[mask, :3, :3], map_c2w[mask, :3, :3])
    return AlignmentReport(
        pairs=len(common), inliers=int(mask.sum()), threshold_m=fit.threshold_m,
        rms_center_error_m=float(np.sqrt(np.mean(center_err ** 2))), max_center_error_m=float(center_err.max()),
        rms_rotation_error_deg=float(np.sqrt(np.mean(rot_err ** 2))), max_rotation_error_deg=float(rot_err.max()),
        spread_ratio=spread_ratio(dst[mask]), similarity=sim,
        outlier_names=tuple(k for k, ok in zip(common, mask, strict=True) if not ok))


# ------------------------------------------------------------------------------------ the model itself

def quaternion_wxyz(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w ≥ 0, of a proper 3×3 rotation."""
    q = Rotation.from_matrix(np.asarray(rotation, dtype=np.float64)).as_quat()  # scipy: (x, y, z, w)
    q = np.array([q[3], q[0], q[1], q[2]])
    return -q if q[0] < 0.0 else q


def quaternion_multiply(a_wxyz: np.ndarray, b_wxyz: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b of (…×4) wxyz quaternions: the rotation of b followed by that of a."""
    a, b = np.asarray(a_wxyz, dtype=np.float64), np.asarray(b_wxyz, dtype=np.float64)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def sh_rotation_matrix(rotation: np.ndarray, degree: int) -> np.ndarray:
    """(2l+1)×(2l+1) matrix M_l (l = ``degree`` in 1..3) rotating the degree-l block of real SH coefficients
    (the 3DGS basis of :func:`~gsrmr_splat.sh.sh_basis`, its C1–C3 constants and signs): with
    coefficients as a row c (one colour channel), c' = c·M_l satisfies Σ c'_k Y_k(R·d) = Σ c_k Y_k(d) for
    every unit direction d — the colour seen along R·d after the rotation is the colour seen along d before.

    Built numerically: on :data:`_SH_FIT_DIRECTIONS` Fibonacci-sphere directions d', Y(R⁻¹·d') = Y(d')·Mᵀ
    exactly (each degree's span is closed under rotation), so M is the least-squares solution (exact up to
    rounding) of A·Mᵀ = B with A = Y(d'), B = Y(Rᵀ·d').
    """
    if not 1 <= degree <= 3:
        raise ValueError(f"SH rotation: degree must be in 1..3, got {degree}")
    rot = np.asarray(rotation, dtype=np.float64)
    dirs = _fibonacci_sphere(_SH_FIT_DIRECTIONS)
    back = dirs @ rot  # row i = Rᵀ·d'_i
    lo, hi = degree * degree, (degree + 1) * (degree + 1)
    a = np.stack(sh_basis(dirs[:, 0], dirs[:, 1], dirs[:, 2], degree, np)[lo:hi], axis=1)
    b = np.stack(sh_basis(back[:, 0], back[:, 1], back[:, 2], degree, np)[lo:hi], axis=1)
    m_t, *_ = np.linalg.lstsq(a, b, rcond=None)
    return m_t.T


def rotate_sh(sh: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """N×K×3 SH coefficients of Gaussians rotated by ``rotation`` (3×3): the DC term unchanged, each degree
    1..3 block multiplied by :func:`sh_rotation_matrix` (float64 result)."""
    coeffs = np.asarray(sh, dtype=np.float64)
    out = coeffs.copy()
    k = coeffs.shape[1]
    for degree in range(1, 4):
        lo, hi = degree * degree, (degree + 1) * (degree + 1)
        if hi > k:
            break
        out[:, lo:hi, :] = np.einsum("nkc,kj->njc", coeffs[:, lo:hi, :], sh_rotation_matrix(rotation, degree))
    return out


def transform_model(model: GaussianModel, sim: Similarity) -> GaussianModel:
    """The model carried by ``sim`` into the target frame: means → s·R·μ + t; rotations q' = q_R ⊗ q (wxyz,
    the norm of q kept); log-scales + log(s); opacities unchanged; SH degrees 1..3 rotated by R
    (:func:`rotate_sh`), so the view-dependent colour follows the rotation. Rendered from a camera carried
    by ``sim`` (:meth:`Similarity.apply_camera_to_world`) it looks as the original from the original camera,
    but for the renderer's fixed near plane in metres (0.2 m)."""
    q_r = quaternion_wxyz(sim.rotation)
    return GaussianModel(means=sim.apply_points(model.means),
                         quats=quaternion_multiply(q_r, model.quats.astype(np.float64)),
                         log_scales=model.log_scales.astype(np.float64) + math.log(sim.scale),
                         opacity_logits=model.opacity_logits,
                         sh=rotate_sh(model.sh, sim.rotation))
