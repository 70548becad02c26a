"""The trocar-constrained re-solve of one instrument's shaft rows
(:func:`mistool.pose.refine._trocar_fusion`), one row at a time on scalars; and the
quaternion of every row's axis (:func:`quats_of_axes`, bit for bit).

Every dot product is summed left to right, where numpy's BLAS may use fused
multiply-adds: the results agree with the former numpy arithmetic to ~1e-13 mm on tracked
sequences (up to ~6e-9 relative in near-degenerate geometry),
not bit for bit (``tests/test_refine.py``)."""

from __future__ import annotations

import math

import numpy as np

from mistool.kernels import helper, kernel
from mistool.kernels.split import fma

#: Columns of the row values the kernel reads, in order.
FUSION_INPUTS = (
    "aux_l1a",
    "aux_l1b",
    "aux_l1c",
    "aux_l2a",
    "aux_l2b",
    "aux_l2c",
    "end_x_mm",
    "end_y_mm",
    "end_z_mm",
    "axis_x",
    "axis_y",
    "axis_z",
    "aux_su_px",
    "aux_sv_px",
    "aux_u_px",
    "aux_v_px",
    "aux_sigma_mm",
    "aux_sigma_deg",
)


@helper
def _unit_ray(K: np.ndarray, u: float, v: float, out: np.ndarray) -> None:
    """The unit viewing ray ``K^-1 (u, v, 1)`` (Gaussian elimination with partial
    pivoting, as LAPACK's solve)."""
    a = np.empty((3, 4))
    for i in range(3):
        for j in range(3):
            a[i, j] = K[i, j]
    a[0, 3] = u
    a[1, 3] = v
    a[2, 3] = 1.0
    for col in range(3):
        piv = col
        for i in range(col + 1, 3):
            if abs(a[i, col]) > abs(a[piv, col]):
                piv = i
        if piv != col:
            for j in range(4):
                tmp = a[col, j]
                a[col, j] = a[piv, j]
                a[piv, j] = tmp
        for i in range(col + 1, 3):
            f = a[i, col] / a[col, col]
            for j in range(col, 4):
                a[i, j] -= f * a[col, j]
    for i in range(2, -1, -1):
        s = a[i, 3]
        for j in range(i + 1, 3):
            s -= a[i, j] * out[j]
        out[i] = s / a[i, i]
    n = math.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2])
    for i in range(3):
        out[i] /= n


@helper
def _sigma_across(cov: np.ndarray, d0: float, d1: float, d2: float) -> float:
    """RMS 1-sigma of the trocar across the unit direction ``d``:
    ``sqrt(max(trace(P cov P), 0) / 2)`` with ``P = I - d d^T``."""
    d = (d0, d1, d2)
    tr = 0.0
    for i in range(3):  # (P cov P)_ii = sum_jk P_ij cov_jk P_ki
        for j in range(3):
            pij = (1.0 if i == j else 0.0) - d[i] * d[j]
            for k in range(3):
                pki = (1.0 if k == i else 0.0) - d[k] * d[i]
                tr += pij * cov[j, k] * pki
    return math.sqrt(max(tr, 0.0) / 2.0)


@helper
def _closest(ray: np.ndarray, p0: np.ndarray, a: np.ndarray) -> float:
    """Axial coordinate of the point of the axis ``(p0, a)`` closest to the ray."""
    da = ray[0] * a[0] + ray[1] * a[1] + ray[2] * a[2]
    dp = ray[0] * p0[0] + ray[1] * p0[1] + ray[2] * p0[2]
    ap = a[0] * p0[0] + a[1] * p0[1] + a[2] * p0[2]
    return (da * dp - ap) / max(1.0 - da * da, 1e-12)


@helper
def _one_line(
    line: np.ndarray,
    K: np.ndarray,
    T: np.ndarray,
    jray: np.ndarray,
    radius: float,
    J: np.ndarray,
    a: np.ndarray,
) -> int:
    """One limb line: the axis at ``radius`` from the line's tangent plane through the
    trocar (moved onto the plane) that meets the joint's ray; 1 with ``J``, ``a`` set,
    else 0."""
    n = np.empty(3)
    for j in range(3):
        n[j] = K[0, j] * line[0] + K[1, j] * line[1] + K[2, j] * line[2]
    nn = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    for j in range(3):
        n[j] /= nn
    off = n[0] * T[0] + n[1] * T[1] + n[2] * T[2] - radius
    p = np.empty(3)
    for j in range(3):
        p[j] = T[j] - off * n[j]
    denom = n[0] * jray[0] + n[1] * jray[1] + n[2] * jray[2]
    if abs(denom) < 1e-9:
        return 0
    scale = radius / denom
    if jray[2] * scale <= 0:
        return 0
    for j in range(3):
        a[j] = jray[j] * scale - p[j]
    nd = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    if nd < 1e-6:
        return 0
    for j in range(3):
        a[j] /= nd
    t = _closest(jray, p, a)
    for j in range(3):
        J[j] = p[j] + t * a[j]
    return 1


