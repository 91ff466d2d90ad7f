"""Numba kernels of the fused engine (:mod:`~gsrmr_splat.fused`) around its rasterizer and loss: projection, the packed
rows with SH colour, the chain rule back to the parameters and the pose (with the density statistics), and Adam — the
torch path's maths with its backward pass written out by hand, every sum in a fixed order.
"""
from __future__ import annotations

import math

import numba as nb
import numpy as np

from gsrmr_splat.project import ALPHA_MIN, EPS2D_PX2
from gsrmr_splat.sh import C0, C1, C2, C3

GEOM_WIDTH = 11  # project_forward_kernel's rows
N_REDUCE = 64  # chunks of the fixed-order reductions (pose gradient, loss sums)
#: grads row layout of the rasterizer backward: d/d (mx, my, conic a, b, c, opacity, r, g, b)
RASTER_GRADS = 9


@nb.njit(parallel=True, cache=True, fastmath=False)
def project_forward_kernel(means, quats, log_scales, opacity_logits, w2c, intr, lims, width, height, near_m,
                           out_geom, out_box):
    """:func:`~gsrmr_splat.project.project_kernel` (the same culling and boxes) with float64
    ``out_geom`` rows (mx, my, conic a, b, c, opacity, z, radius, s0, s1, s2: the scales, for the backward pass);
    ``out_box`` as there (u_min > u_max: culled).

    Before the covariance, a cheap conservative test culls the Gaussians in front of the camera whose box
    cannot reach the image: radius ≤ 3·sqrt(λmax) + 1 and λmax ≤ trace + 0.32 ≤ ‖J·W‖²_F·s_max² + 0.92
    (the 2-D covariance is P·Pᵀ + 0.3·I with P = J·W·R·S, ‖R·S‖₂ = s_max), widened by 2 px; it removes
    nothing the full test would keep."""
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
        if not z >= near_m:
            continue
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
        mx = fx * x / z + cx
        my = fy * y / z + cy
        ls_max = max(float(log_scales[i, 0]), float(log_scales[i, 1]), float(log_scales[i, 2]))
        t_fro = t00 * t00 + t01 * t01 + t02 * t02 + t10 * t10 + t11 * t11 + t12 * t12
        r_bound = 3.0 * math.sqrt(t_fro * math.exp(2.0 * ls_max) + 0.92) + 3.0
        if mx + r_bound < 0.0 or mx - r_bound > width or my + r_bound < 0.0 or my - r_bound > height:
            continue
        opac = 1.0 / (1.0 + math.exp(-float(opacity_logits[i])))
        if not opac >= ALPHA_MIN:
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
        m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
        m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
        m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
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
        cut = 2.0 * math.log(255.0 * opac)
        if cut <= 0.0:
            continue
        ex = min(radius, math.sqrt(cut * ca) * (1.0 + 1e-6) + 1e-4)
        ey = min(radius, math.sqrt(cut * cc) * (1.0 + 1e-6) + 1e-4)
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
        dc = max(det, 1e-12)
        out_geom[i, 0] = mx
        out_geom[i, 1] = my
        out_geom[i, 2] = cc / dc
        out_geom[i, 3] = -cb / dc
        out_geom[i, 4] = ca / dc
        out_geom[i, 5] = opac
        out_geom[i, 6] = z
        out_geom[i, 7] = radius
        out_geom[i, 8] = s0
        out_geom[i, 9] = s1
        out_geom[i, 10] = s2


@nb.njit(inline="always", cache=True)
def _sh_basis(x, y, z, degree, b):
    """The real SH basis at unit direction (x, y, z) into b[0 .. (degree + 1)² − 1] (:func:`sh.sh_basis`)."""
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


