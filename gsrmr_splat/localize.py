"""Registration of a real image against the model: the camera pose that makes the model's render match it
(features on the render and its depth → PnP with RANSAC, iterated from the guess). Design: docs/splatting.md,
"Localization"."""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import time

import cv2
import numpy as np

from gsrmr_common.camera import Camera
from gsrmr_splat.model import GaussianModel
from gsrmr_splat.render import render

#: Why a registration is refused (:attr:`Registration.refused`).
FEW_MATCHES, FEW_INLIERS, NO_CONVERGENCE, LOSS_NOT_REDUCED, TOO_FAR = (
    "few_matches", "few_inliers", "no_convergence", "loss_not_reduced", "too_far")


@dataclass(frozen=True)
class LocalizeConfig:
    """The registration's knobs (pixels at the image's own size)."""

    max_iterations: int = 5  # render → track → PnP rounds
    min_inliers: int = 20  # PnP inliers a round needs
    reprojection_px: float = 1.5  # RANSAC inlier threshold
    window_px: int = 21  # Lucas–Kanade window
    pyramid_levels: int = 3  # LK pyramid: motions up to about 2^levels · window/2 pixels
    forward_backward_px: float = 0.5  # a track must come back to its corner within this
    min_distance_px: int = 4  # between two corners
    corner_quality: float = 0.003  # Shi–Tomasi: a corner's score relative to the render's best
    min_alpha: float = 0.9  # a render pixel is used for 3-D only where it is opaque …
    max_depth_jump: float = 0.03  # … and its depth is smooth (relative change to its 3×3 neighbours)
    converged_m: float = 2e-3  # stop when a round moves the camera less than this …
    converged_rad: float = math.radians(0.05)  # … and turns it less than this (the tracking's noise floor)
    max_correction_m: float = 0.5  # a correction larger than this is refused (a wrong match, not a drift)
    max_correction_rad: float = math.radians(20.0)
    features: int = 800  # corners per render at most


@dataclass
class Registration:
    """What :func:`register` found: the refined camera, how it got there and whether to trust it.

    Attributes:
        camera: The refined camera (the guess when refused).
        accepted: Whether the fit is trustworthy (``refused`` is empty).
        refused: Why not (a ``*`` constant of this module), "" when accepted.
        inliers: PnP inliers of the last round.
        matches: Descriptor matches with a 3-D point in the last round.
        loss_before: Mean absolute RGB difference of the render at the guess against the image.
        loss_after: The same at the refined camera.
        correction_m: How far the camera centre moved [m].
        correction_rad: How far the camera turned [rad].
        seconds: Wall time.
    """

    camera: Camera
    accepted: bool
    refused: str = ""
    inliers: int = 0
    matches: int = 0
    loss_before: float = math.nan
    loss_after: float = math.nan
    correction_m: float = 0.0
    correction_rad: float = 0.0
    seconds: float = 0.0
    rounds: list[tuple[int, int, float, float]] = field(default_factory=list)  # (matches, inliers, moved m, rad)


def _gray_u8(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def _smooth_depth(depth: np.ndarray, alpha: np.ndarray, cfg: LocalizeConfig) -> np.ndarray:
    """Where the render's depth can be lifted to 3-D: opaque, and not on a depth edge."""
    ok = (alpha >= cfg.min_alpha) & (depth > 0) & np.isfinite(depth)
    d = np.where(ok, depth, np.nan).astype(np.float32)
    lo = cv2.erode(np.nan_to_num(d, nan=np.inf), np.ones((3, 3), np.uint8))
    hi = cv2.dilate(np.nan_to_num(d, nan=0.0), np.ones((3, 3), np.uint8))
    with np.errstate(invalid="ignore", divide="ignore"):
        smooth = (hi - lo) <= cfg.max_depth_jump * np.maximum(d, 1e-6)
    return ok & smooth


def _rotation_angle(r: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (float(np.trace(r)) - 1.0) / 2.0)))


def _mean_abs(model: GaussianModel, camera: Camera, image: np.ndarray, background: np.ndarray) -> float:
    return float(np.mean(np.abs(render(model, camera, background=background).rgb - image)))


