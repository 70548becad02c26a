"""The Kalman filter / RTS smoother of mistool.pose.filtering, written out on floats,
against the textbook matrix form (numpy 2x2 matrices) on random series with gaps."""

from __future__ import annotations

import numpy as np
import pytest

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
