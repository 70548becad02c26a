"""Closed-form cylinder pose from its two silhouette (limb) lines, and ray helpers.

A straight cylinder of radius ``r`` seen by a pinhole camera has two straight limb lines.
Each image line ``l = (a, b, c)`` (``a u + b v + c = 0`` in px) back-projects to a plane
through the camera centre with normal ``n = K^T l``; both planes are tangent to the
cylinder, so the axis is parallel to ``n1 x n2`` and lies at distance ``r`` from both planes
(Doignon & de Mathelin 2007; Cano et al. 2008). With both lines oriented so that the
shaft's pixels are on their positive side, the solution is unique:
``P0 = r (n1 + n2) / (1 + n1.n2)`` (the point of the axis closest to the camera centre's
"edge" line ``n1 x n2``), direction ``a = unit(n1 x n2)`` up to sign.

Conventions: camera frame OpenCV (x right, y down, z forward), millimetres; pixel centres
at integer coordinates. Lines are ``(3,)`` float64 with ``hypot(a, b) == 1`` and the shaft's
interior on the positive side.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = [
    "Vec3",
    "axis_from_image_lines",
    "axis_from_lines",
    "axis_from_normals",
    "axis_through_point",
    "closest_on_axis",
    "cross3",
    "pixel_rays",
    "plane_normal",
    "project",
    "quat_from_z",
    "ray_cylinder",
    "tangent_plane",
]


def cross3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross product of two (3,) vectors (``np.cross`` is slow on tiny inputs)."""
    return np.array(
        [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]
    )


def tangent_plane(line: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit normal of the plane through the camera centre that projects onto ``line``.

    Args:
        line: (3,) image line ``(a, b, c)`` in px, interior positive.
        K: (3, 3) intrinsic matrix.

    Returns:
        (3,) unit normal ``n``; a camera-frame point ``X`` in front of the camera projects on
        the interior side of ``line`` iff ``n . X > 0``.
    """
    n = K.T @ line
    return n / np.linalg.norm(n)


#: A 3-vector as plain floats: the closed forms below run per frame on 3-vectors, where
#: numpy's per-call overhead costs more than the arithmetic.
Vec3 = tuple[float, float, float]


def plane_normal(line: Sequence[float], K: Sequence[Sequence[float]]) -> Vec3:
    """:func:`tangent_plane` in plain floats: unit ``K^T line``.

    Args:
        line: image line ``(a, b, c)`` (px), interior positive.
        K: the 3x3 intrinsic matrix as nested sequences (``K.tolist()``).
    """
    (k00, k01, k02), (k10, k11, k12), (k20, k21, k22) = K
    a0, a1, a2 = line
    m0 = a0 * k00 + a1 * k10 + a2 * k20
    m1 = a0 * k01 + a1 * k11 + a2 * k21
    m2 = a0 * k02 + a1 * k12 + a2 * k22
    mn = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    return m0 / mn, m1 / mn, m2 / mn


def axis_from_normals(n1: Vec3, n2: Vec3, radius_mm: float) -> tuple[Vec3, Vec3] | None:
    """The cylinder axis tangent to two planes through the camera centre (the closed form;
    every axis-from-limb-lines solve in mistool goes through here).

    Args:
        n1, n2: unit plane normals, each oriented toward the cylinder.
        radius_mm: cylinder radius (mm).

    Returns:
        ``(P0, a)``: the axis point ``r (n1 + n2) / (1 + n1.n2)`` (mm) and the unit direction
        ``unit(n1 x n2)`` (sign arbitrary: callers orient it distally), or None when the
        planes are (nearly) parallel or opposite.
    """
    p, q, r = n1
    u, v, w = n2
    c = p * u + q * v + r * w
    if c <= -0.999999:  # opposite normals: the two lines coincide, no wedge
        return None
    cx, cy, cz = q * w - r * v, r * u - p * w, p * v - q * u
    sn = math.sqrt(cx * cx + cy * cy + cz * cz)
    if sn < 1e-9:
        return None
    f = radius_mm / (1.0 + c)
    return (f * (p + u), f * (q + v), f * (r + w)), (cx / sn, cy / sn, cz / sn)


def axis_from_image_lines(
    l1: Sequence[float], l2: Sequence[float], K: Sequence[Sequence[float]], radius_mm: float
) -> tuple[Vec3, Vec3] | None:
    """The cylinder axis from its two limb lines in the image (plain floats).

    ``axis_from_normals(plane_normal(l1, K), plane_normal(l2, K), radius_mm)``.
    """
    return axis_from_normals(plane_normal(l1, K), plane_normal(l2, K), radius_mm)


def axis_from_lines(
    n1: np.ndarray, n2: np.ndarray, radius_mm: float
) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`axis_from_normals` for (3,) numpy normals.

    Args:
        n1, n2: (3,) unit plane normals, each oriented toward the cylinder.
        radius_mm: cylinder radius (mm).

    Returns:
        ``(P0, a)``: (3,) point of the axis (mm) and (3,) unit direction (sign arbitrary,
        callers orient it distally), or None when the planes are (nearly) parallel.
    """
    x, y, z = n1.tolist()
    u, v, w = n2.tolist()
    sol = axis_from_normals((x, y, z), (u, v, w), radius_mm)
    if sol is None:
        return None
    return np.array(sol[0]), np.array(sol[1])


def axis_through_point(
    n1: np.ndarray, radius_mm: float, point: np.ndarray, ray: np.ndarray
) -> tuple[np.ndarray, np.ndarray] | None:
    """One-line solve: the axis at distance ``radius_mm`` from plane ``n1`` that passes
    through ``point`` (e.g. the trocar, moved onto the plane) and meets ``ray``.

    Args:
        n1: (3,) unit tangent-plane normal, oriented toward the cylinder.
        radius_mm: cylinder radius (mm).
        point: (3,) a point the axis passes through (mm).
        ray: (3,) direction of a pixel ray that meets the axis (e.g. the joint's pixel).

    Returns:
        ``(P0, a)`` with ``a`` from ``point`` toward the ray's point, or None.
    """
    p = point - (n1 @ point - radius_mm) * n1
    denom = float(n1 @ ray)
    if abs(denom) < 1e-9:
        return None
    q = ray * (radius_mm / denom)
    if q[2] <= 0:
        return None
    d = q - p
    nd = np.linalg.norm(d)
    if nd < 1e-6:
        return None
    return p, d / nd


def pixel_rays(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit viewing rays of pixels.

    Args:
        uv: (N, 2) pixel coordinates (px).
        K: (3, 3) intrinsic matrix.

    Returns:
        (N, 3) unit ray directions in the camera frame (z > 0).
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    d = np.empty((len(uv), 3))
    x, y = d[:, 0], d[:, 1]
    np.subtract(uv[:, 0], K[0, 2], out=x)
    x /= K[0, 0]
    np.subtract(uv[:, 1], K[1, 2], out=y)
    y /= K[1, 1]
    d[:, 2] = 1.0
    n = x * x
    n += y * y
    n += 1.0
    d /= np.sqrt(n, out=n)[:, None]
    return d


def project(X: np.ndarray, K: np.ndarray) -> np.ndarray:  # noqa: N803 - 3D points
    """Project camera-frame points (N, 3) mm to pixels (N, 2); z must be > 0."""
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    uv = np.empty((len(X), 2))
    uv[:, 0] = K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2]
    uv[:, 1] = K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]
    return uv