@nb.njit(inline="always", cache=True)
def _sh_basis_vjp(x, y, z, degree, gb):
    """(d/dx, d/dy, d/dz) of Σ_k gb[k]·Y_k(x, y, z) (the basis as a function of an unnormalised direction's
    components; the normalisation is chained by the caller)."""
    gx = -C1 * gb[3]
    gy = -C1 * gb[1]
    gz = C1 * gb[2]
    if degree >= 2:
        gx += C2[0] * y * gb[4] - 2.0 * C2[2] * x * gb[6] + C2[3] * z * gb[7] + 2.0 * C2[4] * x * gb[8]
        gy += C2[0] * x * gb[4] + C2[1] * z * gb[5] - 2.0 * C2[2] * y * gb[6] - 2.0 * C2[4] * y * gb[8]
        gz += C2[1] * y * gb[5] + 4.0 * C2[2] * z * gb[6] + C2[3] * x * gb[7]
        if degree >= 3:
            xx, yy, zz = x * x, y * y, z * z
            gx += (C3[0] * 6.0 * x * y * gb[9] + C3[1] * y * z * gb[10] - C3[2] * 2.0 * x * y * gb[11]
                   - C3[3] * 6.0 * x * z * gb[12] + C3[4] * (4.0 * zz - 3.0 * xx - yy) * gb[13]
                   + C3[5] * 2.0 * x * z * gb[14] + C3[6] * 3.0 * (xx - yy) * gb[15])
            gy += (C3[0] * 3.0 * (xx - yy) * gb[9] + C3[1] * x * z * gb[10]
                   + C3[2] * (4.0 * zz - xx - 3.0 * yy) * gb[11] - C3[3] * 6.0 * y * z * gb[12]
                   - C3[4] * 2.0 * x * y * gb[13] - C3[5] * 2.0 * y * z * gb[14] - C3[6] * 6.0 * x * y * gb[15])
            gz += (C3[1] * x * y * gb[10] + C3[2] * 8.0 * y * z * gb[11]
                   + C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * gb[12] + C3[4] * 8.0 * x * z * gb[13]
                   + C3[5] * (xx - yy) * gb[14])
    return gx, gy, gz


@nb.njit(parallel=True, cache=True)
def gather_kernel(geom, box, order, means, sh_dc, sh_rest, center, degree, out, out_box):
    """Packed rasterizer rows (:mod:`~gsrmr_splat.rasterize` layout) of the Gaussians ``order``
    (depth order): geometry from ``geom`` (:func:`project_forward_kernel`), colour max(0, SH(dir) + 0.5),
    dir = normalise(mean − center) (degree 0: the DC term alone, as the torch path)."""
    m_rows = order.shape[0]
    per = (m_rows + N_REDUCE - 1) // N_REDUCE
    k_sh = (degree + 1) * (degree + 1)
    for ch in nb.prange(N_REDUCE):
        b = np.empty(16)
        for j in range(ch * per, min(m_rows, (ch + 1) * per)):
            i = order[j]
            for c in range(5):
                out[j, c] = geom[i, c]
            opac = geom[i, 5]
            out[j, 5] = opac
            if degree == 0:
                for c in range(3):
                    out[j, 6 + c] = max(float(sh_dc[i, 0, c]) * C0 + 0.5, 0.0)
            else:
                x = float(means[i, 0]) - center[0]
                y = float(means[i, 1]) - center[1]
                z = float(means[i, 2]) - center[2]
                n = max(math.sqrt(x * x + y * y + z * z), 1e-12)
                _sh_basis(x / n, y / n, z / n, degree, b)
                for c in range(3):
                    acc = b[0] * float(sh_dc[i, 0, c])
                    for m in range(1, k_sh):
                        acc += b[m] * float(sh_rest[i, m - 1, c])
                    out[j, 6 + c] = max(acc + 0.5, 0.0)
            out[j, 9] = geom[i, 6]
            out[j, 10] = geom[i, 7]
            out[j, 11] = math.log(255.0 * opac) + 1e-9
            for c in range(4):
                out_box[j, c] = box[i, c]


