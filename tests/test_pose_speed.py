"""The metric pose's faster pieces equal the definitions they replace, bit for bit
(issue 13: the per-frame pose's cost). Each ``_..._before`` is the code as it was at
commit 4f43a12. The pieces now in compiled kernels are compared with their numpy
definitions in ``tests/test_pose_kernels.py``."""

from __future__ import annotations

import functools
import math
from typing import Any

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


# -- the compiled kernels' faster pieces (tenth session) against their former code -------


def _kth(v: np.ndarray, k: int) -> float:
    """``mistool.kernels.pose._kth`` (a helper: called from a kernel) on a copy of ``v``."""
    import numba

    from mistool.kernels.pose import _kth as kth

    call = numba.njit(lambda buf, n, k: kth(buf, n, k))
    buf = np.empty(2 * len(v))
    buf[: len(v)] = v
    return float(call(buf, len(v), k))


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 3, 5, 8, 81, 192, 900]))
def test_kth_equals_numpy_and_the_former_select(seed: int, n: int) -> None:
    """The branch-free selection of the line fit's scale gives the element of rank k, as
    the quickselect it replaces: ties, runs, sorted and reversed input, all equal."""
    from mistool.kernels import pose as kp

    rng = np.random.default_rng(seed)
    v = np.abs(rng.normal(size=n))
    kind = int(rng.integers(5))
    if kind == 1:
        v = np.round(v * 3.0)  # many ties
    elif kind == 2:
        v = np.sort(v)[:: rng.choice([-1, 1])]
    elif kind == 3:
        v = np.full(n, 0.7)
    elif kind == 4:
        v = np.concatenate([np.sort(p)[:: rng.choice([-1, 1])] for p in np.array_split(v, 4)])
    for k in {0, n - 1, n // 2, int(rng.integers(n))}:
        got = _kth(v, k)
        assert got == np.partition(v, k)[k] == kp._select(v.copy(), k)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([8, 9, 30, 191, 192]), st.booleans())
def test_fit_line_as_before_bit_for_bit(seed: int, n: int, pixels: bool) -> None:
    """``fit_line`` with the branch-free scale selection: the same line, RMS and inliers
    as the former kernel, bit for bit."""
    import pose_kernels_before as before_k

    from mistool.kernels import pose as kp

    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, 300.0, n))
    phi = rng.uniform(0.0, np.pi)
    pts = np.stack([100 + t * np.cos(phi), 200 + t * np.sin(phi)], axis=1)
    pts += rng.normal(0.0, rng.choice([0.05, 0.4, 1.5]), pts.shape)
    out = rng.random(n) < 0.2
    pts[out] += rng.normal(0.0, 8.0, (int(out.sum()), 2))  # outliers
    if pixels:
        pts = np.round(2.0 * pts) / 2.0
    along = pts @ np.array([np.cos(phi), np.sin(phi)])
    px, py = pts[:, 0].copy(), pts[:, 1].copy()
    got, ref = np.full(4, np.nan), np.full(4, np.nan)
    gi, ri = np.zeros(n, np.int64), np.zeros(n, np.int64)
    k_got = kp.fit_line(px, py, along, 1.5, 12, got, gi)
    k_ref = before_k.fit_line(px, py, along, 1.5, 12, ref, ri)
    assert k_got == k_ref
    assert got.tobytes() == ref.tobytes()
    assert np.array_equal(gi[: max(k_got, 0)], ri[: max(k_ref, 0)])