def ray_cylinder(
    rays: np.ndarray, p0: np.ndarray, a: np.ndarray, radius_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axial coordinates where rays from the camera centre enter and leave an infinite
    cylinder.

    Args:
        rays: (N, 3) unit ray directions.
        p0: (3,) point on the axis; axial coordinate ``t = (X - p0) . a``.
        a: (3,) unit axis direction.
        radius_mm: radius (mm).

    Returns:
        ``(t_in, t_out, hit)``: (N,) axial coordinates (mm) of the entry and exit points
        (for a ray that misses, both are the axial coordinate of the ray's closest approach
        to the axis) and (N,) bool, True where the ray really hits.
    """
    da = rays @ a
    dp = rays - da[:, None] * a
    w = -p0
    wa = float(w @ a)
    wp = w - wa * a
    A = np.einsum("ij,ij->i", dp, dp)
    B = dp @ wp
    C = float(wp @ wp) - radius_mm**2
    A = np.maximum(A, 1e-12)
    disc = B * B - A * C
    hit = disc >= 0
    sq = np.sqrt(np.maximum(disc, 0.0))
    s_in = (-B - sq) / A
    s_out = (-B + sq) / A
    t0 = -float(p0 @ a)
    return s_in * da + t0, s_out * da + t0, hit


def closest_on_axis(rays: np.ndarray, p0: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Axial coordinate of the axis point closest to each ray from the camera centre.

    Args:
        rays: (N, 3) unit ray directions.
        p0: (3,) point on the axis; a: (3,) unit axis direction.

    Returns:
        (N,) axial coordinates ``t`` (mm); the point is ``p0 + t a``.
    """
    # minimise |s d - (p0 + t a)|: [1, -da; -da, 1][s; t] = [d.p0; -a.p0]
    da = rays @ a
    dp = rays @ p0
    ap = float(a @ p0)
    den = np.maximum(1.0 - da * da, 1e-12)
    return (da * dp - ap) / den


def quat_from_z(z: np.ndarray) -> np.ndarray:
    """Quaternion ``wxyz`` of the shortest-arc rotation taking the camera's +z to ``z``.

    Roll about the axis is not observable from a cylinder's silhouette; the shortest arc
    is a stable convention (the part frame's +z is the part's axis). For ``z`` = -z_cam
    the rotation is 180 degrees about +x.

    Args:
        z: (3,) unit vector.

    Returns:
        (4,) unit quaternion ``(w, x, y, z)``.
    """
    c = float(z[2])
    if c < -1.0 + 1e-12:
        return np.array([0.0, 1.0, 0.0, 0.0])
    # axis = e_z x z = (-z_y, z_x, 0); q = (1 + c, axis) normalised
    q = np.array([1.0 + c, -float(z[1]), float(z[0]), 0.0])
    return q / math.sqrt(float(q @ q))  # np.linalg.norm(q), without its overhead