@nb.njit(parallel=True, cache=True, fastmath=True)
def project_backward_kernel(visible, rank, entry_grads, entry_start, geom, means, quats, log_scales,
                            opacity_logits, sh_dc, sh_rest, w2c, intr, lims, center, degree, g_means, g_quats,
                            g_log_scales, g_opacity, g_sh_dc, g_sh_rest, pose_grads, want_pose, half_w, half_h, radius,
                            grad_accum, grad_count, max_radius, last_seen, it):
    """Chain rule from the rasterizer's gradients to the parameters. Gaussian i = ``visible[q]`` (ascending, so that
    the parameter rows are visited in memory order) is packed row j = ``rank[q]``; its rasterizer gradient is the
    sum of ``entry_grads`` rows entry_start[q] … entry_start[q + 1] − 1 (its tile-list entries, in a fixed order:
    the result does not depend on the thread count). Parameters' gradients: row i of ``g_means`` (3),
    ``g_quats`` (4), ``g_log_scales`` (3), ``g_opacity`` (1), ``g_sh_dc`` (1×3), ``g_sh_rest`` (K−1×3) (N rows;
    the others are not written). The forward is recomputed from the parameters in float64 (the torch path's
    :func:`~gsrmr_splat.diffrender.project_torch`, activations and SH, no clamp at the near plane since
    culled Gaussians are not here; the scales and opacity are read from ``geom``, the forward's rows).

    With ``want_pose``, ``pose_grads`` (N_REDUCE × 15) receives per chunk dL/dW (3×3 row-major), dL/dt and
    dL/d(camera centre) for the SH directions. Density statistics of Gaussian i = order[j]:
    grad_accum[i] += ‖(dL/dmx·W/2, dL/dmy·H/2)‖, grad_count[i] += 1, max_radius[i] = max(·, radius[j]),
    last_seen[i] = it.
    """
    m_rows = visible.shape[0]
    fx, fy = intr[0], intr[1]
    w00, w01, w02 = w2c[0, 0], w2c[0, 1], w2c[0, 2]
    w10, w11, w12 = w2c[1, 0], w2c[1, 1], w2c[1, 2]
    w20, w21, w22 = w2c[2, 0], w2c[2, 1], w2c[2, 2]
    n_sh = (degree + 1) * (degree + 1)
    per = (m_rows + N_REDUCE - 1) // N_REDUCE
    for ch in nb.prange(N_REDUCE):
        pg = np.zeros(15)
        b = np.empty(16)
        gb = np.zeros(16)
        for q in range(ch * per, min(m_rows, (ch + 1) * per)):
            i = visible[q]
            j = rank[q]
            g_mx = 0.0
            g_my = 0.0
            g_A = 0.0
            g_B = 0.0
            g_C = 0.0
            g_o = 0.0
            g_r = 0.0
            g_g = 0.0
            g_b = 0.0
            for r in range(entry_start[q], entry_start[q + 1]):
                g_mx += entry_grads[r, 0]
                g_my += entry_grads[r, 1]
                g_A += entry_grads[r, 2]
                g_B += entry_grads[r, 3]
                g_C += entry_grads[r, 4]
                g_o += entry_grads[r, 5]
                g_r += entry_grads[r, 6]
                g_g += entry_grads[r, 7]
                g_b += entry_grads[r, 8]
            # density statistics (the torch path: |means2d.grad · (W/2, H/2)|)
            sx, sy = g_mx * half_w, g_my * half_h
            grad_accum[i] += math.sqrt(sx * sx + sy * sy)
            grad_count[i] += 1.0
            max_radius[i] = max(max_radius[i], radius[j])
            last_seen[i] = it
            # ---- forward recomputation
            mwx, mwy, mwz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
            x = w00 * mwx + w01 * mwy + w02 * mwz + w2c[0, 3]
            y = w10 * mwx + w11 * mwy + w12 * mwz + w2c[1, 3]
            z = w20 * mwx + w21 * mwy + w22 * mwz + w2c[2, 3]
            qw0, qx0, qy0, qz0 = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
            qn = max(math.sqrt(qw0 * qw0 + qx0 * qx0 + qy0 * qy0 + qz0 * qz0), 1e-12)
            qw, qx, qy, qz = qw0 / qn, qx0 / qn, qy0 / qn, qz0 / qn
            r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
            r01 = 2.0 * (qx * qy - qw * qz)
            r02 = 2.0 * (qx * qz + qw * qy)
            r10 = 2.0 * (qx * qy + qw * qz)
            r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
            r12 = 2.0 * (qy * qz - qw * qx)
            r20 = 2.0 * (qx * qz - qw * qy)
            r21 = 2.0 * (qy * qz + qw * qx)
            r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
            s0, s1, s2 = geom[i, 8], geom[i, 9], geom[i, 10]
            m00, m01, m02 = r00 * s0, r01 * s1, r02 * s2
            m10, m11, m12 = r10 * s0, r11 * s1, r12 * s2
            m20, m21, m22 = r20 * s0, r21 * s1, r22 * s2
            z = max(z, 1e-6)
            ux = x / z
            uy = y / z
            cux = min(max(ux, -lims[0]), lims[1])
            cuy = min(max(uy, -lims[2]), lims[3])
            tx = cux * z
            ty = cuy * z
            iz = 1.0 / z
            j00, j02 = fx * iz, -fx * tx * iz * iz
            j11, j12 = fy * iz, -fy * ty * iz * iz
            t00 = j00 * w00 + j02 * w20
            t01 = j00 * w01 + j02 * w21
            t02 = j00 * w02 + j02 * w22
            t10 = j11 * w10 + j12 * w20
            t11 = j11 * w11 + j12 * w21
            t12 = j11 * w12 + j12 * w22
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
            # ---- conic (A, B, C) = (cc, −cb, ca)/det → 2-D covariance (det clamp as the torch path)
            if det > 1e-12:
                id2 = 1.0 / (det * det)
                gca = (g_A * (-cc * cc) + g_B * (cb * cc) + g_C * (det - ca * cc)) * id2
                gcb = (g_A * (2.0 * cc * cb) + g_B * (-det - 2.0 * cb * cb) + g_C * (2.0 * ca * cb)) * id2
                gcc = (g_A * (det - cc * ca) + g_B * (cb * ca) + g_C * (-ca * ca)) * id2
            else:
                idt = 1e12
                gca = g_C * idt
                gcb = -g_B * idt
                gcc = g_A * idt
            # ---- covariance → P = T M (2×3)
            gp00 = 2.0 * gca * p00 + gcb * p10
            gp01 = 2.0 * gca * p01 + gcb * p11
            gp02 = 2.0 * gca * p02 + gcb * p12
            gp10 = 2.0 * gcc * p10 + gcb * p00
            gp11 = 2.0 * gcc * p11 + gcb * p01
            gp12 = 2.0 * gcc * p12 + gcb * p02
            # P = T M: dM = Tᵀ dP, dT = dP Mᵀ
            gm00 = t00 * gp00 + t10 * gp10
            gm01 = t00 * gp01 + t10 * gp11
            gm02 = t00 * gp02 + t10 * gp12
            gm10 = t01 * gp00 + t11 * gp10
            gm11 = t01 * gp01 + t11 * gp11
            gm12 = t01 * gp02 + t11 * gp12
            gm20 = t02 * gp00 + t12 * gp10
            gm21 = t02 * gp01 + t12 * gp11
            gm22 = t02 * gp02 + t12 * gp12
            gt00 = gp00 * m00 + gp01 * m01 + gp02 * m02
            gt01 = gp00 * m10 + gp01 * m11 + gp02 * m12
            gt02 = gp00 * m20 + gp01 * m21 + gp02 * m22
            gt10 = gp10 * m00 + gp11 * m01 + gp12 * m02
            gt11 = gp10 * m10 + gp11 * m11 + gp12 * m12
            gt12 = gp10 * m20 + gp11 * m21 + gp12 * m22
            # T = J W: dJ = dT Wᵀ (only J00, J02, J11, J12 vary); dW = Jᵀ dT
            gj00 = gt00 * w00 + gt01 * w01 + gt02 * w02
            gj02 = gt00 * w20 + gt01 * w21 + gt02 * w22
            gj11 = gt10 * w10 + gt11 * w11 + gt12 * w12
            gj12 = gt10 * w20 + gt11 * w21 + gt12 * w22
            # J(z, tx, ty)
            gz = (-gj00 * fx - gj11 * fy) * iz * iz + (gj02 * 2.0 * fx * tx + gj12 * 2.0 * fy * ty) * iz * iz * iz
            gtx = -gj02 * fx * iz * iz
            gty = -gj12 * fy * iz * iz
            gx = 0.0
            gy = 0.0
            # tx = clamp(x/z)·z: ∂/∂x = 1 inside the clamp, ∂/∂z = the clamped value outside
            if -lims[0] <= ux <= lims[1]:
                gx += gtx
            else:
                gz += gtx * cux
            if -lims[2] <= uy <= lims[3]:
                gy += gty
            else:
                gz += gty * cuy
            # means2d = (fx x/z + cx, fy y/z + cy)
            gx += g_mx * fx * iz
            gy += g_my * fy * iz
            gz -= (g_mx * fx * x + g_my * fy * y) * iz * iz
            # M = R diag(s)
            gr00, gr01, gr02 = gm00 * s0, gm01 * s1, gm02 * s2
            gr10, gr11, gr12 = gm10 * s0, gm11 * s1, gm12 * s2
            gr20, gr21, gr22 = gm20 * s0, gm21 * s1, gm22 * s2
            g_log_scales[i, 0] = (gm00 * r00 + gm10 * r10 + gm20 * r20) * s0
            g_log_scales[i, 1] = (gm01 * r01 + gm11 * r11 + gm21 * r21) * s1
            g_log_scales[i, 2] = (gm02 * r02 + gm12 * r12 + gm22 * r22) * s2
            # R(q̂)
            gqw = 2.0 * (-qz * gr01 + qy * gr02 + qz * gr10 - qx * gr12 - qy * gr20 + qx * gr21)
            gqx = 2.0 * (qy * gr01 + qz * gr02 + qy * gr10 - 2.0 * qx * gr11 - qw * gr12 + qz * gr20 + qw * gr21
                         - 2.0 * qx * gr22)
            gqy = 2.0 * (-2.0 * qy * gr00 + qx * gr01 + qw * gr02 + qx * gr10 + qz * gr12 - qw * gr20 + qz * gr21
                         - 2.0 * qy * gr22)
            gqz = 2.0 * (-2.0 * qz * gr00 - qw * gr01 + qx * gr02 + qw * gr10 - 2.0 * qz * gr11 + qy * gr12
                         + qx * gr20 + qy * gr21)
            dot = qw * gqw + qx * gqx + qy * gqy + qz * gqz
            g_quats[i, 0] = (gqw - qw * dot) / qn
            g_quats[i, 1] = (gqx - qx * dot) / qn
            g_quats[i, 2] = (gqy - qy * dot) / qn
            g_quats[i, 3] = (gqz - qz * dot) / qn
            # opacity = sigmoid(logit)
            opac = geom[i, 5]
            g_opacity[i] = g_o * opac * (1.0 - opac)
            # colour = max(0, SH(dir) + 0.5)
            gdx = 0.0
            gdy = 0.0
            gdz = 0.0
            if degree == 0:
                for c in range(3):
                    gc = g_r if c == 0 else (g_g if c == 1 else g_b)
                    g_sh_dc[i, 0, c] = gc * C0 if float(sh_dc[i, 0, c]) * C0 + 0.5 >= 0.0 else 0.0
                for m in range(g_sh_rest.shape[1]):
                    for c in range(3):
                        g_sh_rest[i, m, c] = 0.0
            else:
                vx = mwx - center[0]
                vy = mwy - center[1]
                vz = mwz - center[2]
                vn = max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-12)
                dx, dy, dz = vx / vn, vy / vn, vz / vn
                _sh_basis(dx, dy, dz, degree, b)
                for m in range(16):
                    gb[m] = 0.0
                for c in range(3):
                    gc = g_r if c == 0 else (g_g if c == 1 else g_b)
                    acc = b[0] * float(sh_dc[i, 0, c])
                    for m in range(1, n_sh):
                        acc += b[m] * float(sh_rest[i, m - 1, c])
                    if acc + 0.5 < 0.0:
                        gc = 0.0
                    g_sh_dc[i, 0, c] = gc * b[0]
                    for m in range(1, n_sh):
                        g_sh_rest[i, m - 1, c] = gc * b[m]
                        gb[m] += gc * float(sh_rest[i, m - 1, c])
                for m in range(n_sh - 1, g_sh_rest.shape[1]):
                    for c in range(3):
                        g_sh_rest[i, m, c] = 0.0
                gux, guy, guz = _sh_basis_vjp(dx, dy, dz, degree, gb)
                dd = dx * gux + dy * guy + dz * guz
                gdx = (gux - dx * dd) / vn
                gdy = (guy - dy * dd) / vn
                gdz = (guz - dz * dd) / vn
            # p = W·mean + t
            g_means[i, 0] = w00 * gx + w10 * gy + w20 * gz + gdx
            g_means[i, 1] = w01 * gx + w11 * gy + w21 * gz + gdy
            g_means[i, 2] = w02 * gx + w12 * gy + w22 * gz + gdz
            if want_pose:
                # dW from p = W mean + t and from T = J W (row 0 of J: J00, J02; row 1: J11, J12)
                pg[0] += gx * mwx + j00 * gt00
                pg[1] += gx * mwy + j00 * gt01
                pg[2] += gx * mwz + j00 * gt02
                pg[3] += gy * mwx + j11 * gt10
                pg[4] += gy * mwy + j11 * gt11
                pg[5] += gy * mwz + j11 * gt12
                pg[6] += gz * mwx + j02 * gt00 + j12 * gt10
                pg[7] += gz * mwy + j02 * gt01 + j12 * gt11
                pg[8] += gz * mwz + j02 * gt02 + j12 * gt12
                pg[9] += gx
                pg[10] += gy
                pg[11] += gz
                pg[12] -= gdx
                pg[13] -= gdy
                pg[14] -= gdz
        if want_pose:
            for c in range(15):
                pose_grads[ch, c] = pg[c]