@st.composite
def _jaw_case(draw: st.DrawFn) -> tuple:  # type: ignore[type-arg]
    """A clasper-like crop (blobs and lines, some noise), a pixel of it, a disc radius
    and a direction."""
    import cv2

    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    h, w = (int(v) for v in rng.integers(1, 120, 2))
    m = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(1, 4))):
        a = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        b = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        if rng.random() < 0.5:
            cv2.line(m, a, b, 1, int(rng.integers(1, 12)))
        else:
            axes = (int(rng.integers(1, w + 1)), int(rng.integers(1, h + 1)))
            cv2.ellipse(m, a, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    if rng.random() < 0.3:
        m ^= (rng.random((h, w)) < 0.15).astype(np.uint8)
    cx, cy = int(rng.integers(-5, w + 5)), int(rng.integers(-5, h + 5))
    rad = float(rng.choice([0.5, 1.0, rng.uniform(1.0, 80.0)]))
    u = rng.normal(size=2)
    off = (int(rng.integers(0, 600)), int(rng.integers(0, 500)))
    return m.view(bool), off, cx, cy, rad, float(u[0]), float(u[1]), float(rng.uniform(1, 30))


@settings(max_examples=400, deadline=None)
@given(_jaw_case())
def test_jaw_axis_as_before_bit_for_bit(case: tuple) -> None:  # type: ignore[type-arg]
    """A jaw's axis from the disc's pixels as row runs (its extents from each run's two
    ends): the same end, direction and half-width as the former pixel-by-pixel kernel."""
    import pose_kernels_before as before_k

    from mistool.kernels import pose as kp

    mask, (ox, oy), cx, cy, rad, ux, uy, width = case
    got, ref = np.full(5, np.nan), np.full(5, np.nan)
    a = kp._jaw_axis(mask, ox, oy, cx, cy, rad, ux, uy, width, got)
    b = before_k.jaw_axis(mask, ox, oy, cx, cy, rad, ux, uy, width, ref)
    assert a == b
    assert got.tobytes() == ref.tobytes()


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2]))
def test_iou_count_as_before(seed: int, st_: int) -> None:
    """The IoU's byte counts eight bytes at a time (a canvas of step 2: eight samples of
    every other mask byte at a time, ``_ones_both_step2``): the same counts as the former
    loops (canvas and mask of any sizes and overlaps, both strides)."""
    import pose_kernels_before as before_k

    from mistool.kernels import pose as kp

    rng = np.random.default_rng(seed)
    hc, wc = (int(v) for v in rng.integers(0, 300, 2))
    rend = (rng.random((hc, wc)) < rng.uniform(0, 1)).astype(np.uint8)
    mh, mw = (int(v) for v in rng.integers(1, 400, 2))
    mask = rng.random((mh, mw)) < rng.uniform(0, 1)
    x0, y0 = (int(v) for v in rng.integers(0, 200, 2))
    ox, oy = x0 + int(rng.integers(-150, 150)), y0 + int(rng.integers(-150, 150))
    got = kp.iou_count(rend, mask, ox, oy, x0, y0, st_)
    ref = before_k.iou_count(rend, mask, ox, oy, x0, y0, st_)
    assert np.float64(got).tobytes() == np.float64(ref).tobytes()


# -- the eleventh session's pieces against their former code (5bd7ced) -------------------


@functools.cache
def _wrapped() -> dict[str, Any]:
    """The helpers under test, each in a small compiled function (a helper is called from
    kernels), compiled once for the module's tests."""
    import numba

    from mistool.kernels import contours as kc
    from mistool.kernels import polygon as kg
    from mistool.kernels import pose as kp

    return {
        "trace": numba.njit(
            lambda flat, h, w, x0, y0, pts, start: kc._trace(flat, h, w, x0, y0, pts, start)
        ),
        "next_change": numba.njit(
            lambda flat, i, end, inside: kc._next_change(flat, i, end, inside)
        ),
        "jaw_picks": numba.njit(
            lambda ci, ox, oy, ju, jv, wd, p: kp._jaw_picks(ci, ox, oy, ju, jv, wd, p)
        ),
        "vmax_vmin": numba.njit(lambda v: (kp._vmax(v), kp._vmin(v))),
        "sorted_points": numba.njit(lambda pts: kg._sorted_points(pts)),
        "inserted": numba.njit(lambda pts: kg._inserted(pts)),
        "median_in": numba.njit(lambda v, n, stride: kp._median_in(v, n, stride, np.empty(2 * n))),
        "across_gap": numba.njit(
            lambda outline, shaft, sx, sy, o1, x1, y1, o2, x2, y2, n, hh, ww, rows: kp._across_gap(
                outline, shaft, sx, sy, o1, x1, y1, o2, x2, y2, n, hh, ww, rows
            )
        ),
        "max_min": numba.njit(lambda v: (v.max(), v.min())),
    }


