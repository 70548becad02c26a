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

__all__ = ["MODES", "filter_series", "median", "noise_scale"]

MODES = ("none", "offline", "online")


def median(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a 1-D float64 array, the same value without
    ``np.median``'s dispatch (~20 us a call, most of a short series' cost): one
    ``np.partition`` (the middle element(s), and the largest, where a NaN goes), then
    the middle one or the mean of the middle two as ``np.mean`` takes it: the sum from
    ``+0.0`` (a zero sum is ``+0.0``), divided by the count."""
    n = len(values)
    if n == 0:
        return float(np.median(values))  # NaN, with numpy's warning
    h = n // 2
    part = np.partition(values, (h, n - 1) if n % 2 else (h - 1, h, n - 1))
    if math.isnan(part[n - 1]):
        return math.nan
    if n % 2:
        return float(part[h]) + 0.0
    return (float(part[h - 1]) + float(part[h]) + 0.0) / 2


def noise_scale(y: np.ndarray, floor: float) -> float:
    """Per-frame noise standard deviation of a 1-D series from its second differences."""
    y = y[np.isfinite(y)]
    if len(y) < 4:
        return floor
    d2 = y[2:] - 2.0 * y[1:-1] + y[:-2]
    return max(1.4826 * median(np.abs(d2 - median(d2))) / np.sqrt(6.0), floor)


#: The exponents the filter's kernel takes as data (see ``kalman_1d``'s docstring).
_POWERS = np.array([2.0, 3.0])


def _kalman_1d(t: np.ndarray, y: np.ndarray, r: np.ndarray, q: float, smooth: bool) -> np.ndarray:
    """Constant-velocity Kalman filter (and RTS smoother) of one series: positions (N,).

    The 2x2 algebra written out on scalars and compiled
    (:func:`mistool.kernels.filtering.kalman_1d`, about 25x the former Python loop on
    600 samples): the same equations as the matrix form (x = F x, P = F P F^T + Q; gain
    on the position; RTS with C = P F^T Pp^-1), results agree with it to ~1e-13
    relative, and bit for bit with the former Python loop (``tests/test_filtering.py``).
    Only the smoothed positions are returned; the RTS state update needs the filtered and
    predicted covariances only, so the smoothed covariances are not computed."""
    from mistool.kernels.filtering import kalman_1d  # numba: imported at the first use

    return kalman_1d(
        np.ascontiguousarray(t, np.float64),
        np.ascontiguousarray(y, np.float64),
        np.ascontiguousarray(r, np.float64),
        float(q),
        bool(smooth),
        _POWERS,
    )


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
