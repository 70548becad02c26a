"""The metric pose's faster pieces equal the definitions they replace, bit for bit
(issue 13: the per-frame pose's cost). Each ``_..._before`` is the code as it was at
commit 4f43a12. The pieces now in compiled kernels are compared with their numpy
definitions in ``tests/test_pose_kernels.py``."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.pose.cylinder import pixel_rays, quat_from_z


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)


@st.composite
def _points(draw: st.DrawFn) -> np.ndarray:
    """(N, 2) float64 points: any floats, or pixel centres / mid-points."""
    seed = draw(st.integers(0, 2**32 - 1))
    n = draw(st.sampled_from([1, 2, 3, 7, 64, 193, 700]))
    rng = np.random.default_rng(seed)
    p = rng.normal(300.0, 200.0, (n, 2))
    if draw(st.booleans()):
        p = np.round(2.0 * p) / 2.0
    return p


def _quat_before(z: np.ndarray) -> np.ndarray:
    c = float(z[2])
    if c < -1.0 + 1e-12:
        return np.array([0.0, 1.0, 0.0, 0.0])
    q = np.array([1.0 + c, -float(z[1]), float(z[0]), 0.0])
    return q / np.linalg.norm(q)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_quaternion_as_before(seed: int) -> None:
    z = np.random.default_rng(seed).normal(size=3)
    z /= np.linalg.norm(z)
    assert _same(quat_from_z(z), _quat_before(z))


def _pixel_rays_before(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    d = np.empty((len(uv), 3))
    d[:, 0] = (uv[:, 0] - K[0, 2]) / K[0, 0]
    d[:, 1] = (uv[:, 1] - K[1, 2]) / K[1, 1]
    d[:, 2] = 1.0
    d /= np.sqrt(d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + 1.0)[:, None]
    return d


@settings(max_examples=200, deadline=None)
@given(_points(), st.floats(100.0, 2000.0), st.floats(0.5, 2.0))
def test_pixel_rays_as_before(uv: np.ndarray, f: float, aspect: float) -> None:
    K = np.array([[f, 0.0, 359.5], [0.0, f * aspect, 287.5], [0.0, 0.0, 1.0]])
    assert _same(pixel_rays(uv, K), _pixel_rays_before(uv, K))