def _masks(seed: int) -> np.ndarray:
    """A 0/1 crop: blobs, lines, noise, single pixels, pieces touching the crop's edges."""
    import cv2

    rng = np.random.default_rng(seed)
    h, w = (int(v) for v in rng.integers(1, 90, 2))
    m = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(0, 5))):
        a = (int(rng.integers(-5, w + 5)), int(rng.integers(-5, h + 5)))
        b = (int(rng.integers(-5, w + 5)), int(rng.integers(-5, h + 5)))
        kind = rng.random()
        if kind < 0.4:
            cv2.line(m, a, b, 1, int(rng.integers(1, 9)))
        elif kind < 0.8:
            axes = (int(rng.integers(1, w + 1)), int(rng.integers(1, h + 1)))
            cv2.ellipse(m, a, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        else:
            m[a[1] % h, a[0] % w] = 1
    if rng.random() < 0.3:
        m ^= (rng.random((h, w)) < rng.uniform(0.02, 0.6)).astype(np.uint8)
    return m


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_contour_trace_as_before(seed: int) -> None:
    """The contour tracing with its flat index carried along (unsigned, moved by each
    chain code's offset): the same points as the former kernel from every component's
    first pixel, and the same answer when the points do not fit."""
    import cv2
    import pose_kernels_before as before_k

    trace = _wrapped()["trace"]
    m = _masks(seed)
    h, w = m.shape
    flat = m.ravel()
    rng = np.random.default_rng(seed)
    n_comp, lab = cv2.connectedComponents(m, connectivity=8)
    for c in range(1, n_comp):
        ys, xs = np.nonzero(lab == c)
        x0, y0 = int(xs[0]), int(ys[0])  # its first pixel in raster order
        start = int(rng.integers(0, 4))
        size = start + (4 * h * w + 4 if rng.random() < 0.8 else int(rng.integers(0, 12)))
        got = np.full((size, 2), -7, np.int32)
        ref = got.copy()
        a = trace(flat, h, w, x0, y0, got, start)
        b = before_k.trace(flat, h, w, x0, y0, ref, start)
        assert a == b
        assert np.array_equal(got, ref)


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_next_change_equals_its_definition(seed: int) -> None:
    """The row scan passing over 32 bytes at a time: the first index from ``i`` below
    ``end`` whose byte is zero (inside) or non-zero (outside), ``end`` for none; also on
    bytes other than 0 and 1."""
    nxt = _wrapped()["next_change"]
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 300))
    runs = rng.integers(1, rng.choice([3, 40, 120]), n + 1)  # alternate 0 and 1 runs
    v = np.repeat((np.arange(n + 1) + int(rng.integers(2))) % 2, runs)[:n].astype(np.uint8)
    flips = rng.random(n) < rng.choice([0.0, 0.01, 0.3])
    v = (v ^ flips).astype(np.uint8)
    if rng.random() < 0.2:
        v = v * rng.integers(1, 256, n).astype(np.uint8)
    for _ in range(20):
        i = int(rng.integers(0, n + 1))
        end = int(rng.integers(i, n + 1))
        inside = bool(rng.random() < 0.5)
        ref = i
        while ref < end and (v[ref] != 0) == inside:
            ref += 1
        assert nxt(v, i, end, inside) == ref


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_jaw_picks_as_before(seed: int) -> None:
    """The jaw ends' picks with each window's two neighbours looked at first and the few
    candidates sorted in place: the same picks, in the same order, as the former code
    (outlines of random crops, J anywhere, widths from 0 to 40 px)."""
    import cv2
    import pose_kernels_before as before_k

    picks_new = _wrapped()["jaw_picks"]
    rng = np.random.default_rng(seed)
    m = _masks(seed)
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    outlines = [c.reshape(-1, 2).astype(np.int32) for c in contours]
    outlines.append(rng.integers(0, 30, (int(rng.integers(0, 9)), 2)).astype(np.int32))
    for ci in outlines:
        ci = np.ascontiguousarray(ci)
        ox, oy = float(rng.integers(0, 600)), float(rng.integers(0, 500))
        ju, jv = ox + float(rng.uniform(-60, 150)), oy + float(rng.uniform(-60, 150))
        if rng.random() < 0.3:
            ju, jv = float(np.round(ju)), float(np.round(jv))
        width = float(rng.choice([0.0, 1.0, 2.5, rng.uniform(0.0, 40.0)]))
        got = np.full(2, -1, np.int64)
        ref = got.copy()
        a = picks_new(ci, ox, oy, ju, jv, width, got)
        b = before_k.jaw_picks(ci, ox, oy, ju, jv, width, ref)
        assert a == b
        assert np.array_equal(got, ref)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 7, 48, 301]), st.booleans())