def register(model: GaussianModel, image: np.ndarray, guess: Camera, *, config: LocalizeConfig | None = None,
             background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Registration:
    """Refine ``guess`` so that the model's render at it matches ``image``.

    Each round renders the model at the current camera (colour and depth), tracks corners of the render into the
    image (pyramidal Lucas–Kanade, checked forward and backward), lifts the tracked corners to 3-D with the render's
    depth (opaque, smooth pixels only) and solves PnP with RANSAC for the camera that sees those points where the
    image shows them, refined by Levenberg–Marquardt on the inliers; it stops when a
    round moves the camera less than ``converged_m`` / ``converged_rad``. The fit is refused when a round has
    too few matches or inliers, when it does not converge, when the correction is larger than any drift, or when
    the render at it matches the image worse than at the guess.

    Args:
        model: The scene's model (world frame, metres).
        image: H×W×3 RGB in [0, 1], the guess's size (rectified: the guess's pinhole camera).
        guess: The camera the image is believed to be taken with (OpenCV axes, world → camera).
        config: The knobs (:class:`LocalizeConfig`).
        background: The render's background, RGB in [0, 1].

    Returns:
        The :class:`Registration`; ``camera`` is ``guess`` when refused.

    Example:
        ::

            reg = register(model, frame.image, frame.camera)
            if reg.accepted:
                camera = reg.camera
    """
    cfg = config or LocalizeConfig()
    t0 = time.perf_counter()
    bg = np.asarray(background, np.float32)
    h, w = image.shape[:2]
    if (w, h) != (guess.width, guess.height):
        raise ValueError(f"image {w}×{h} is not the guess camera's {guess.width}×{guess.height}")
    gray_img = _gray_u8(image)
    k_cv = guess.intrinsics.ros_k()
    camera = guess
    out = Registration(guess, False)
    loss_before = None
    lk = dict(winSize=(cfg.window_px, cfg.window_px), maxLevel=cfg.pyramid_levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    for _ in range(cfg.max_iterations):
        rendered = render(model, camera, background=bg)
        if loss_before is None:
            loss_before = float(np.mean(np.abs(rendered.rgb - image)))
        usable = _smooth_depth(rendered.depth, rendered.alpha, cfg)
        gray_r = _gray_u8(rendered.rgb)
        corners = None
        for quality in (cfg.corner_quality, cfg.corner_quality / 10):  # a plain view: weaker corners too
            corners = cv2.goodFeaturesToTrack(gray_r, maxCorners=cfg.features, qualityLevel=quality,
                                              minDistance=cfg.min_distance_px, mask=usable.astype(np.uint8))
            if corners is not None and len(corners) >= 3 * cfg.min_inliers:
                break
        if corners is None or len(corners) < cfg.min_inliers:
            out.refused = FEW_MATCHES
            break
        tracked, status, _ = cv2.calcOpticalFlowPyrLK(gray_r, gray_img, corners, None, **lk)
        back, status_b, _ = cv2.calcOpticalFlowPyrLK(gray_img, gray_r, tracked, None, **lk)
        fb = np.linalg.norm((back - corners).reshape(-1, 2), axis=1)
        good = (status.ravel() == 1) & (status_b.ravel() == 1) & (fb < cfg.forward_backward_px)
        src = corners.reshape(-1, 2)[good]
        dst = tracked.reshape(-1, 2)[good]
        inside = (dst[:, 0] >= 0) & (dst[:, 0] <= w - 1) & (dst[:, 1] >= 0) & (dst[:, 1] <= h - 1)
        src, dst = src[inside], dst[inside]
        iu, iv = np.rint(src[:, 0]).astype(int), np.rint(src[:, 1]).astype(int)
        z = rendered.depth[iv, iu].astype(np.float64)
        p_c = np.stack([(src[:, 0] - k_cv[0, 2]) / k_cv[0, 0] * z, (src[:, 1] - k_cv[1, 2]) / k_cv[1, 1] * z, z,
                        np.ones_like(z)], axis=1)
        pts_w = list((p_c @ camera.camera_to_world.T)[:, :3])
        pts_i = list(dst)
        out.matches = len(pts_w)
        if len(pts_w) < cfg.min_inliers:
            out.refused = FEW_MATCHES
            break
        obj = np.asarray(pts_w, np.float64)
        img = np.asarray(pts_i, np.float64)
        rvec, _ = cv2.Rodrigues(camera.world_to_camera[:3, :3])
        tvec = camera.world_to_camera[:3, 3].reshape(3, 1).copy()
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, k_cv, None, rvec=rvec, tvec=tvec, useExtrinsicGuess=True,
                                                 iterationsCount=200, reprojectionError=cfg.reprojection_px,
                                                 confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE)
        n_in = 0 if inl is None else len(inl)
        out.inliers = n_in
        if not ok or n_in < cfg.min_inliers:
            out.refused = FEW_INLIERS
            break
        idx = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], k_cv, None, rvec, tvec)
        w2c = np.eye(4)
        w2c[:3, :3] = cv2.Rodrigues(rvec)[0]
        w2c[:3, 3] = tvec.ravel()
        moved_m = float(np.linalg.norm(np.linalg.inv(w2c)[:3, 3] - camera.camera_to_world[:3, 3]))
        turned = _rotation_angle(w2c[:3, :3] @ camera.world_to_camera[:3, :3].T)
        camera = Camera(guess.intrinsics, w2c)
        out.rounds.append((len(pts_w), n_in, moved_m, turned))
        if moved_m < cfg.converged_m and turned < cfg.converged_rad:
            break
    else:
        if out.rounds and (out.rounds[-1][2] >= 5 * cfg.converged_m or out.rounds[-1][3] >= 5 * cfg.converged_rad):
            out.refused = NO_CONVERGENCE
    out.loss_before = loss_before if loss_before is not None else math.nan
    out.correction_m = float(np.linalg.norm(camera.camera_to_world[:3, 3] - guess.camera_to_world[:3, 3]))
    out.correction_rad = _rotation_angle(camera.world_to_camera[:3, :3] @ guess.world_to_camera[:3, :3].T)
    if not out.refused and (out.correction_m > cfg.max_correction_m or out.correction_rad > cfg.max_correction_rad):
        out.refused = TOO_FAR
    if not out.refused:
        out.loss_after = _mean_abs(model, camera, image, bg)
        if not out.loss_after <= out.loss_before:
            out.refused = LOSS_NOT_REDUCED
    out.accepted = not out.refused and bool(out.rounds)
    out.camera = camera if out.accepted else guess
    out.seconds = time.perf_counter() - t0
    return out
