"""Temporal filtering of per-frame metric estimates: a constant-velocity Kalman filter.

- ``"online"``: the causal forward filter (each estimate uses only past and current
  frames: what a live system can output; it lags slightly behind fast motion).
- ``"offline"``: the Rauch-Tung-Striebel smoother, i.e. the same filter run forward and
  then backward; zero-phase (no lag), for recorded sequences.
- ``"none"``: the per-frame estimates unchanged.

Each coordinate is filtered independently with state (position, velocity), white
acceleration of standard deviation ``accel`` (units/s^2) and a measurement noise
estimated from the data itself: the robust (median absolute deviation) scale of the
series' second differences divided by sqrt(6), which is the per-frame noise for white
noise on smooth motion (offline: over the whole track; online: over the last 250 samples
seen so far, so that the online output never depends on the future). NaN measurements are
skipped (prediction only); gaps longer than ``max_gap_s`` start a new track so that a tool
leaving and coming back is not smeared.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MODES", "filter_series", "noise_scale"]

MODES = ("none", "offline", "online")


def noise_scale(y: np.ndarray, floor: float) -> float:
    """Per-frame noise standard deviation of a 1-D series from its second differences."""
    y = y[np.isfinite(y)]
    if len(y) < 4:
        return floor
    d2 = y[2:] - 2.0 * y[1:-1] + y[:-2]
    return max(1.4826 * float(np.median(np.abs(d2 - np.median(d2)))) / np.sqrt(6.0), floor)


def _kalman_1d(t: np.ndarray, y: np.ndarray, r: np.ndarray, q: float, smooth: bool) -> np.ndarray:
    """Constant-velocity Kalman filter (and RTS smoother) of one series.

    The 2x2 algebra is written out on Python floats: the same equations as the matrix
    form (x = F x, P = F P F^T + Q; gain on the position; RTS with C = P F^T Pp^-1), about
    7x faster than small numpy matrices (scripts/bench_throughput.py --stages, the
    refinement stage); results agree with the matrix form to ~1e-13 relative.

    Only the smoothed positions are returned, and the RTS state update needs the filtered
    and predicted covariances only, so the smoothed covariances are not computed (the
    same positions, bit for bit: ``tests/test_filtering.py``)."""
    n = len(t)
    tl, yl = t.tolist(), y.tolist()
    r2 = [v**2 for v in r.tolist()]
    seen = [math.isfinite(v) for v in yl]
    first = seen.index(True)
    x0, x1 = yl[first], 0.0
    p00, p01, p10, p11 = r2[first], 0.0, 0.0, 1e6
    qq = q * q
    xs0, xs1 = [0.0] * n, [0.0] * n
    if smooth:  # kept for the backward pass: filtered P, predicted x and P
        ps: list[tuple[float, float, float, float]] = [(0.0, 0.0, 0.0, 0.0)] * n
        xp0, xp1 = [0.0] * n, [0.0] * n
        pp: list[tuple[float, float, float, float]] = [(0.0, 0.0, 0.0, 0.0)] * n
    for k in range(n):
        if k > 0:  # predict: F = [[1, dt], [0, 1]], Q = q^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]]
            dt = tl[k] - tl[k - 1]
            x0 = x0 + dt * x1
            a00, a01 = p00 + dt * p10, p01 + dt * p11
            q01 = qq * (dt**2 / 2)
            p00 = a00 + a01 * dt + qq * (dt**3 / 3)
            p01 = a01 + q01
            p10 = p10 + p11 * dt + q01
            p11 = p11 + qq * dt
        if smooth:
            xp0[k], xp1[k], pp[k] = x0, x1, (p00, p01, p10, p11)
        if seen[k]:  # update with the position measurement
            s = p00 + r2[k]
            k0, k1 = p00 / s, p10 / s
            innov = yl[k] - x0
            x0, x1 = x0 + k0 * innov, x1 + k1 * innov
            p00, p01, p10, p11 = p00 - k0 * p00, p01 - k0 * p01, p10 - k1 * p00, p11 - k1 * p01
        xs0[k], xs1[k] = x0, x1
        if smooth:
            ps[k] = (p00, p01, p10, p11)
    if smooth:
        for k in range(n - 2, -1, -1):
            dt = tl[k + 1] - tl[k]
            b00, b01, b10, b11 = ps[k]
            c00, c10 = b00 + b01 * dt, b10 + b11 * dt  # P F^T = [[c00, b01], [c10, b11]]
            e00, e01, e10, e11 = pp[k + 1]
            det = e00 * e11 - e01 * e10
            i00, i01, i10, i11 = e11 / det, -e01 / det, -e10 / det, e00 / det
            d0, d1 = xs0[k + 1] - xp0[k + 1], xs1[k + 1] - xp1[k + 1]
            # C = P F^T Pp^-1; x += C d
            xs0[k] += (c00 * i00 + b01 * i10) * d0 + (c00 * i01 + b01 * i11) * d1
            xs1[k] += (c10 * i00 + b11 * i10) * d0 + (c10 * i01 + b11 * i11) * d1
    return np.array(xs0)


def filter_series(
    t: np.ndarray,
    y: np.ndarray,
    mode: str,
    accel: float,
    noise_floor: float,
    max_gap_s: float = 0.4,
) -> np.ndarray:
    """Filter a (N, D) series sampled at times ``t`` (N,) seconds, rows in time order.

    Args:
        t: (N,) strictly increasing times (s).
        y: (N, D) values; NaN rows (or cells) are missing measurements.
        mode: ``"none"``, ``"online"`` or ``"offline"``.
        accel: white-acceleration standard deviation (units/s^2).
        noise_floor: lower bound of the estimated measurement noise (units).
        max_gap_s: a gap between valid measurements longer than this splits the track.

    Returns:
        (N, D) filtered values; NaN where the input had no measurement.
    """
    y = np.asarray(y, dtype=np.float64)
    if mode == "none" or len(t) == 0:
        return y.copy()
    if mode not in MODES:
        raise ValueError(f"mode = {mode!r}: choose one of {', '.join(MODES)}")
    out = np.full_like(y, np.nan)
    valid_rows = np.all(np.isfinite(y), axis=1)
    idx = np.flatnonzero(valid_rows)
    if len(idx) == 0:
        return out
    breaks = np.flatnonzero(np.diff(t[idx]) > max_gap_s) + 1
    for seg in np.split(idx, breaks):
        if len(seg) < 3:
            out[seg] = y[seg]
            continue
        ts = t[seg]
        for d in range(y.shape[1]):
            ys = y[seg, d]
            if mode == "offline":
                r = np.full(len(ys), noise_scale(ys, noise_floor))
            else:  # causal: the noise scale from the (last 250) samples seen so far
                r = np.array(
                    [noise_scale(ys[max(0, k - 249) : k + 1], noise_floor) for k in range(len(ys))]
                )
            out[seg, d] = _kalman_1d(ts, ys, r, accel, smooth=(mode == "offline"))
    return out