def test_vmax_vmin_equal_numbas_reductions(seed: int, n: int, single: bool) -> None:
    """The plain max / min loops give numba's ``a.max()`` / ``a.min()`` bit for bit:
    the first NaN, the first of equal extremes (signed zeros), float32 columns too."""
    rng = np.random.default_rng(seed)
    a = rng.choice([-0.0, 0.0, 1.5, -2.25, np.inf, -np.inf], (n, 2))
    if rng.random() < 0.5:
        a = rng.normal(0.0, 100.0, (n, 2))
    if rng.random() < 0.3:
        a[rng.random((n, 2)) < 0.2] = np.nan
    if single:
        a = a.astype(np.float32)
    for col in (a[:, 0], np.ascontiguousarray(a[:, 1])):
        got = _wrapped()["vmax_vmin"](col)
        ref = _wrapped()["max_min"](col)
        for g, r in zip(got, ref, strict=True):
            assert np.asarray(g).tobytes() == np.asarray(r).tobytes()


# -- the twelfth session's pieces against their former code (37a36fc) -------------------


@settings(max_examples=500, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.booleans())
def test_tip_depth_as_before(seed: int, known: bool, near: bool) -> None:
    """The tip's depth with the arc cosine taken only where the length term alone does
    not exceed the cost at its own least: the same depth as the former loop over the
    whole grid (rays and joints anywhere, lengths, bends and widths of the grid from
    tiny to huge, ties; NaN and infinite inputs go through the whole grid)."""
    import pose_kernels_before as before_k

    from mistool.kernels import pose as kp

    rng = np.random.default_rng(seed)
    r = rng.normal(size=3)
    r /= np.linalg.norm(r)
    joint = rng.normal(0.0, 40.0, 3) + [0.0, 0.0, rng.uniform(-20.0, 150.0)]
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    if near:  # the tip's ray close to the clasper's end: a minimum inside the grid
        tip = joint + rng.uniform(5.0, 25.0) * a
        r = tip / np.linalg.norm(tip) + rng.normal(0.0, 0.01, 3)
        r /= np.linalg.norm(r)
    l_nom = float(rng.choice([10.0, 16.0, rng.uniform(0.0, 60.0), 0.0, 1e-300]))
    par = _params_array()
    par[kp.PARAMS.index("tip_bend_sigma_rad")] = float(
        rng.choice([math.radians(45.0), rng.uniform(1e-3, 3.0), 0.0])
    )
    par[kp.PARAMS.index("tip_length_sigma")] = float(rng.choice([0.05, rng.uniform(1e-4, 2.0)]))
    if rng.random() < 0.05:
        joint[int(rng.integers(3))] = rng.choice([math.nan, math.inf])
    if rng.random() < 0.05:
        l_nom = float(rng.choice([math.nan, math.inf]))
    args = (*r, *joint, *a, l_nom, known)
    got = kp._tip_depth(*args, par)
    ref = before_k.tip_depth(
        *args,
        par[kp.PARAMS.index("tip_bend_sigma_rad")],
        par[kp.PARAMS.index("tip_length_sigma")],
    )
    assert np.float64(got).tobytes() == np.float64(ref).tobytes()