@nb.njit(parallel=True, cache=True)
def adam_kernel(params, exp_avgs, exp_avg_sqs, grads, step_sizes, bc2, beta1, beta2, eps):
    """One Adam step of every parameter group (tuples of flat float32 arrays, one parallel region), the operations
    of :func:`~gsrmr_splat.optim.adam_step`: m ← β1·m + (1 − β1)·g, s ← β2·s + (1 − β2)·g²,
    param ← param − step_size·m / (sqrt(s / bc2) + eps), step_size = lr / bc1 of the group (``step_sizes``);
    ``grad`` is set back to zero (the engine's gradient buffers start each step at zero). Unsigned indices, so
    that LLVM vectorises the loop (a signed index's wrap-around test would stop it)."""
    b1 = np.float32(beta1)
    ob1 = np.float32(1.0 - beta1)
    b2 = np.float32(beta2)
    ob2 = np.float32(1.0 - beta2)
    bc = np.float32(bc2)
    ep = np.float32(eps)
    zero = np.float32(0.0)
    for ch in nb.prange(N_REDUCE):
        for g in range(len(params)):
            param, exp_avg, exp_avg_sq, grad = params[g], exp_avgs[g], exp_avg_sqs[g], grads[g]
            neg = np.float32(-step_sizes[g])
            n = param.shape[0]
            per = (n + N_REDUCE - 1) // N_REDUCE
            lo = np.uint64(min(n, ch * per))
            hi = np.uint64(min(n, ch * per + per))
            for e in range(lo, hi):
                gv = grad[e]
                m = exp_avg[e] * b1 + ob1 * gv
                s = exp_avg_sq[e] * b2 + ob2 * gv * gv
                exp_avg[e] = m
                exp_avg_sq[e] = s
                param[e] = param[e] + neg * m / (np.sqrt(s / bc) + ep)
                grad[e] = zero