@helper
def _two_lines(
    row: np.ndarray,
    T: np.ndarray,
    cov: np.ndarray,
    max_sigma_deg: float,
    sig_j: float,
    J: np.ndarray,
    a: np.ndarray,
) -> int:
    """Two limb lines: the joint fused with the trocar line's, the direction with
    ``unit(J - T)``; 1 with ``J``, ``a`` set, else 0 (``J``, ``a`` hold the measured
    values on entry)."""
    sig_a = math.radians(row[17])
    have_a = (
        math.isfinite(a[0]) and math.isfinite(a[1]) and math.isfinite(a[2])
    ) and math.isfinite(sig_a)
    sig_j = max(sig_j, 0.05)
    if have_a:
        nj = math.sqrt(J[0] * J[0] + J[1] * J[1] + J[2] * J[2])
        jray = np.empty(3)
        for j in range(3):
            jray[j] = J[j] / nj
        t = _closest(jray, T, a)
        s_r = 0.0
        for j in range(3):
            s_r += jray[j] * (T[j] + t * a[j])
        ja = jray[0] * a[0] + jray[1] * a[1] + jray[2] * a[2]
        sin_ang = math.sqrt(max(1.0 - ja * ja, 1e-6))
        dx = J[0] - T[0]
        dy = J[1] - T[1]
        dz = J[2] - T[2]
        dist_jt = math.sqrt(dx * dx + dy * dy + dz * dz)
        sig_t = (dist_jt * max(sig_a, 1e-4) + _sigma_across(cov, a[0], a[1], a[2])) / sin_ang
        if s_r > 0:
            w_t = 1.0 / (sig_t * sig_t)
            w_m = 1.0 / (sig_j * sig_j)
            for j in range(3):
                J[j] = (w_t * s_r * jray[j] + w_m * J[j]) / (w_t + w_m)
            sig_j = 1.0 / math.sqrt(w_t + w_m)
    dx = J[0] - T[0]
    dy = J[1] - T[1]
    dz = J[2] - T[2]
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    at0 = dx / dist
    at1 = dy / dist
    at2 = dz / dist
    sig_at = math.hypot(sig_j, _sigma_across(cov, at0, at1, at2)) / dist
    if have_a and at0 * a[0] + at1 * a[1] + at2 * a[2] > 0:
        va = sig_a * sig_a
        vat = sig_at * sig_at
        b0 = a[0] / va + at0 / vat
        b1 = a[1] / va + at1 / vat
        b2 = a[2] / va + at2 / vat
        nb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        a[0] = b0 / nb
        a[1] = b1 / nb
        a[2] = b2 / nb
    elif not have_a and math.degrees(sig_at) <= max_sigma_deg:
        a[0] = at0
        a[1] = at1
        a[2] = at2
    else:
        return 0
    return 1


@kernel(
    "int64[::1](float64[:, ::1], float64[:, ::1], float64[::1], float64[:, ::1], float64,"
    " float64, float64[:, ::1])"
)
def trocar_fusion(
    rows: np.ndarray,
    K: np.ndarray,
    T: np.ndarray,
    cov: np.ndarray,
    radius: float,
    max_sigma_deg: float,
    out: np.ndarray,
) -> np.ndarray:
    """Re-solve each shaft row (``rows`` (N, 18), the :data:`FUSION_INPUTS` columns) with
    the trocar ``T`` (3,) of covariance ``cov`` (3, 3); camera ``K`` (3, 3), shaft
    ``radius`` (mm). Per row, ``out`` (N, 9) gets the joint, the axis and the proximal
    point; the result says what to write: 0 nothing, 1 joint and axis, 2 all three."""
    n = rows.shape[0]
    what = np.zeros(n, np.int64)
    J = np.empty(3)
    a = np.empty(3)
    sray = np.empty(3)
    jray = np.empty(3)
    line = np.empty(3)
    for r in range(n):
        v = rows[r]
        have0 = math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])
        have1 = math.isfinite(v[3]) and math.isfinite(v[4]) and math.isfinite(v[5])
        has_start = math.isfinite(v[12]) and math.isfinite(v[13])
        if has_start:
            _unit_ray(K, v[12], v[13], sray)
        for j in range(3):
            J[j] = v[6 + j]
            a[j] = v[9 + j]
        ok = 0
        if (
            have0
            and have1
            and math.isfinite(J[0])
            and math.isfinite(J[1])
            and math.isfinite(J[2])
            and math.isfinite(v[16])
        ):
            ok = _two_lines(v, T, cov, max_sigma_deg, v[16], J, a)
        elif have0 != have1 and math.isfinite(v[14]):
            for j in range(3):
                line[j] = v[j] if have0 else v[3 + j]
            _unit_ray(K, v[14], v[15], jray)
            ok = _one_line(line, K, T, jray, radius, J, a)
        if not ok:
            continue
        for j in range(3):
            out[r, j] = J[j]
            out[r, 3 + j] = a[j]
        what[r] = 1
        if has_start:
            t = _closest(sray, J, a)
            for j in range(3):
                out[r, 6 + j] = J[j] + t * a[j]
            what[r] = 2
    return what


@kernel("void(float64[:, ::1], int64[::1], float64[:, ::1])")
def quats_of_axes(ax: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """``quat_from_z(a / np.linalg.norm(a))`` (:mod:`mistool.pose.cylinder`) of each
    ``a = ax[r]``, ``r`` in ``rows``, into
    ``out[k]`` for ``rows[k]``, bit for bit: both dot products (``v.dot(v)`` of 3 and
    ``q @ q`` of 4 elements, OpenBLAS's ``ddot`` below 16 elements) as one multiply-add
    per element from 0 (:func:`mistool.kernels.split.dot2`'s order)."""
    for k in range(len(rows)):
        r = rows[k]
        a0, a1, a2 = ax[r, 0], ax[r, 1], ax[r, 2]
        n = math.sqrt(fma(a2, a2, fma(a1, a1, fma(a0, a0, 0.0))))
        z0, z1, z2 = a0 / n, a1 / n, a2 / n
        if z2 < -1.0 + 1e-12:
            out[k, 0], out[k, 1], out[k, 2], out[k, 3] = 0.0, 1.0, 0.0, 0.0
            continue
        q0, q1, q2, q3 = 1.0 + z2, -z1, z0, 0.0
        s = math.sqrt(fma(q3, q3, fma(q2, q2, fma(q1, q1, fma(q0, q0, 0.0)))))
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = q0 / s, q1 / s, q2 / s, q3 / s
