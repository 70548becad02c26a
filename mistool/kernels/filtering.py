"""The constant-velocity Kalman filter and RTS smoother of one series
(:func:`mistool.pose.filtering.filter_series`), written out on scalars."""

from __future__ import annotations

import math

import numpy as np

from mistool.kernels import kernel


@kernel("float64[::1](float64[::1], float64[::1], float64[::1], float64, boolean, float64[::1])")
def kalman_1d(
    t: np.ndarray, y: np.ndarray, r: np.ndarray, q: float, smooth: bool, powers: np.ndarray
) -> np.ndarray:
    """Filtered (``smooth``: RTS-smoothed) positions of the series ``y`` (N,) at times
    ``t`` (N,), measurement noise ``r`` (N,) per sample, white acceleration ``q``; NaN
    samples are prediction only. State (position, velocity); ``F = [[1, dt], [0, 1]]``,
    ``Q = q^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]``, the gain on the position; RTS with
    ``C = P F^T Pp^-1``. The same scalar operations, in the same order, as the Python
    definition it replaces, so the same bits. ``powers`` must be ``[2.0, 3.0]``: Python's
    ``x ** 2`` calls the C library's ``pow``, which differs from ``x * x`` in the last bit
    for about 0.1% of inputs, and LLVM turns ``pow(x, 2.0)`` with a constant exponent into
    ``x * x``; exponents given as data keep the library's ``pow``. Needs at least one
    finite sample."""
    two = powers[0]
    three = powers[1]
    n = t.shape[0]
    first = 0
    while not math.isfinite(y[first]):
        first += 1
    x0 = y[first]
    x1 = 0.0
    p00 = math.pow(r[first], two)
    p01 = 0.0
    p10 = 0.0
    p11 = 1e6
    qq = q * q
    xs0 = np.zeros(n)
    xs1 = np.zeros(n)
    # kept for the backward pass: filtered P, predicted x and P
    m = n if smooth else 0
    ps = np.zeros((m, 4))
    xp = np.zeros((m, 2))
    pp = np.zeros((m, 4))
    for k in range(n):
        if k > 0:
            dt = t[k] - t[k - 1]
            x0 = x0 + dt * x1
            a00 = p00 + dt * p10
            a01 = p01 + dt * p11
            q01 = qq * (math.pow(dt, two) / 2)
            p00 = a00 + a01 * dt + qq * (math.pow(dt, three) / 3)
            p01 = a01 + q01
            p10 = p10 + p11 * dt + q01
            p11 = p11 + qq * dt
        if smooth:
            xp[k, 0] = x0
            xp[k, 1] = x1
            pp[k, 0] = p00
            pp[k, 1] = p01
            pp[k, 2] = p10
            pp[k, 3] = p11
        if math.isfinite(y[k]):
            s = p00 + math.pow(r[k], two)
            k0 = p00 / s
            k1 = p10 / s
            innov = y[k] - x0
            x0 = x0 + k0 * innov
            x1 = x1 + k1 * innov
            n00 = p00 - k0 * p00
            n01 = p01 - k0 * p01
            n10 = p10 - k1 * p00
            n11 = p11 - k1 * p01
            p00, p01, p10, p11 = n00, n01, n10, n11
        xs0[k] = x0
        xs1[k] = x1
        if smooth:
            ps[k, 0] = p00
            ps[k, 1] = p01
            ps[k, 2] = p10
            ps[k, 3] = p11
    if smooth:
        for k in range(n - 2, -1, -1):
            dt = t[k + 1] - t[k]
            b00 = ps[k, 0]
            b01 = ps[k, 1]
            b10 = ps[k, 2]
            b11 = ps[k, 3]
            c00 = b00 + b01 * dt
            c10 = b10 + b11 * dt
            e00 = pp[k + 1, 0]
            e01 = pp[k + 1, 1]
            e10 = pp[k + 1, 2]
            e11 = pp[k + 1, 3]
            det = e00 * e11 - e01 * e10
            i00 = e11 / det
            i01 = -e01 / det
            i10 = -e10 / det
            i11 = e00 / det
            d0 = xs0[k + 1] - xp[k + 1, 0]
            d1 = xs1[k + 1] - xp[k + 1, 1]
            xs0[k] += (c00 * i00 + b01 * i10) * d0 + (c00 * i01 + b01 * i11) * d1
            xs1[k] += (c10 * i00 + b11 * i10) * d0 + (c10 * i01 + b11 * i11) * d1
    return xs0