def _params_array() -> np.ndarray:
    from mistool.pose.measure import _params

    return _params().copy()


@settings(max_examples=500, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300), st.sampled_from([1, 2]))
def test_median_in_equals_the_median(seed: int, n: int, stride: int) -> None:
    """The median from the branch-free selection (every ``stride``-th value): the
    former kernel's value and numpy's bit for bit, NaN and signed zeros included (they
    go through the former kernel), the values left as they were."""
    from mistool.kernels import pose as kp

    rng = np.random.default_rng(seed)
    kind = rng.random()
    if kind < 0.3:  # few distinct values: ties, zeros of both signs
        v = rng.choice([-0.0, 0.0, 1.5, -2.25, 3.0, 7.5], n * stride)
    elif kind < 0.6:
        v = np.round(rng.normal(300.0, 100.0, n * stride) * 2.0) / 2.0
    else:
        v = rng.normal(0.0, 1.0, n * stride)
    if rng.random() < 0.1:
        v[rng.random(n * stride) < 0.1] = np.nan
    if rng.random() < 0.2:
        v = np.abs(v)  # deviations: zeros of one sign
    keep = v.copy()
    got = _wrapped()["median_in"](v, n, stride)
    vals = keep[::stride][:n]
    assert np.array_equal(v, keep, equal_nan=True)
    assert np.float64(got).tobytes() == np.float64(kp._median(vals.copy())).tobytes()
    if not np.isnan(vals).any():
        assert got == np.median(vals)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_across_gap_as_before(seed: int) -> None:
    """The boundary across a junction gap with the grown other parts looked up only at
    the background neighbours of the outline (``_near_other_at``): the same points as
    the former code (the whole window grown, ``_near_others``, then ``shaft_boundary``
    with it as the other part), shafts and other parts of any shapes, near and far, at
    the image's edges."""
    import pose_kernels_before as before_k

    from mistool.kernels import contours as kc
    from mistool.kernels import pose as kp
    from mistool.pose.measure import _GAP_ROWS

    rng = np.random.default_rng(seed)
    shaft = _masks(seed).astype(bool)
    h, w = shaft.shape
    H, W = h + int(rng.integers(0, 60)), w + int(rng.integers(0, 60))
    sx, sy = int(rng.integers(0, W - w + 1)), int(rng.integers(0, H - h + 1))
    others = []
    for k in range(int(rng.integers(0, 3))):
        m = _masks(seed + 1000 + k).astype(bool)
        mh, mw = m.shape
        mx = int(np.clip(sx + rng.integers(-mw, w + 1), 0, max(W - mw, 0)))
        my = int(np.clip(sy + rng.integers(-mh, h + 1), 0, max(H - mh, 0)))
        m = m[: H - my, : W - mx]
        m &= ~_window(shaft, sx, sy, m.shape, mx, my)  # the parts do not overlap
        others.append((np.ascontiguousarray(m), mx, my))
    buf = np.empty((4 * h * w + 4, 2), np.int32)
    starts = np.empty(65, np.int64)
    n_pieces, _ = kc.external_contours(shaft, buf, starts)
    if n_pieces < 1:
        return
    outline = np.ascontiguousarray(buf[: starts[n_pieces]])
    none = np.zeros((0, 0), bool)
    (o1, x1, y1), (o2, x2, y2) = (others + [(none, 0, 0)] * 2)[:2]
    got = _wrapped()["across_gap"](
        outline, shaft, sx, sy, o1, x1, y1, o2, x2, y2, len(others), H, W, _GAP_ROWS
    )
    # the former code: the window labelled and grown as a whole, then shaft_boundary
    g = (len(_GAP_ROWS) - 1) // 2
    cx0, cy0 = max(sx - 2 - g, 0), max(sy - 2 - g, 0)
    cx1, cy1 = min(sx + w + 2 + g, W), min(sy + h + 2 + g, H)
    wx0, wy0, wx1, wy1 = cx1, cy1, cx0, cy0
    for m, mx, my in others:
        mh, mw = m.shape
        wx0, wy0 = min(wx0, max(mx, cx0)), min(wy0, max(my, cy0))
        wx1, wy1 = max(wx1, min(mx + mw, cx1)), max(wy1, min(my + mh, cy1))
    wx0, wy0 = max(wx0 - g, cx0), max(wy0 - g, cy0)
    wx1, wy1 = min(wx1 + g, cx1), min(wy1 + g, cy1)
    if wx0 >= wx1 or wy0 >= wy1:
        assert not got[0] and len(got[1]) == len(got[2]) == 0
        return
    lab = np.zeros((wy1 - wy0, wx1 - wx0), np.uint8)
    for m, mx, my in others:
        lab[_window(m, mx, my, lab.shape, wx0, wy0)] = 2
    lab[_window(shaft, sx, sy, lab.shape, wx0, wy0)] = 1
    near = np.empty(lab.shape, bool)
    before_k.near_others(lab, _GAP_ROWS, near)
    _, _, bg, other, _ = kp.shaft_boundary(
        outline, starts[: n_pieces + 1], shaft, sx, sy, near, wx0, wy0, none, 0, 0, H, W
    )
    assert got[0] == (len(other) >= 3)
    assert _same(got[1], bg) and _same(got[2], other)


