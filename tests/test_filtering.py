"""The Kalman filter / RTS smoother of mistool.pose.filtering, written out on floats,
against the textbook matrix form (numpy 2x2 matrices) on random series with gaps."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.pose.filtering import _kalman_1d


def _matrix_form(t: np.ndarray, y: np.ndarray, r: np.ndarray, q: float, smooth: bool) -> np.ndarray:
    n = len(t)
    xs, ps = np.zeros((n, 2)), np.zeros((n, 2, 2))
    xp, pp = np.zeros((n, 2)), np.zeros((n, 2, 2))
    first = int(np.flatnonzero(np.isfinite(y))[0])
    x, P = np.array([y[first], 0.0]), np.diag([r[first] ** 2, 1e6])
    for k in range(n):
        if k > 0:
            dt = t[k] - t[k - 1]
            F = np.array([[1.0, dt], [0.0, 1.0]])
            Q = q * q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
            x, P = F @ x, F @ P @ F.T + Q
        xp[k], pp[k] = x, P
        if np.isfinite(y[k]):
            kg = P[:, 0] / (P[0, 0] + r[k] ** 2)
            x, P = x + kg * (y[k] - x[0]), P - np.outer(kg, P[0, :])
        xs[k], ps[k] = x, P
    if smooth:
        for k in range(n - 2, -1, -1):
            F = np.array([[1.0, t[k + 1] - t[k]], [0.0, 1.0]])
            c = ps[k] @ F.T @ np.linalg.inv(pp[k + 1])
            xs[k] = xs[k] + c @ (xs[k + 1] - xp[k + 1])
            ps[k] = ps[k] + c @ (ps[k + 1] - pp[k + 1]) @ c.T
    return xs[:, 0]


@pytest.mark.parametrize("smooth", [False, True])
def test_written_out_filter_equals_the_matrix_form(smooth: bool) -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        n = int(rng.integers(3, 300))
        t = np.cumsum(rng.uniform(0.02, 0.1, n))
        y = np.cumsum(rng.normal(0.0, 1.0, n)) * 10.0
        y[rng.random(n) < 0.2] = np.nan
        y[int(rng.integers(0, n))] = 3.0  # at least one measurement
        r = rng.uniform(0.1, 2.0, n)
        expected = _matrix_form(t, y, r, 300.0, smooth)
        np.testing.assert_allclose(_kalman_1d(t, y, r, 300.0, smooth), expected, rtol=1e-9)


def _former_kalman_1d(
    t: np.ndarray, y: np.ndarray, r: np.ndarray, q: float, smooth: bool
) -> np.ndarray:
    """As it was (e67ef6d). Constant-velocity Kalman filter (and RTS smoother) of one series.

    The 2x2 algebra is written out on Python floats: the same equations as the matrix
    form (x = F x, P = F P F^T + Q; gain on the position; RTS with C = P F^T Pp^-1), about
    7x faster than small numpy matrices (scripts/bench_throughput.py --stages, the
    refinement stage); results agree with the matrix form to ~1e-13 relative."""
    n = len(t)
    tl, yl, rl = t.tolist(), y.tolist(), r.tolist()
    seen = [math.isfinite(v) for v in yl]
    first = seen.index(True)
    x0, x1 = yl[first], 0.0
    p00, p01, p10, p11 = rl[first] ** 2, 0.0, 0.0, 1e6
    qq = q * q
    xs0, xs1 = [0.0] * n, [0.0] * n
    ps: list[tuple[float, float, float, float]] = [(0.0, 0.0, 0.0, 0.0)] * n
    xp: list[tuple[float, float]] = [(0.0, 0.0)] * n
    pp: list[tuple[float, float, float, float]] = [(0.0, 0.0, 0.0, 0.0)] * n
    for k in range(n):
        if k > 0:  # predict: F = [[1, dt], [0, 1]], Q = q^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]
            dt = tl[k] - tl[k - 1]
            x0 = x0 + dt * x1
            a00, a01 = p00 + dt * p10, p01 + dt * p11
            p00 = a00 + a01 * dt + qq * (dt**3 / 3)
            p01 = a01 + qq * (dt**2 / 2)
            p10 = p10 + p11 * dt + qq * (dt**2 / 2)
            p11 = p11 + qq * dt
        xp[k], pp[k] = (x0, x1), (p00, p01, p10, p11)
        if seen[k]:  # update with the position measurement
            s = p00 + rl[k] ** 2
            k0, k1 = p00 / s, p10 / s
            innov = yl[k] - x0
            x0, x1 = x0 + k0 * innov, x1 + k1 * innov
            p00, p01, p10, p11 = p00 - k0 * p00, p01 - k0 * p01, p10 - k1 * p00, p11 - k1 * p01
        xs0[k], xs1[k], ps[k] = x0, x1, (p00, p01, p10, p11)
    if smooth:
        for k in range(n - 2, -1, -1):
            dt = tl[k + 1] - tl[k]
            b00, b01, b10, b11 = ps[k]
            c00, c01, c10, c11 = b00 + b01 * dt, b01, b10 + b11 * dt, b11  # P F^T
            e00, e01, e10, e11 = pp[k + 1]
            det = e00 * e11 - e01 * e10
            i00, i01, i10, i11 = e11 / det, -e01 / det, -e10 / det, e00 / det
            g00, g01 = c00 * i00 + c01 * i10, c00 * i01 + c01 * i11  # C = P F^T Pp^-1
            g10, g11 = c10 * i00 + c11 * i10, c10 * i01 + c11 * i11
            d0, d1 = xs0[k + 1] - xp[k + 1][0], xs1[k + 1] - xp[k + 1][1]
            xs0[k] += g00 * d0 + g01 * d1
            xs1[k] += g10 * d0 + g11 * d1
            f00, f01, f10, f11 = ps[k + 1]
            h00, h01, h10, h11 = f00 - e00, f01 - e01, f10 - e10, f11 - e11
            m00, m01 = g00 * h00 + g01 * h10, g00 * h01 + g01 * h11  # C (P' - Pp)
            m10, m11 = g10 * h00 + g11 * h10, g10 * h01 + g11 * h11
            ps[k] = (
                b00 + m00 * g00 + m01 * g01,
                b01 + m00 * g10 + m01 * g11,
                b10 + m10 * g00 + m11 * g01,
                b11 + m10 * g10 + m11 * g11,
            )
    return np.array(xs0)


@settings(max_examples=150, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 60),
    st.floats(1e-4, 100.0),
    st.booleans(),
    st.booleans(),
)
def test_kalman_is_its_former_definition(seed, n, q, smooth, constant_r):
    """Irregular times, missing samples, per-sample or constant noise: the same
    positions, bit for bit, as the former filter (which also smoothed the covariances)."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.choice([0.04, 1 / 25, 0.08, 0.12, 1 / 3], n))
    y = np.cumsum(rng.normal(0.0, 2.0, n)) + rng.normal(0.0, 0.5, n)
    y[rng.random(n) < 0.2] = np.nan
    y[rng.integers(0, n)] = 1.5  # at least one sample
    r = np.full(n, rng.uniform(0.01, 3.0)) if constant_r else rng.uniform(0.01, 3.0, n)
    got = _kalman_1d(t, y, r, q, smooth)
    want = _former_kalman_1d(t, y, r, q, smooth)
    assert np.array_equal(got.view(np.int64), want.view(np.int64))
