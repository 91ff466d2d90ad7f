"""EWA projection of 3-D Gaussians to the image plane (3DGS / gsplat conventions): culling, 2-D conic, 3-sigma radius
and the opacity-limited pixel box. Camera: OpenCV axes (x right, y down, z forward), ``world_to_camera`` 4×4, pinhole
fx, fy, cx, cy in pixels, pixel centres at +0.5. The rules (near plane :data:`NEAR_M`, Jacobian clamp, 0.3 px² blur; the
projected mean itself is not clamped): docs/splatting.md, "Conventions"; the box: "How the fast path works".
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

NEAR_M = 0.2
EPS2D_PX2 = 0.3
CLAMP_FOV_MARGIN = 0.3
ALPHA_MIN = 1.0 / 255.0


def fov_limits(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> tuple[float, ...]:
    """(lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos): the Jacobian clamp bounds on x/z and y/z."""
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    return (cx / fx + CLAMP_FOV_MARGIN * tan_x, (width - cx) / fx + CLAMP_FOV_MARGIN * tan_x,
            cy / fy + CLAMP_FOV_MARGIN * tan_y, (height - cy) / fy + CLAMP_FOV_MARGIN * tan_y)


@nb.njit(parallel=True, cache=True, fastmath=False)
def project_kernel(means, quats, log_scales, opacity_logits, w2c, intr, lims, width, height, near_m,
                   out_geom, out_box):
    """Numba projection. ``intr`` = (fx, fy, cx, cy); ``lims`` from :func:`fov_limits`.

    ``out_geom[i]`` = (mx, my, conic_a, conic_b, conic_c, opacity, depth_z, radius, cov_xx, cov_yy)
    as float32; ``out_box[i]`` = (u_min, u_max, v_min, v_max) pixel range that can receive
    alpha ≥ 1/255, with ``u_min > u_max`` for a culled Gaussian.
    """
    n = means.shape[0]
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for i in nb.prange(n):
        out_box[i, 0] = 1
        out_box[i, 1] = 0
        out_box[i, 2] = 1
        out_box[i, 3] = 0
        out_geom[i, 7] = 0.0
        mx_w, my_w, mz_w = means[i, 0], means[i, 1], means[i, 2]
        x = w2c[0, 0] * mx_w + w2c[0, 1] * my_w + w2c[0, 2] * mz_w + w2c[0, 3]
        y = w2c[1, 0] * mx_w + w2c[1, 1] * my_w + w2c[1, 2] * mz_w + w2c[1, 3]
        z = w2c[2, 0] * mx_w + w2c[2, 1] * my_w + w2c[2, 2] * mz_w + w2c[2, 3]
        if not z >= near_m:  # also rejects NaN
            continue
        opac = 1.0 / (1.0 + math.exp(-float(opacity_logits[i])))
        if not opac >= ALPHA_MIN:  # also rejects NaN
            continue
        qw, qx, qy, qz = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        if not qn > 0.0:
            continue
        qw /= qn
        qx /= qn
        qy /= qn
        qz /= qn
        r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
        r01 = 2.0 * (qx * qy - qw * qz)
        r02 = 2.0 * (qx * qz + qw * qy)
        r10 = 2.0 * (qx * qy + qw * qz)
        r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
        r12 = 2.0 * (qy * qz - qw * qx)
        r20 = 2.0 * (qx * qz - qw * qy)
        r21 = 2.0 * (qy * qz + qw * qx)
        r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
        s0 = math.exp(float(log_scales[i, 0]))
        s1 = math.exp(float(log_scales[i, 1]))
        s2 = math.exp(float(log_scales[i, 2]))
        # M = R S; Σ = M Mᵀ
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
        # T = J W (2×3); project M with it: P = T M (2×3) then cov2 = P Pᵀ
        tx = min(max(x / z, -lims[0]), lims[1]) * z
        ty = min(max(y / z, -lims[2]), lims[3]) * z
        j00, j02 = fx / z, -fx * tx / (z * z)
        j11, j12 = fy / z, -fy * ty / (z * z)
        t00 = j00 * w2c[0, 0] + j02 * w2c[2, 0]
        t01 = j00 * w2c[0, 1] + j02 * w2c[2, 1]
        t02 = j00 * w2c[0, 2] + j02 * w2c[2, 2]
        t10 = j11 * w2c[1, 0] + j12 * w2c[2, 0]
        t11 = j11 * w2c[1, 1] + j12 * w2c[2, 1]
        t12 = j11 * w2c[1, 2] + j12 * w2c[2, 2]
        p00 = t00 * m00 + t01 * m10 + t02 * m20
        p01 = t00 * m01 + t01 * m11 + t02 * m21
        p02 = t00 * m02 + t01 * m12 + t02 * m22
        p10 = t10 * m00 + t11 * m10 + t12 * m20
        p11 = t10 * m01 + t11 * m11 + t12 * m21
        p12 = t10 * m02 + t11 * m12 + t12 * m22
        ca = p00 * p00 + p01 * p01 + p02 * p02 + EPS2D_PX2
        cb = p00 * p10 + p01 * p11 + p02 * p12
        cc = p10 * p10 + p11 * p11 + p12 * p12 + EPS2D_PX2
        det = ca * cc - cb * cb
        if not det > 0.0 or not math.isfinite(det):
            continue
        mid = 0.5 * (ca + cc)
        lam = mid + math.sqrt(max(0.1, mid * mid - det))
        radius = math.ceil(3.0 * math.sqrt(lam))
        mx = fx * x / z + cx
        my = fy * y / z + cy
        cut = 2.0 * math.log(255.0 * opac)
        if cut <= 0.0:
            continue
        ex = min(radius, math.sqrt(cut * ca) * (1.0 + 1e-6) + 1e-4)
        ey = min(radius, math.sqrt(cut * cc) * (1.0 + 1e-6) + 1e-4)
        # pixel u receives the Gaussian only if |u + 0.5 − mx| ≤ ex
        u0 = max(math.ceil(mx - ex - 0.5), 0.0)
        u1 = min(math.floor(mx + ex - 0.5), width - 1.0)
        v0 = max(math.ceil(my - ey - 0.5), 0.0)
        v1 = min(math.floor(my + ey - 0.5), height - 1.0)
        if u0 > u1 or v0 > v1:
            continue
        out_box[i, 0] = int(u0)
        out_box[i, 1] = int(u1)
        out_box[i, 2] = int(v0)
        out_box[i, 3] = int(v1)
        out_geom[i, 0] = mx
        out_geom[i, 1] = my
        out_geom[i, 2] = cc / det
        out_geom[i, 3] = -cb / det
        out_geom[i, 4] = ca / det
        out_geom[i, 5] = opac
        out_geom[i, 6] = z
        out_geom[i, 7] = radius
        out_geom[i, 8] = ca
        out_geom[i, 9] = cc


def project_numpy(means, quats, log_scales, opacity_logits, world_to_camera, intr, width, height,
                  near_m=NEAR_M):
    """Run :func:`project_kernel`; returns (geom N×10 float32, box N×4 int32)."""
    n = means.shape[0]
    geom = np.zeros((n, 10), np.float32)
    box = np.zeros((n, 4), np.int32)
    if n:
        lims = np.asarray(fov_limits(*intr, width, height), np.float64)
        project_kernel(means, quats, log_scales, opacity_logits, np.asarray(world_to_camera, np.float64),
                       np.asarray(intr, np.float64), lims, int(width), int(height), float(near_m), geom, box)
    return geom, box