def _window(
    mask: np.ndarray, mx: int, my: int, shape: tuple[int, ...], x0: int, y0: int
) -> np.ndarray:
    """``mask`` (at ``(mx, my)``) on a canvas of ``shape`` at ``(x0, y0)``: a bool array
    of the canvas' shape."""
    out = np.zeros(shape, bool)
    mh, mw = mask.shape
    xa, ya = max(mx, x0), max(my, y0)
    xb, yb = min(mx + mw, x0 + shape[1]), min(my + mh, y0 + shape[0])
    if xa < xb and ya < yb:
        out[ya - y0 : yb - y0, xa - x0 : xb - x0] = mask[ya - my : yb - my, xa - mx : xb - mx]
    return out


@settings(max_examples=500, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 3, 5, 24, 48, 97]))
def test_sorted_points_as_the_insertion_sort(seed: int, n: int) -> None:
    """The hull's points sorted by a natural merge sort: the former insertion sort's
    order (by x, then y, then index) on rims (two ellipses' points in angle order), on
    points with ties in x, in both, on signed zeros, and with NaN among them."""
    rng = np.random.default_rng(seed)
    kind = rng.random()
    if kind < 0.4:  # rims: runs of ascending and descending x
        t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False) + rng.uniform(0, 6.3)
        pts = np.stack(
            [
                rng.uniform(50, 400) + rng.uniform(1, 80) * np.cos(t),
                rng.uniform(50, 300) + rng.uniform(1, 80) * np.sin(t),
            ],
            axis=1,
        )
    elif kind < 0.7:  # ties
        pts = rng.integers(-3, 4, (n, 2)).astype(np.float64)
        pts[pts == 0] = rng.choice([-0.0, 0.0], int((pts == 0).sum()))
    else:
        pts = rng.normal(0.0, 100.0, (n, 2))
    pts = pts.astype(np.float32)
    if rng.random() < 0.1:
        pts[rng.random((n, 2)) < 0.2] = np.nan
    got = _wrapped()["sorted_points"](pts)
    ref = _wrapped()["inserted"](pts)
    assert np.array_equal(got, ref)
