"""The crossing split's (and Algorithm 1's) faster pieces equal the definitions they
replace, bit for bit (issue 13: the sequential identity step's cost)."""

from __future__ import annotations

import functools
import math
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.model import InstanceObservation, PartObservation, RotatedBox
from mistool.tracking.split import (
    BlobPixels,
    argmin_rows,
    nearest_axis,
    segment_d2,
    segment_d2_rows,
)


def _segment_d2_before(
    p: np.ndarray, ends: np.ndarray, dirs: np.ndarray, back: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """``split.segment_d2`` as it was (commit ddfb117): (N, 2) x (2, 2K), (N, K) work."""
    k = len(ends)
    nrm = np.stack([-dirs[:, 1], dirs[:, 0]], 1)
    frame = np.concatenate([dirs, nrm]).T
    coords = p @ frame
    coords -= np.concatenate([(ends * dirs).sum(1), (ends * nrm).sum(1)])
    along, perp = coords[:, :k], coords[:, k:]
    excess = np.maximum(along, 0.0)
    for j in np.flatnonzero(np.isfinite(back)):
        excess[:, j] += np.maximum(-along[:, j] - back[j], 0.0)
    d2 = perp * perp
    d2 += excess * excess
    d2 *= 1.0 / (radius * radius)
    return d2


@st.composite
def _segments(draw: st.DrawFn) -> tuple[np.ndarray, ...]:
    """Points (pixel centres or any floats) and K segments (some half-lines)."""
    seed = draw(st.integers(0, 2**32 - 1))
    n = draw(st.sampled_from([0, 1, 2, 3, 7, 64, 513, 3000]))
    k = draw(st.integers(1, 4))
    rng = np.random.default_rng(seed)
    p = rng.uniform(-50, 800, (n, 2))
    if draw(st.booleans()):
        p = np.round(p)
    t = rng.uniform(0, 2 * math.pi, k)
    dirs = np.stack([np.cos(t), np.sin(t)], 1)
    ends = rng.uniform(0, 700, (k, 2))
    back = np.where(rng.random(k) < 0.5, math.inf, rng.uniform(0, 400, k))
    radius = rng.uniform(1.0, 40.0, k)
    return p, ends, dirs, back, radius


@settings(max_examples=150, deadline=None)
@given(_segments())
def test_segment_distances_in_rows_equal_the_former_definition(args):
    want = _segment_d2_before(*args)
    assert np.array_equal(segment_d2_rows(*args), want.T)
    assert np.array_equal(segment_d2(*args), want)
    assert np.array_equal(nearest_axis(*args), want.argmin(1))


@settings(max_examples=150, deadline=None)
@given(
    st.integers(1, 5),
    st.integers(0, 200),
    st.integers(0, 2**32 - 1),
    st.sampled_from(["continuous", "ties", "nan"]),
)
def test_argmin_rows_is_argmin_over_the_first_axis(k, n, seed, kind):
    rng = np.random.default_rng(seed)
    d2 = rng.uniform(0, 10, (k, n))
    if kind == "ties":
        d2 = rng.integers(0, 3, (k, n)).astype(np.float64)
    elif kind == "nan" and n:
        d2[rng.integers(0, k, 3), rng.integers(0, n, 3)] = np.nan
    assert np.array_equal(argmin_rows(d2), d2.argmin(0))


def _blob(mask: np.ndarray, offset: tuple[int, int]) -> InstanceObservation:
    box = RotatedBox(0.0, 0.0, 1.0, 1.0, 0.0)
    part = PartObservation("shaft", box, np.zeros((4, 2)), int(mask.sum()), mask, offset)
    return InstanceObservation(None, {"shaft": part}, (0.0, 0.0), part.area_px, (0, 0, 1, 1))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 5, 300, 1000, 10**6]))
def test_shaft_sample_is_every_step_th_shaft_pixel(seed, max_points):
    rng = np.random.default_rng(seed)
    mask = np.zeros((int(rng.integers(1, 300)), int(rng.integers(1, 300))), np.uint8)
    for _ in range(3):  # a few thick strokes
        a, b = rng.integers(0, 300, 2), rng.integers(0, 300, 2)
        cv2.line(mask, tuple(map(int, a)), tuple(map(int, b)), 1, int(rng.integers(1, 30)))
    mask[int(rng.integers(0, mask.shape[0])), int(rng.integers(0, mask.shape[1]))] = 1
    mask = mask.astype(bool)
    offset = (int(rng.integers(0, 500)), int(rng.integers(0, 500)))
    ys, xs = np.nonzero(mask)
    full = np.stack([xs + offset[0], ys + offset[1]], 1).astype(np.float64)
    pixels = BlobPixels(_blob(mask, offset))
    pts, step = pixels.shaft_sample(max_points)
    assert step == max(1, len(full) // max_points)
    assert np.array_equal(pts, full[::step])
    assert np.array_equal(pixels.shaft_points(), full)


def _lattice_gaps_before(
    normals: np.ndarray, h: np.ndarray, t_lo: np.ndarray, t_hi: np.ndarray
) -> np.ndarray:
    """``geometry._lattice_gaps`` as it was (commit ddfb117): the sides' columns in one
    ragged run, ``maximum.reduceat``."""
    from mistool.geometry import _GAP_WALK

    eps = 1e-4
    nx, ny = normals[:, 0], normals[:, 1]
    horiz = np.abs(ny) >= np.abs(nx)
    a = np.where(horiz, nx, ny)
    b = np.where(horiz, ny, nx)
    w0 = h * a + t_lo * np.where(horiz, -ny, nx)
    w1 = h * a + t_hi * np.where(horiz, -ny, nx)
    start = np.ceil(np.minimum(w0, w1) - eps)
    full = np.maximum(np.floor(np.maximum(w0, w1) + eps) - start + 1, 1).astype(np.int64)
    count = np.minimum(full, _GAP_WALK)
    side = np.repeat(np.arange(len(h)), count)
    first = np.cumsum(count) - count
    idx = np.arange(side.size) - first[side]
    skip = np.where(idx >= _GAP_WALK // 2, (full - count)[side], 0)
    p = start[side] + idx + skip
    r = ((h + eps)[side] - a[side] * p) / np.abs(b)[side]
    frac = r - np.floor(r)
    best = np.maximum.reduceat(frac, first)
    return np.abs(b) * (1.0 - best) + eps


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0.0, 180.0, exclude_max=True),
    st.lists(st.integers(0, 700), min_size=2, max_size=40),
    st.booleans(),
)
def test_pixel_edge_gaps_equal_the_former_definition(angle, coords, snap):
    """A box's sides (any angle, short and long) walked as before, bit for bit."""
    from mistool.geometry import _lattice_gaps

    if snap:  # axis-aligned and 45 deg sides
        angle = float(round(angle / 45.0) * 45.0) % 180.0
    t = math.radians(angle)
    e1, e2 = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    pts = np.array(coords[: len(coords) // 2 * 2], np.float64).reshape(-1, 2)
    p1, p2 = pts @ e1, pts @ e2
    normals = np.stack([e2, -e2, e1, -e1])
    h = np.array([p2.max(), -p2.min(), p1.max(), -p1.min()])
    t_lo = np.array([-p1.max(), p1.min(), p2.min(), -p2.max()])
    t_hi = np.array([-p1.min(), p1.max(), p2.max(), -p2.min()])
    assert np.array_equal(
        _lattice_gaps(normals, h, t_lo, t_hi), _lattice_gaps_before(normals, h, t_lo, t_hi)
    )


def _box_distance_before(xy: np.ndarray, box: RotatedBox) -> np.ndarray:
    """``heads.box_distance`` as it was (commit d6ce7fd), numpy."""
    t = math.radians(box.angle_deg)
    u = np.array([math.cos(t), math.sin(t)])
    d = xy - np.array([box.cx, box.cy])
    along = np.abs(d @ u) - 0.5 * box.length
    across = np.abs(d @ np.array([-u[1], u[0]])) - 0.5 * box.width
    return np.hypot(np.maximum(along, 0.0), np.maximum(across, 0.0))


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 2, 3, 50, 2000]))
def test_box_distances_are_the_former_ones(seed, n):
    """heads.box_distance (compiled) gives the former numpy distances bit for bit, one
    point (BLAS's one-point order) or many, inside and outside the box."""
    from mistool.tracking import heads

    rng = np.random.default_rng(seed)
    box = RotatedBox(
        *rng.uniform(0, 600, 2), *sorted(rng.uniform(0, 80, 2))[::-1], rng.uniform(0, 180)
    )
    xy = rng.uniform(-50, 700, (n, 2))
    if rng.random() < 0.5:
        xy = np.round(xy)
    assert np.array_equal(heads.box_distance(xy, box), _box_distance_before(xy, box))


@settings(max_examples=400, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.floats(0.0, 180.0, exclude_max=True),
    st.sampled_from([1, 5, 40, 200, 600]),
)
def test_a_head_shown_where_expected_is_decided_as_by_every_pixel(seed, angle, min_area):
    """heads._shows' shortcuts (pixels well inside the box, every pixel within reach)
    give the answer of counting every pixel's distance."""
    from mistool.tracking import heads

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 70)), int(rng.integers(1, 70))
    mask = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(1, 4))):
        a, b = rng.integers(-5, 75, 2), rng.integers(-5, 75, 2)
        cv2.line(mask, tuple(map(int, a)), tuple(map(int, b)), 1, int(rng.integers(1, 15)))
    mask[int(rng.integers(0, h)), int(rng.integers(0, w))] = 1
    offset = (int(rng.integers(0, 600)), int(rng.integers(0, 400)))
    ys, xs = np.nonzero(mask)
    # near a pixel of the part: its pixels on both sides of the reach
    k = int(rng.integers(0, len(xs)))
    t = rng.uniform(0, 2 * math.pi)
    far = rng.uniform(0, 25)
    length = float(rng.uniform(1, 60))
    box = RotatedBox(
        offset[0] + xs[k] + far * math.cos(t),
        offset[1] + ys[k] + far * math.sin(t),
        length,
        float(rng.uniform(1, length)),
        angle,
    )
    blob = _blob(mask.astype(bool), offset)
    xy = np.stack([xs + offset[0], ys + offset[1]], 1).astype(np.float64)
    want = int((_box_distance_before(xy, box) <= heads.HEAD_CLAIM_PX).sum()) >= min_area
    assert heads._shows(blob, "shaft", box, min_area) == want
    assert np.array_equal(heads._pixels(blob, "shaft"), xy)


@settings(max_examples=400, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.floats(0.0, 180.0, exclude_max=True),
    st.sampled_from(["none", "box", "same"]),
    st.booleans(),
)
def test_the_head_pixels_claimed_are_counted_as_from_their_pixel_list(seed, angle, own, one):
    """heads._claimed (one compiled pass over the donor's mask) counts the pixels that
    hand_over_heads moves, ``(to_me <= HEAD_CLAIM_PX) & (to_me < to_own)`` of their
    box_distance to the expected box and to the donor's own (none: inf; the same box:
    none moves), for parts of one pixel (its one-point order) and of many."""
    from mistool.tracking import heads

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 70)), int(rng.integers(1, 70))
    mask = np.zeros((h, w), np.uint8)
    if one:
        mask[int(rng.integers(0, h)), int(rng.integers(0, w))] = 1
    else:
        for _ in range(int(rng.integers(1, 4))):
            a, b = rng.integers(-5, 75, 2), rng.integers(-5, 75, 2)
            cv2.line(mask, tuple(map(int, a)), tuple(map(int, b)), 1, int(rng.integers(1, 15)))
        mask[int(rng.integers(0, h)), int(rng.integers(0, w))] = 1
    offset = (int(rng.integers(0, 600)), int(rng.integers(0, 400)))
    ys, xs = np.nonzero(mask)

    def near_box(a: float) -> RotatedBox:  # near a pixel of the part
        k = int(rng.integers(0, len(xs)))
        t = rng.uniform(0, 2 * math.pi)
        far = rng.uniform(0, 20)
        length = float(rng.uniform(0.5, 60))
        return RotatedBox(
            offset[0] + xs[k] + far * math.cos(t),
            offset[1] + ys[k] + far * math.sin(t),
            length,
            float(rng.uniform(0.5, length)),
            a,
        )

    want = near_box(angle)
    theirs = {"none": None, "box": near_box(float(rng.uniform(0, 180))), "same": want}[own]
    blob = _blob(mask.astype(bool), offset)
    xy = np.stack([xs + offset[0], ys + offset[1]], 1).astype(np.float64)
    to_me = _box_distance_before(xy, want)
    to_own = _box_distance_before(xy, theirs) if theirs is not None else np.full(len(xy), np.inf)
    moved = int(((to_me <= heads.HEAD_CLAIM_PX) & (to_me < to_own)).sum())
    assert heads._claimed(blob, "shaft", want, theirs) == moved


def _fit_part_before(mask: np.ndarray, min_area_px: int, offset: tuple[int, int]):
    """``geometry.fit_part`` as it was (commit ddfb117): numpy's min/max of the points,
    the former pixel-edge gaps."""
    from mistool import geometry

    kept, area, contours = geometry._clean(mask, min_area_px)
    if area == 0:
        return None
    pts = (
        geometry.mask_points(kept)
        if contours is None
        else np.concatenate(contours, axis=0).reshape(-1, 2)
    )
    x, y = (int(v) for v in pts.min(axis=0))
    x1, y1 = (int(v) + 1 for v in pts.max(axis=0))
    pts = pts + np.asarray(offset, np.int32)
    (_, _), (_, _), angle = cv2.minAreaRect(pts)
    t = math.radians(float(angle))
    c, s = math.cos(t), math.sin(t)
    e1, e2 = np.array([c, s]), np.array([-s, c])
    pf = pts.astype(np.float64)
    p1, p2 = pf @ e1, pf @ e2
    a_lo, a_hi = float(p1.min()), float(p1.max())
    b_lo, b_hi = float(p2.min()), float(p2.max())
    normals = np.stack([e2, -e2, e1, -e1])
    h = np.array([b_hi, -b_lo, a_hi, -a_lo])
    t_lo = np.array([-a_hi, a_lo, b_lo, -b_hi])
    t_hi = np.array([-a_lo, a_hi, b_hi, -b_lo])
    g = _lattice_gaps_before(normals, h, t_lo, t_hi) / 2.0
    b_hi, b_lo, a_hi, a_lo = b_hi + g[0], b_lo - g[1], a_hi + g[2], a_lo - g[3]
    ca, cb = (a_lo + a_hi) / 2.0, (b_lo + b_hi) / 2.0
    rect = ((ca * c - cb * s, ca * s + cb * c), (a_hi - a_lo, b_hi - b_lo), float(angle))
    box = geometry._canonical(rect)
    return box, geometry.box_points(rect), area, kept[y:y1, x:x1], (offset[0] + x, offset[1] + y)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 30, 400]))
def test_algorithm_1_of_a_mask_equals_the_former_definition(seed, min_area):
    """fit_part (speck removal, tight crop, box grown to the pixel edges), bit for bit."""
    from mistool.geometry import fit_part

    rng = np.random.default_rng(seed)
    mask = np.zeros((int(rng.integers(1, 120)), int(rng.integers(1, 120))), np.uint8)
    for _ in range(int(rng.integers(1, 5))):
        a, b = rng.integers(-10, 130, 2), rng.integers(-10, 130, 2)
        cv2.line(mask, tuple(map(int, a)), tuple(map(int, b)), 255, int(rng.integers(1, 25)))
    for _ in range(int(rng.integers(0, 6))):  # specks
        mask[int(rng.integers(0, mask.shape[0])), int(rng.integers(0, mask.shape[1]))] = 255
    if rng.integers(0, 2):  # in a larger window (fit_part then works on its bounds)
        big = np.zeros((mask.shape[0] + int(rng.integers(0, 200)), mask.shape[1] + 150), np.uint8)
        y0, x0 = int(rng.integers(0, big.shape[0] - mask.shape[0] + 1)), int(rng.integers(0, 151))
        big[y0 : y0 + mask.shape[0], x0 : x0 + mask.shape[1]] = mask
        mask = big
    offset = (int(rng.integers(0, 600)), int(rng.integers(0, 400)))
    got = fit_part(mask, min_area, offset)
    want = _fit_part_before(mask, min_area, offset)
    if want is None:
        assert got is None
        return
    box, corners, area, kept, off = want
    assert got is not None
    assert got.box == box and np.array_equal(got.corners, corners) and got.area_px == area
    assert np.array_equal(got.mask, kept) and got.offset == off


@settings(max_examples=300, deadline=None)
@given(
    st.floats(-1e4, 1e4),
    st.floats(-1e4, 1e4),
    st.floats(0.0, 1e3),
    st.floats(0.0, 1.0),
    st.floats(0.0, 180.0, exclude_max=True),
)
def test_box_corners_equal_the_former_definition(cx, cy, length, frac, angle):
    box = RotatedBox(cx, cy, length, length * frac, angle)
    t = math.radians(angle)
    u = np.array([math.cos(t), math.sin(t)])
    v = np.array([-math.sin(t), math.cos(t)])
    hl, hw = box.length / 2.0, box.width / 2.0
    c = np.array([cx, cy])
    want = np.stack(
        [c - hl * u - hw * v, c + hl * u - hw * v, c + hl * u + hw * v, c - hl * u + hw * v]
    )
    got = box.corners()
    assert got.dtype == np.float64 and got.shape == (4, 2)
    assert np.array_equal(got, want)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 3000), st.booleans())
def test_principal_direction_equals_the_former_definition(seed, n, pixels):
    from mistool.tracking.split import _centred_direction, _principal_direction

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 2)) * rng.uniform(0.1, 50, 2) + rng.uniform(0, 700, 2)
    if pixels:
        q = np.round(q)
    c = q.mean(0)
    r = q - c
    sxx, syy, sxy = float(r[:, 0] @ r[:, 0]), float(r[:, 1] @ r[:, 1]), float(r[:, 0] @ r[:, 1])
    t = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    got_c, got_r, got_d = _centred_direction(q)
    assert np.array_equal(got_c, c) and np.array_equal(got_r, r)
    assert np.array_equal(got_d, [math.cos(t), math.sin(t)])
    pc, pd = _principal_direction(q)
    assert np.array_equal(pc, c) and np.array_equal(pd, got_d)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 30]))
def test_algorithm_1_of_a_window_equals_that_of_the_whole_crop(seed, min_area):
    """fit_part of a window holding every pixel (at any margin, pixels on its edges) is
    fit_part of the whole crop, bit for bit: the split cuts its pieces from windows."""
    from mistool.geometry import fit_part

    rng = np.random.default_rng(seed)
    mask = np.zeros((int(rng.integers(1, 100)), int(rng.integers(1, 100))), np.uint8)
    for _ in range(int(rng.integers(1, 4))):
        a, b = rng.integers(-10, 110, 2), rng.integers(-10, 110, 2)
        cv2.line(mask, tuple(map(int, a)), tuple(map(int, b)), 1, int(rng.integers(1, 15)))
    mask[int(rng.integers(0, mask.shape[0])), int(rng.integers(0, mask.shape[1]))] = 1
    x, y, bw, bh = cv2.boundingRect(mask)
    x0, y0 = int(rng.integers(0, x + 1)), int(rng.integers(0, y + 1))
    x1 = int(rng.integers(x + bw, mask.shape[1] + 1))
    y1 = int(rng.integers(y + bh, mask.shape[0] + 1))
    whole = fit_part(mask, min_area, (100, 50))
    window = fit_part(mask[y0:y1, x0:x1], min_area, (100 + x0, 50 + y0))
    if whole is None:
        assert window is None
        return
    assert window is not None
    assert whole.box == window.box and np.array_equal(whole.corners, window.corners)
    assert whole.area_px == window.area_px and whole.offset == window.offset
    assert np.array_equal(whole.mask, window.mask)


# the compiled split (mistool/kernels/split.py) against the numpy code it replaced -----


def test_the_blas_orders_are_numpys() -> None:
    """The strided dot products and pairwise sums the split's kernels copy
    (mistool/kernels/split.py) give numpy's bits. (The orders of ``dot2`` and
    ``row_dot``, helpers compiled only into kernels, are checked through those kernels:
    the segment distances, box distances, refit, score and initial axes against their
    former numpy definitions.)"""
    from mistool.kernels import split as k

    rng = np.random.default_rng(11)
    for n in [1, 2, 3, 4, 5, 7, 8, 9, 15, 16, 17, 127, 128, 129, 1000, 4099, 10_000, 70001]:
        a = rng.normal(0, 100, (n, 2))
        if n <= k.DOT_SERIAL_MAX:
            assert k.dot_strided(a[:, 0], a[:, 1]) == float(a[:, 0] @ a[:, 1])
            assert k.dot_strided(a[:, 1], a[:, 1]) == float(a[:, 1] @ a[:, 1])
        v = rng.uniform(0, 30, n)
        assert k.pairwise_sum(v, n) == float(np.add.reduce(v))
    assert k.pairwise_sum(np.array([-0.0]), 1) == np.add.reduce(np.array([-0.0]))


def _nearest_before(pts: np.ndarray, ax: Any) -> np.ndarray:
    """``split._Axes.nearest`` as it was (commit 3fc5814)."""
    if ax.keep_d2 is None:
        d2 = _segment_d2_before(pts, ax.ends, ax.dirs, ax.back, ax.radius).T
        if len(ax.ends) == 2:
            return (d2[1] < d2[0]).astype(np.intp)
        return d2.argmin(0)
    d2 = _segment_d2_before(pts, ax.ends, ax.dirs, ax.back, ax.radius).T
    lab = d2.argmin(0)
    lab[np.minimum.reduce(d2) > ax.keep_d2] = len(ax.dirs)
    return lab


def _centred_direction_before(q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    c = np.add.reduce(q, 0) / len(q)
    r = q - c
    sxx = float(r[:, 0] @ r[:, 0])
    syy = float(r[:, 1] @ r[:, 1])
    sxy = float(r[:, 0] @ r[:, 1])
    t = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    return c, r, np.array([math.cos(t), math.sin(t)])


def _shared_before(pts: np.ndarray, ax: Any, lab: np.ndarray) -> np.ndarray:
    """(N,) bool, the points labelled ``j`` lying within another axis ``k``'s half-width
    and behind its distal end, where ``k``'s points lie on both sides of ``j``'s line
    farther than ``split.SPLIT_THROUGH_RADII`` of ``j``'s half-widths (numpy, the
    coordinates of ``_segment_d2_before``)."""
    from mistool.tracking import split

    k = len(ax.dirs)
    nrm = np.stack([-ax.dirs[:, 1], ax.dirs[:, 0]], 1)
    coords = pts @ np.concatenate([ax.dirs, nrm]).T
    coords -= np.concatenate([(ax.ends * ax.dirs).sum(1), (ax.ends * nrm).sum(1)])
    along, perp = coords[:, :k], coords[:, k:]
    d2 = _segment_d2_before(pts, ax.ends, ax.dirs, ax.back, ax.radius)
    shared = np.zeros(len(pts), bool)
    for j in range(k):
        thr = split.SPLIT_THROUGH_RADII * ax.radius[j]
        for o in range(k):
            across = perp[lab == o, j]
            if o == j or min(0.0, across.min(initial=0.0)) >= -thr:
                continue
            if max(0.0, across.max(initial=0.0)) <= thr:
                continue
            shared |= (lab == j) & (d2[:, o] < 1.0) & (along[:, o] < 0.0)
    return shared


def _refit_before(
    ax: Any, pts: np.ndarray, weight: int, min_area_px: int, contiguous: bool
) -> bool:
    """``split._refit`` as it was (commit 3fc5814), with the reach cut where another
    shaft passes through (fits of ``split.SPLIT_THROUGH_AXES`` axes or more)."""
    from mistool.tracking import split

    through = len(ax.dirs) >= split.SPLIT_THROUGH_AXES
    prev: np.ndarray | None = None
    for _ in range(split.SPLIT_REFIT_ROUNDS):
        lab = _nearest_before(pts, ax)
        if prev is not None and np.array_equal(lab, prev):
            break
        prev = lab
        shared = _shared_before(pts, ax, lab) if through else None
        for j in range(len(ax.dirs)):
            q = pts[lab == j]
            if len(q) < 3 or len(q) * weight < min_area_px:
                return False
            c, r, d = _centred_direction_before(q)
            if abs(float(d @ ax.start_dirs[j])) >= split.SPLIT_MAX_TURN_COS:
                ax.dirs[j] = d if d @ ax.dirs[j] >= 0 else -d
            limit = float((ax.limit_end[j] + ax.margin[j] * ax.dirs[j] - c) @ ax.dirs[j])
            proj = r @ ax.dirs[j]
            reach = float(proj.max())
            if shared is not None and not shared[lab == j].all():
                own = float(proj[~shared[lab == j]].max())
                if reach - own > split.SPLIT_THROUGH_CUT_RADII * ax.radius[j]:
                    reach = own
            if contiguous:
                sp = np.sort(proj)
                gaps = np.flatnonzero(np.diff(sp) > split.SPLIT_CONTIGUOUS_GAP * ax.radius[j])
                if len(gaps):
                    reach = float(sp[gaps[0]])
            ax.ends[j] = c + min(reach, limit) * ax.dirs[j]
    return True


def _side_by_side_before(ax: Any, i: int, j: int) -> bool:
    from mistool.tracking import split

    cos = float(ax.dirs[i] @ ax.dirs[j])
    if math.degrees(math.acos(min(1.0, abs(cos)))) >= split.SPLIT_MIN_ANGLE_DEG:
        return False
    if cos > 0:
        return True
    u = ax.dirs[i]
    hi_i, lo_j = float(ax.ends[i] @ u), float(ax.ends[j] @ u)
    return hi_i - lo_j > ax.radius[i] + ax.radius[j]


def _score_before(ax: Any, pts: np.ndarray) -> float | None:
    """``split._score`` as it was (commit 3fc5814)."""
    from mistool.tracking import split

    d2 = _segment_d2_before(pts, ax.ends, ax.dirs, ax.back, ax.radius).T
    lab = d2.argmin(0)
    if ax.keep_d2 is not None:
        lab[np.minimum.reduce(d2) > ax.keep_d2] = len(ax.dirs)
    score = 0.0
    k = len(ax.dirs)
    for j in range(k):
        with np.errstate(invalid="ignore"):
            sel = d2[j][lab == j]
            rms = math.sqrt(float(sel.mean())) if len(sel) else math.nan
        if rms > 2.0 * split.SPLIT_MAX_SPREAD + 0.5 / ax.radius[j]:
            return None
        score = max(score, rms)
    for i in range(k):
        for j in range(i + 1, k):
            if _side_by_side_before(ax, i, j):
                return None
    return score


@st.composite
def _fits(draw: st.DrawFn) -> tuple[Any, np.ndarray, int, int, bool]:
    """A blob's shaft points drawn as K thick strokes (pixel centres, or any floats),
    K axes near them (some crossing, some parallel, some half-lines), fit options."""
    from mistool.tracking.split import _Axes

    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    k = draw(st.integers(1, 4))
    mask = np.zeros((200, 260), np.uint8)
    t = rng.uniform(0, math.pi, k)
    if draw(st.booleans()):  # near parallel
        t = t[0] + rng.normal(0, 0.1, k)
    centre = rng.uniform(60, 140, (k, 2))
    for j in range(k):
        d = 90 * np.array([math.cos(t[j]), math.sin(t[j])])
        a, b = (centre[j] - d).astype(int), (centre[j] + d).astype(int)
        cv2.line(mask, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1, int(rng.integers(3, 25)))
    ys, xs = np.nonzero(mask)
    pts = np.stack([xs, ys], 1).astype(np.float64) + rng.integers(0, 400, 2)
    pts = pts[:: max(1, len(pts) // int(rng.integers(3, 1500)))]
    if draw(st.booleans()):
        pts = pts + rng.uniform(-0.5, 0.5, pts.shape)
    turn = t + rng.normal(0, 0.3, k)
    dirs = np.stack([np.cos(turn), np.sin(turn)], 1) * rng.choice([-1, 1], (k, 1))
    ends0 = pts.mean(0) + rng.normal(0, 40, (k, 2))
    margin = rng.uniform(0, 30, k)
    ax = _Axes(
        ends=ends0 + margin[:, None] * dirs,
        dirs=dirs,
        back=np.where(rng.random(k) < 0.5, math.inf, rng.uniform(5, 200, k)),
        radius=rng.uniform(1.0, 15.0, k),
        limit_end=ends0,
        start_dirs=dirs.copy(),
        margin=margin,
        keep_d2=float(rng.uniform(1, 30)) if draw(st.booleans()) else None,
    )
    weight = int(rng.integers(1, 60))
    min_area = draw(st.sampled_from([1, 20, 400, 5000]))
    return ax, pts, weight, min_area, draw(st.booleans())


@settings(max_examples=300, deadline=None)
@given(_fits())
def test_the_compiled_refit_and_score_are_the_former_numpy_ones(case) -> None:
    """split._refit / _score / _Axes.nearest (compiled) give the former numpy fit's
    result, axes and score bit for bit: crossing, parallel and single axes, half-lines,
    another tool's points left out (keep_d2), contiguous shafts, few and many points."""
    import copy

    from mistool.tracking import split

    ax, pts, weight, min_area, contiguous = case
    assert np.array_equal(ax.nearest(pts), _nearest_before(pts, ax))
    before = copy.deepcopy(ax)
    ok = split._refit(ax, pts, weight, min_area, contiguous)
    assert ok == _refit_before(before, pts, weight, min_area, contiguous)
    assert np.array_equal(ax.ends, before.ends) and np.array_equal(ax.dirs, before.dirs)
    got, want = split._score(ax, pts), _score_before(before, pts)
    assert got == want or (
        got is not None and want is not None and math.isnan(got) and math.isnan(want)
    )
    assert np.array_equal(ax.nearest(pts), _nearest_before(pts, before))


def _owner_cells_before(part: PartObservation, ax: Any) -> np.ndarray:
    """``split._owner_cells``' owner image as it was (commit 3fc5814): the cells' nearest
    axes blown up by OpenCV's resize, refined per pixel in the cells where cv2.dilate and
    cv2.erode of the cells differ."""
    h, w = part.mask.shape
    s = 8
    x0, y0 = part.offset
    cx = x0 + np.arange(0, w, s) + 0.5 * (s - 1)
    cy = y0 + np.arange(0, h, s) + 0.5 * (s - 1)
    gx, gy = np.meshgrid(cx, cy)
    centres = np.stack([gx.ravel(), gy.ravel()], 1)
    coarse = _nearest_before(centres, ax).reshape(len(cy), len(cx)).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    mixed = cv2.dilate(coarse, kernel) != cv2.erode(coarse, kernel)
    owner = np.repeat(np.repeat(coarse, s, 0), s, 1)[:h, :w].copy()
    inside = np.repeat(np.repeat(mixed, s, 0), s, 1)[:h, :w] & part.mask.astype(bool)
    ys, xs = np.nonzero(inside)  # (their order changes no label)
    if len(xs):
        p = np.stack([xs + x0, ys + y0], 1).astype(np.float64)
        owner[ys, xs] = _nearest_before(p, ax)
    return owner


@settings(max_examples=200, deadline=None)
@given(
    st.integers(0, 2**32 - 1), st.integers(1, 4), st.booleans(), st.sampled_from([1, 6, 60, 200])
)
def test_the_compiled_shaft_owner_is_the_former_owner_image(seed, k, keep, size):
    """split._shaft_pieces (from the shaft's runs, compiled) gives each axis the row runs
    of the pixels the former owner image gave it (cells, then pixels in mixed cells; one
    cell, one mixed pixel: BLAS's one-point order): the runs ``mask_runs`` finds in its
    mask ``owner == j``, nothing off the mask."""
    from mistool.kernels.boxes import mask_runs
    from mistool.tracking.split import BlobPixels, _Axes, _owner_image, _shaft_pieces

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, size + 1)), int(rng.integers(1, size + 1))
    mask = rng.random((h, w)) < rng.uniform(0.01, 1.0)
    if rng.random() < 0.2:
        mask[:] = False
        mask[int(rng.integers(0, h)), int(rng.integers(0, w))] = True
    t = rng.uniform(0, 2 * math.pi, k)
    offset = (int(rng.integers(0, 300)), int(rng.integers(0, 300)))
    ax = _Axes(
        ends=rng.uniform(-20, size + 20, (k, 2)) + offset,
        dirs=np.stack([np.cos(t), np.sin(t)], 1),
        back=np.where(rng.random(k) < 0.5, math.inf, rng.uniform(5, 100, k)),
        radius=rng.uniform(1, 15, k),
        limit_end=np.zeros((k, 2)),
        start_dirs=np.zeros((k, 2)),
        margin=np.zeros(k),
        keep_d2=float(rng.uniform(1, 30)) if keep else None,
    )
    blob = _blob(mask, offset)
    part = blob.parts["shaft"]
    want = _owner_cells_before(part, ax)
    want[~mask] = 255
    ry, rx0, rx1, n = _shaft_pieces(BlobPixels(blob), ax, k + 1)
    for j in range(k + 1):
        wy, wx0, wx1, wn = mask_runs(np.where(want == j, np.uint8(1), np.uint8(0)))
        assert n[j] == wn
        assert np.array_equal(ry[j, :wn], wy[:wn]) and np.array_equal(rx0[j, :wn], wx0[:wn])
        assert np.array_equal(rx1[j, :wn], wx1[:wn])
    assert np.array_equal(_owner_image(part, ax), want)


def _mirror_axes(c: float) -> Any:
    """Two axes mirrored about the row y = c: its points are equally far from both, and
    which is nearer turns on the last bit, which differs between BLAS's order for one
    point and for several."""
    from mistool.tracking.split import _Axes

    a = 0.766
    dirs = np.array([[math.cos(a), math.sin(a)], [math.cos(a), -math.sin(a)]])
    return _Axes(
        ends=np.array([[379.46, c + 9.5], [379.46, c - 9.5]]),
        dirs=dirs,
        back=np.full(2, math.inf),
        radius=np.full(2, 7.0),
        limit_end=np.zeros((2, 2)),
        start_dirs=np.zeros((2, 2)),
        margin=np.zeros(2),
    )


@pytest.mark.parametrize("where", ["one cell", "one pixel in a mixed cell"])
def test_the_shaft_owner_takes_blas_one_point_order_where_numpy_did(where):
    """A crop of one cell (its centre the only point of the cells' product) and a crop
    with one pixel in a mixed cell (the only point of the pixels' product): labelled as
    numpy labelled that one point, which here differs from the label the same point gets
    among others."""
    from mistool.tracking.split import _owner_image, nearest_axis

    centre = where == "one cell"
    c = 238.5 if centre else 238.0
    ax = _mirror_axes(c)
    xs = np.arange(200.0, 360.0, 1.0) + (0.5 if centre else 0.0)
    line = np.stack([xs, np.full(len(xs), c)], 1)
    many = nearest_axis(line, ax.ends, ax.dirs, ax.back, ax.radius)
    alone = np.array([nearest_axis(q[None], ax.ends, ax.dirs, ax.back, ax.radius)[0] for q in line])
    flips = np.flatnonzero(many != alone)
    assert len(flips), "no point whose label turns on BLAS's order"
    x, y = line[flips[0]]
    if centre:  # an 8 x 8 crop whose one cell's centre is (x, y)
        mask = np.ones((8, 8), bool)
        offset = (int(x - 3.5), int(y - 3.5))
    else:  # one pixel at (x, y), in a crop whose cells around it take both labels
        mask = np.zeros((64, 64), bool)
        mask[32, 32] = True
        offset = (int(x) - 32, int(y) - 32)
    part = _blob(mask, offset).parts["shaft"]
    owner = _owner_image(part, ax)
    want = _owner_cells_before(part, ax)
    assert np.array_equal(owner[mask], want[mask])
    assert owner[mask][0] == alone[flips[0]] != many[flips[0]]


def _part_distance_before(name: str, p: np.ndarray, ax: Any, expected: list) -> np.ndarray:
    """``split._part_distance`` as it was (commit 40eb396): (K, N) distances of a head
    part's pixels to each instrument's head segment or, when nearer, its expected box of
    that part moved with its shaft's end."""
    from mistool.tracking.instances import unit_vector
    from mistool.tracking.split import HEAD_LENGTH_WIDTHS

    length = 2.0 * HEAD_LENGTH_WIDTHS * ax.radius if ax.head_len is None else ax.head_len
    out = _segment_d2_before(p, ax.ends + length[:, None] * ax.dirs, ax.dirs, length, ax.radius).T
    idx = [k for k, e in enumerate(expected) if name in e]
    if not idx:
        return out
    boxes = [expected[k][name] for k in idx]
    shift = (ax.ends - ax.limit_end)[idx]
    u = np.array([unit_vector(b.angle_deg) for b in boxes])
    h = np.array([0.5 * b.length for b in boxes])
    c = np.array([[b.cx, b.cy] for b in boxes]) + shift
    r = np.array([max(b.width / 2.0, 1.0) for b in boxes])
    box = _segment_d2_before(p, c + h[:, None] * u, u, 2 * h, r).T
    out[idx] = np.minimum(out[idx], box)
    return out


def _anchor_distance_before(anchor: Any, name: str, p: np.ndarray) -> np.ndarray:
    """``split.HeadAnchor.distance2`` as it was (commit 40eb396)."""
    from mistool.tracking.instances import unit_vector

    boxes = [anchor.boxes[name]] if name in anchor.boxes else list(anchor.boxes.values())
    if not boxes:
        d = p - anchor.centre
        return np.einsum("nd,nd->n", d, d) / (anchor.radius * anchor.radius)
    u = np.array([unit_vector(b.angle_deg) for b in boxes])
    h = np.array([0.5 * b.length for b in boxes])
    c = np.array([[b.cx, b.cy] for b in boxes])
    r = np.array([max(b.width / 2.0, 1.0) for b in boxes])
    return np.minimum.reduce(_segment_d2_before(p, c + h[:, None] * u, u, 2 * h, r).T)


def _split_with_heads_before(pixels: Any, fit: Any, min_area_px: int, anchors: list) -> Any:
    """``split.split_with_heads`` as it was (commit 3307ee1): each piece's part mask
    measured by ``part_observation``, its instance by ``make_instance``; head parts'
    distances in numpy."""
    from mistool.tracking.instances import make_instance, part_observation
    from mistool.tracking.split import argmin_rows

    inst = pixels.inst
    k = len(fit.expected)
    pieces: list[dict] = [{} for _ in range(k + len(anchors))]
    for name, part in inst.parts.items():
        if name == "shaft":
            owner = _owner_cells_before(part, fit.axes)
            mask = part.mask.view(np.uint8)
            for j in range(k + (len(anchors) == 1)):
                m = np.where((owner == j) & (mask > 0), np.uint8(1), np.uint8(0))
                obs = part_observation(name, m, part.offset[0], part.offset[1], min_area_px)
                if obs is not None:
                    pieces[j][name] = obs
            continue
        ys, xs, p = pixels.get(name)
        d2 = _part_distance_before(name, p, fit.axes, fit.expected)
        if anchors:
            d2 = np.concatenate(
                [d2, np.stack([_anchor_distance_before(a, name, p) for a in anchors])]
            )
        owner = argmin_rows(d2)
        for j in range(len(pieces)):
            sel = owner == j
            if not sel.any():
                continue
            m = np.zeros(part.mask.shape, np.uint8)
            m[ys[sel], xs[sel]] = 255
            obs = part_observation(name, m, part.offset[0], part.offset[1], min_area_px)
            if obs is not None:
                pieces[j][name] = obs
    if any("shaft" not in parts for parts in pieces[:k]):
        return None
    shape = inst.image_shape
    return (
        [make_instance(None, parts, shape) for parts in pieces[:k]],
        [make_instance(None, parts, shape) if parts else None for parts in pieces[k:]],
    )


def _same_instance(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is b
    if (a.label, a.centroid_px, a.area_px, a.bbox_xywh, a.image_shape) != (
        b.label,
        b.centroid_px,
        b.area_px,
        b.bbox_xywh,
        b.image_shape,
    ) or list(a.parts) != list(b.parts):
        return False
    for name, p in a.parts.items():
        q = b.parts[name]
        if (p.part, p.box, p.area_px, p.offset) != (q.part, q.box, q.area_px, q.offset):
            return False
        if not (np.array_equal(p.corners, q.corners) and np.array_equal(p.mask, q.mask)):
            return False
    return True


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 3), st.integers(0, 2), st.booleans())
def test_split_pieces_measured_from_runs_are_the_former_pieces(seed, k, n_anchors, keep):
    """split_with_heads (label images, row runs, Algorithm 1 of the runs, the instance
    from the runs' sums) gives the former pieces bit for bit: shaft and head parts with
    specks, anchors with and without head boxes, a lone anchor taking the shaft pixels
    far from every axis."""
    from mistool.tracking.instances import make_instance, part_observation
    from mistool.tracking.split import (
        HeadAnchor,
        SplitFit,
        _Axes,
        _initial_axes,
        split_with_heads,
    )

    rng = np.random.default_rng(seed)
    shape = (576, 720)
    parts = {}
    for name in ["shaft", "wrist", "clasper"][: int(rng.integers(1, 4))]:
        h, w = int(rng.integers(5, 200)), int(rng.integers(5, 200))
        m = np.zeros((h, w), np.uint8)
        for _ in range(int(rng.integers(1, 4))):
            a, b = rng.integers(-10, 210, 2), rng.integers(-10, 210, 2)
            cv2.line(
                m, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 255, int(rng.integers(1, 20))
            )
        for _ in range(int(rng.integers(0, 5))):  # specks
            m[int(rng.integers(0, h)), int(rng.integers(0, w))] = 255
        obs = part_observation(name, m, int(rng.integers(0, 400)), int(rng.integers(0, 300)), 1)
        if obs is not None:
            parts[name] = obs
    if "shaft" not in parts:
        return
    inst = make_instance(None, parts, shape)
    t = rng.uniform(0, 2 * math.pi, k)
    ends = rng.uniform(0, 500, (k, 2))
    ax = _Axes(
        ends=ends,
        dirs=np.stack([np.cos(t), np.sin(t)], 1),
        back=np.where(rng.random(k) < 0.5, math.inf, rng.uniform(5, 200, k)),
        radius=rng.uniform(2, 15, k),
        limit_end=ends - rng.uniform(0, 20, (k, 2)),
        start_dirs=np.zeros((k, 2)),
        margin=np.zeros(k),
        head_len=rng.uniform(5, 60, k) if rng.random() < 0.5 else None,
        keep_d2=float(rng.uniform(1, 30)) if keep else None,
    )

    def box() -> RotatedBox:
        length = float(rng.uniform(2, 80))
        x, y = rng.uniform(0, 600, 2)
        return RotatedBox(
            float(x),
            float(y),
            length,
            length * float(rng.uniform(0.1, 1)),
            float(rng.uniform(0, 180)),
        )

    expected = [
        {"shaft": box(), **{p: box() for p in ("wrist", "clasper") if rng.random() < 0.6}}
        for _ in range(k)
    ]
    anchors = [
        HeadAnchor(
            {p: box() for p in ("wrist", "clasper") if rng.random() < 0.5},
            rng.uniform(0, 600, 2),
            float(rng.uniform(5, 40)),
        )
        for _ in range(n_anchors)
    ]
    if ax.head_len is not None and rng.random() < 0.7:
        # the expected boxes as fit_split's axes carry them: without anchors, the head
        # parts' segments from them in one compiled call (kernels.split.head_part_runs)
        ref = _initial_axes(expected, None)
        ax.boxes, ax.others = ref.boxes, ref.others
    fit = SplitFit(0.5, ax, expected)
    min_area = int(rng.choice([1, 20, 300]))
    got = split_with_heads(BlobPixels(inst), fit, min_area, anchors)
    want = _split_with_heads_before(BlobPixels(inst), fit, min_area, anchors)
    if want is None:
        assert got is None
        return
    assert got is not None
    assert len(got[0]) == len(want[0]) and len(got[1]) == len(want[1])
    for a, b in zip(got[0] + got[1], want[0] + want[1], strict=True):
        assert _same_instance(a, b)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4))
def test_head_segments_kernel_is_head_segments(seed, k):
    """kernels.split.head_segments (a head part's segments from _initial_axes' boxes,
    inside head_part_runs) gives split._head_segments' segments and rows bit for bit:
    axes moved by a refit, expected boxes with and without the part, widths below 2
    px (radius 1), any angle."""
    from mistool.kernels.split import head_segments
    from mistool.tracking.split import _head_segments, _initial_axes

    rng = np.random.default_rng(seed)

    def box() -> RotatedBox:
        length = float(rng.uniform(0.5, 200))
        x, y = rng.uniform(-50, 800, 2)
        width = length * float(rng.uniform(0.01, 1))
        return RotatedBox(float(x), float(y), length, width, float(rng.uniform(0, 180)))

    expected = []
    for _ in range(k):
        heads = [p for p in ("wrist", "clasper", "jaws") if rng.random() < 0.5][:2]
        rng.shuffle(heads)
        expected.append({"shaft": box(), **{p: box() for p in heads}})
    ax = _initial_axes(expected, None, (576, 720) if rng.random() < 0.5 else None)
    ax.ends = ax.ends + rng.normal(0, 30, (k, 2))  # (a refit moves the ends and turns)
    t = rng.uniform(0, 2 * math.pi, k)
    ax.dirs = np.stack([np.cos(t), np.sin(t)], 1)
    assert ax.boxes is not None and ax.others is not None and ax.head_len is not None
    for name in ("wrist", "clasper", "jaws"):
        which = np.array([o.index(name) + 1 if name in o else 0 for o in ax.others], np.int64)
        got = head_segments(ax.boxes, which, ax.ends, ax.dirs, ax.radius, ax.head_len, ax.limit_end)
        (ends, dirs, back, radius), rows = _head_segments(name, ax, expected)
        for a, b in zip(got, (ends, dirs, back, radius, rows), strict=True):
            assert a.shape == b.shape and a.tobytes() == b.tobytes()


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 5), st.integers(1, 90), st.integers(1, 90))
def test_runs_cut_by_label_are_each_labels_mask_runs(seed, nlab, h, w):
    """kernels.split.cut_runs: a mask's runs, their pixels labelled, cut per label into
    the row runs mask_runs gives for the mask of that label (long stretches of one
    label, single pixels, labels beyond nlab left out)."""
    from mistool.kernels.boxes import mask_runs
    from mistool.kernels.split import cut_runs

    rng = np.random.default_rng(seed)
    labels = rng.integers(0, nlab + 1, (h, w))
    if rng.random() < 0.5:  # long runs
        labels = np.repeat(labels[:, : max(1, w // 9)], 9, 1)[:, :w].copy()
    mask = rng.random(labels.shape) < rng.uniform(0.2, 1.0)
    ry, rx0, rx1, nr = mask_runs(mask.view(np.uint8))
    lab = np.concatenate(
        [labels[y, a:b] for y, a, b in zip(ry[:nr], rx0[:nr], rx1[:nr], strict=True)] or [[]]
    ).astype(np.int64)
    oy, oa, ob, n = cut_runs(ry, rx0, rx1, nr, lab, nlab)
    for j in range(nlab):
        wy, wx0, wx1, wn = mask_runs((mask & (labels == j)).view(np.uint8))
        assert n[j] == wn
        assert np.array_equal(oy[j, :wn], wy[:wn]) and np.array_equal(oa[j, :wn], wx0[:wn])
        assert np.array_equal(ob[j, :wn], wx1[:wn])


def test_a_one_pixel_head_part_takes_blas_one_point_order():
    """A head part of one pixel: its head distances as numpy computed them for that one
    point (BLAS's one-point order), which here differ from the same point's among
    others."""
    from mistool.tracking.split import _head_labels

    c = 238.0
    ax = _mirror_axes(c)
    ax.head_len = np.full(2, 30.0)
    xs = np.arange(150.0, 420.0, 1.0)
    line = np.stack([xs, np.full(len(xs), c)], 1)
    many = _part_distance_before("clasper", line, ax, [{}, {}]).argmin(0)
    alone = np.array(
        [_part_distance_before("clasper", q[None], ax, [{}, {}]).argmin(0)[0] for q in line]
    )
    flips = np.flatnonzero(many != alone)
    assert len(flips), "no point whose head turns on BLAS's order"
    x, y = line[flips[0]]
    mask = np.ones((1, 1), bool)
    box = RotatedBox(0.0, 0.0, 1.0, 1.0, 0.0)
    part = PartObservation("clasper", box, np.zeros((4, 2)), 1, mask, (int(x), int(y)))
    _, lab = _head_labels(part, ax, [{}, {}], [])
    assert lab[0] == alone[flips[0]] != many[flips[0]]


def _border_runs_before(inst: Any) -> list:
    """``split.border_runs`` as it was (commit b04a2f1): the border loop in numpy."""
    from mistool.tracking.split import ENTRY_MAX_GAP_PX, ENTRY_MIN_PX, _border_index_to_xy

    shaft = inst.parts.get("shaft")
    if shaft is None or inst.image_shape is None:
        return []
    hh, ww = inst.image_shape
    x0, y0 = shaft.offset
    m = shaft.mask
    h, w = m.shape
    if x0 > 0 and y0 > 0 and x0 + w < ww and y0 + h < hh:
        return []
    n = 2 * (ww - 1) + 2 * (hh - 1)
    on = np.zeros(n, bool)
    xs, ys = np.arange(x0, x0 + w), np.arange(y0, y0 + h)
    if y0 == 0:
        on[xs[m[0]]] = True
    if x0 + w == ww:
        on[(ww - 1 + ys[m[:, -1]]) % n] = True
    if y0 + h == hh:
        on[(ww - 1) + (hh - 1) + (ww - 1 - xs[m[-1]])] = True
    if x0 == 0:
        on[(2 * (ww - 1) + (hh - 1) + (hh - 1 - ys[m[:, 0]])) % n] = True
    if on.sum() < ENTRY_MIN_PX or on.all():
        return []
    start = int(np.argmin(on))
    roll = np.roll(on, -start).astype(np.int8)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], roll, [0]])))
    runs: list[list[int]] = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if runs and int(a) - runs[-1][1] <= ENTRY_MAX_GAP_PX:
            runs[-1][1] = int(b)
        else:
            runs.append([int(a), int(b)])
    out = []
    for a, b in runs:
        length = b - a
        if length >= ENTRY_MIN_PX:
            first = a + start
            ends = np.array(
                [
                    _border_index_to_xy(k, ww, hh)
                    for k in (first, first + length // 2, first + length - 1)
                ]
            )
            out.append((ends, length))
    return out


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(["corner", "side", "whole", "inside", "sparse"]))
def test_border_runs_are_the_former_ones(seed, where):
    """split.border_runs (compiled loop) gives the former runs: shafts entering at a
    side, round a corner, spanning the whole image (every border pixel), inside the view,
    or touching the border in many short stretches (gaps joined, short runs dropped)."""
    from mistool.tracking.split import border_runs

    rng = np.random.default_rng(seed)
    hh, ww = int(rng.integers(20, 120)), int(rng.integers(20, 120))
    h, w = int(rng.integers(1, hh + 1)), int(rng.integers(1, ww + 1))
    if where == "whole":
        h, w = hh, ww
    mask = np.zeros((h, w), bool)
    for _ in range(int(rng.integers(1, 4))):
        a, b = rng.integers(-5, max(h, w) + 5, 2), rng.integers(-5, max(h, w) + 5, 2)
        cv2.line(
            mask.view(np.uint8),
            (int(a[0]), int(a[1])),
            (int(b[0]), int(b[1])),
            1,
            int(rng.integers(1, 15)),
        )
    if where == "sparse":
        mask |= rng.random((h, w)) < 0.3
    if where == "whole" and rng.random() < 0.5:
        mask[:] = True
    x0 = {"corner": ww - w, "inside": 1, "whole": 0}.get(where, int(rng.integers(0, ww - w + 1)))
    y0 = {"corner": 0, "inside": 1, "whole": 0}.get(where, int(rng.choice([0, hh - h])))
    if where == "inside":
        mask = mask[: max(1, min(h, hh - 2)), : max(1, min(w, ww - 2))]
    inst = _blob(mask, (x0, y0))
    inst = InstanceObservation(None, inst.parts, (0.0, 0.0), 1, (0, 0, 1, 1), (hh, ww))
    got, want = border_runs(inst), _border_runs_before(inst)
    assert len(got) == len(want)
    for (e1, n1), (e2, n2) in zip(got, want, strict=True):
        assert n1 == n2 and np.array_equal(e1, e2)
        assert type(n1) is int and e1.dtype == np.float64 and e1.shape == (3, 2)


def test_a_one_pixel_head_is_shown_by_its_one_point_distance():
    """kernels.split.shown_near of a one-pixel part: its distance as numpy computed it
    for that one point (BLAS's one-point order), at a reach between that distance and
    the one the point gets among others."""
    from mistool.kernels.split import shown_near

    rng = np.random.default_rng(5)
    box = RotatedBox(300.3, 200.7, 40.0, 12.0, 33.3)
    t = math.radians(box.angle_deg)
    for _ in range(1000):
        p = np.round(rng.uniform(250, 350, (2, 2)))
        alone = _box_distance_before(p[:1], box)[0]
        among = _box_distance_before(p, box)[0]
        if alone != among:
            break
    else:
        raise AssertionError("no point whose distance turns on BLAS's order")
    mask = np.ones((1, 1), np.uint8)
    x0, y0 = int(p[0, 0]), int(p[0, 1])
    args = (box.cx, box.cy, math.cos(t), math.sin(t), 0.5 * box.length, 0.5 * box.width)
    reach = min(alone, among)
    assert shown_near(mask, x0, y0, *args, reach, 1) == (alone <= reach)


def _distal_axis_before(boxes: dict, shape: Any) -> Any:
    """``split.distal_axis`` (numpy) as it was used by the fit (commit 7ea023c)."""
    from mistool.tracking.instances import unit_vector
    from mistool.tracking.split import Axis

    sb = boxes["shaft"]
    u = unit_vector(sb.angle_deg)
    c = np.array([sb.cx, sb.cy])
    others = [b for p, b in boxes.items() if p != "shaft"]
    if others:
        o = np.mean([[b.cx, b.cy] for b in others], axis=0)
        if (o - c) @ u < 0:
            u = -u
        back = math.inf
    else:
        back = sb.length
        if shape is not None:
            h, w = shape

            def inside(q: np.ndarray) -> float:
                return float(min(q[0], w - 1 - q[0], q[1], h - 1 - q[1]))

            if inside(c - 0.5 * sb.length * u) > inside(c + 0.5 * sb.length * u):
                u = -u
    return Axis(c + 0.5 * sb.length * u, u, back)


def _initial_axes_before(expected: list, axes: Any, shape: Any) -> Any:
    """``split._initial_axes`` and ``_head_length`` as they were (commit 7ea023c)."""
    from mistool.tracking.split import (
        HEAD_LENGTH_WIDTHS,
        HEAD_SEEN_MARGIN,
        SPLIT_END_MARGIN,
        _Axes,
    )

    def head_length(e: dict, d: np.ndarray, r: float) -> float:
        longest = 2.0 * HEAD_LENGTH_WIDTHS * r
        heads = [b for p, b in e.items() if p != "shaft"]
        if not heads:
            return longest
        along = np.concatenate([b.corners() @ d for b in heads])
        reach = float(along.max() - along.min())
        return min(longest, max(2.0 * r, HEAD_SEEN_MARGIN * reach))

    if axes is None:
        axes = [_distal_axis_before(e, shape) for e in expected]
    dirs = np.array([a.direction for a in axes], dtype=np.float64)
    ends0 = np.array([a.end for a in axes], dtype=np.float64)
    margin = np.array([SPLIT_END_MARGIN * e["shaft"].length for e in expected])
    radius = np.array([max(e["shaft"].width / 2.0, 1.0) for e in expected])
    return _Axes(
        ends=ends0 + margin[:, None] * dirs,
        dirs=dirs,
        back=np.array([a.back for a in axes], dtype=np.float64),
        radius=radius,
        limit_end=ends0,
        start_dirs=dirs.copy(),
        margin=margin,
        head_len=np.array(
            [head_length(e, d, r) for e, d, r in zip(expected, dirs, radius, strict=True)]
        ),
    )


@settings(max_examples=300, deadline=None)
@given(
    st.integers(0, 2**32 - 1), st.integers(1, 4), st.sampled_from(["distal", "no shape", "given"])
)
def test_the_compiled_initial_axes_are_the_former_ones(seed, k, how):
    """split._initial_axes (compiled) gives the former axes bit for bit: shafts with and
    without other parts (their mean deciding the distal side, their corners the head
    length), stubs near the image border, thin shafts (radius 1), given axes."""
    from mistool.tracking.split import Axis, _initial_axes

    rng = np.random.default_rng(seed)

    def box(length_max: float) -> RotatedBox:
        length = float(rng.uniform(0.5, length_max))
        x, y = rng.uniform(-20, 740, 2)
        return RotatedBox(
            float(x),
            float(y),
            length,
            length * float(rng.uniform(0, 1)),
            float(rng.uniform(0, 180)),
        )

    expected = []
    for _ in range(k):
        e = {"shaft": box(400.0)}
        for p in ("wrist", "clasper"):
            if rng.random() < 0.5:
                e[p] = box(60.0)
        if rng.random() < 0.3:  # the others before the shaft
            e = {p: e[p] for p in reversed(list(e))}
        if rng.random() < 0.15:  # a lone shaft in the middle: both ends as far inside
            e = {"shaft": RotatedBox(359.5, 287.5, 100.0, 10.0, 0.0)}
        expected.append(e)
    shape = None if how == "no shape" else (576, 720)
    axes = None
    if how == "given":
        t = rng.uniform(0, 2 * math.pi, k)
        axes = [
            Axis(rng.uniform(0, 700, 2), np.array([math.cos(a), math.sin(a)]), float(b))
            for a, b in zip(t, np.where(rng.random(k) < 0.5, math.inf, 100.0), strict=True)
        ]
    got, want = _initial_axes(expected, axes, shape), _initial_axes_before(expected, axes, shape)
    for name in ("ends", "dirs", "back", "radius", "limit_end", "start_dirs", "margin", "head_len"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name


def _entry_lane_before(pts: np.ndarray, mid: np.ndarray, half: float) -> np.ndarray:
    """``split._entry_lane`` as it was (commit ff8f414): (N, K) numpy products."""
    from mistool.tracking.split import _ENTRY_DIRS

    rel = pts - mid
    along = rel @ _ENTRY_DIRS
    across = rel @ np.stack([-_ENTRY_DIRS[1], _ENTRY_DIRS[0]])
    inside = (along >= 0.0) & (np.abs(across) <= half)
    return pts[inside[:, int(np.argmax(inside.sum(axis=0)))]]


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 3, 40, 700, 4000]), st.booleans())
def test_the_compiled_entry_lane_is_the_former_one(seed, n, border):
    """split._entry_lane (compiled) keeps the points the former (N, K) products kept:
    lanes along and across a shaft from the border, one point (BLAS's one-point order),
    points on a lane's edge (pixel centres, half-integer widths)."""
    from mistool.tracking.split import _entry_lane

    rng = np.random.default_rng(seed)
    mid = np.array([0.0, float(rng.integers(0, 576))]) if border else rng.uniform(0, 700, 2)
    t = rng.uniform(-1.2, 1.2)
    along = rng.uniform(0, 200, n)
    across = rng.normal(0, rng.uniform(2, 40), n)
    pts = mid + np.stack(
        [along * math.cos(t) - across * math.sin(t), along * math.sin(t) + across * math.cos(t)], 1
    )
    if rng.random() < 0.5:
        pts = np.round(pts)
    half = float(rng.integers(1, 40)) * 0.5
    assert np.array_equal(_entry_lane(pts, mid, half), _entry_lane_before(pts, mid, half))


def _with_part_before(inst: Any, part: str, xy: np.ndarray, min_area: int) -> Any:
    """``heads._with_part`` as it was (commit 7cc3df9): the pixels' bounds by numpy's
    min and max over the first axis."""
    from mistool.model import PARTS
    from mistool.tracking.instances import make_instance, part_observation

    parts = {p: o for p, o in inst.parts.items() if p != part}
    if len(xy) >= min_area:
        ij = xy.astype(np.int64)
        x0, y0 = ij.min(axis=0)
        x1, y1 = ij.max(axis=0) + 1
        m = np.zeros((y1 - y0, x1 - x0), np.uint8)
        m[ij[:, 1] - y0, ij[:, 0] - x0] = 255
        obs = part_observation(part, m, int(x0), int(y0), min_area)
        if obs is not None:
            parts[part] = obs
    if not parts:
        return None
    return make_instance(inst.label, {p: parts[p] for p in PARTS if p in parts}, inst.image_shape)


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 400), st.sampled_from([1, 5, 50]))
def test_a_head_handed_over_is_the_former_instance(seed, n, min_area):
    """heads._with_part (the pixels painted on a larger canvas by the hand-over kernel,
    their count and bounds beside it) gives the former instance made from their list:
    every value, box and mask bit."""
    from mistool.tracking.heads import _with_part
    from mistool.tracking.instances import make_instance, part_observation

    rng = np.random.default_rng(seed)
    m = np.zeros((40, 60), np.uint8)
    cv2.line(m, (2, 3), (55, 30), 255, 6)
    shaft = part_observation("shaft", m, int(rng.integers(0, 300)), int(rng.integers(0, 300)), 1)
    assert shaft is not None
    inst = make_instance(None, {"shaft": shaft}, (576, 720))
    c = rng.uniform(20, 500, 2)
    xy = np.unique(np.floor(c + rng.normal(0, 12, (n, 2))).clip(0, 700), axis=0)
    rng.shuffle(xy)
    ij = xy.astype(np.int64)
    canvas = np.zeros((720, 760), np.uint8)  # (at (-5, -7), as the kernel paints it)
    canvas[ij[:, 1] + 7, ij[:, 0] + 5] = 255
    bounds = np.zeros(12, np.int64)
    bounds[:3] = -5, -7, len(ij)
    if len(ij):
        bounds[3:7] = *ij.min(axis=0), *(ij.max(axis=0) + 1)
    got = _with_part(inst, "clasper", canvas, bounds, 2, min_area)
    want = _with_part_before(inst, "clasper", xy, min_area)
    assert _same_instance(got, want)


def _lane_bins_before(q: np.ndarray, p: np.ndarray, d: np.ndarray, width: float) -> np.ndarray:
    """``split.head_stop``'s ``lane_bins`` as it was (commit 7cc3df9), in numpy."""
    step = max(0.25 * width, 1.0)
    start = 1.0 * width
    rel = q - p
    along = rel @ d
    across = np.abs(rel[:, 0] * d[1] - rel[:, 1] * d[0])
    return ((along[(across <= 0.5 * width) & (along > start)] - start) // step).astype(np.int64)


@settings(max_examples=300, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.sampled_from([0, 1, 2, 3, 50, 4000]),
    st.booleans(),
    st.floats(0.5, 80.0),
)
def test_the_compiled_lane_bins_are_numpys(seed, n, on_grid, width):
    """kernels.split.lane_bins (head_stop's lane) gives numpy's bins: the points in the
    lane in their order, ``rel @ d`` by dgemv's order, numpy's float floor division;
    pixel-grid points and entries (ties on the lane's edges) included."""
    from mistool.kernels.split import lane_bins

    rng = np.random.default_rng(seed)
    q = rng.uniform(-50, 800, (n, 2))
    p = rng.uniform(0, 700, 2)
    if on_grid:
        q, p = np.floor(q), np.floor(p)
    t = float(rng.uniform(0, 2 * math.pi))
    d = np.array([math.cos(t), math.sin(t)])
    if on_grid and rng.random() < 0.3:  # along an axis: points on the lane's edges
        d = np.array([1.0, 0.0]) if rng.random() < 0.5 else np.array([0.0, -1.0])
    step = max(0.25 * width, 1.0)
    got = lane_bins(q, float(p[0]), float(p[1]), float(d[0]), float(d[1]), 0.5 * width, width, step)
    assert np.array_equal(got, _lane_bins_before(q, p, d, width))


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e6, 1e6), st.floats(-1e3, 1e3).filter(lambda b: b != 0))
def test_the_compiled_floor_division_is_numpys(a, b):
    """kernels.split.floor_divide: numpy's float ``//`` bit for bit (signs, exact
    multiples, the nearest-integer correction)."""
    import numba

    from mistool.kernels.split import floor_divide

    call = numba.njit(lambda x, y: floor_divide(x, y))  # (a helper: called from a kernel)

    for x, y in ((a, b), (float(np.round(a)), float(np.round(b)) or 1.0), (a, 0.1), (-a, 0.3)):
        with np.errstate(all="ignore"):  # (huge quotients: numpy's own overflow)
            want = np.float64(x) // np.float64(y)
        got = call(x, y)
        assert np.float64(got).tobytes() == want.tobytes()


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_pixels_by_findnonzero_are_numpys_nonzero(seed):
    """split._pixels and border_entries' window (OpenCV's findNonZero, also of a
    window's strided view) give np.nonzero's pixels in its order."""
    from mistool.tracking.split import _nonzero_xy, _pixels

    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 60)), int(rng.integers(1, 60))
    mask = rng.random((h, w)) < rng.uniform(0, 1)
    box = RotatedBox(0.0, 0.0, 1.0, 1.0, 0.0)
    part = PartObservation("shaft", box, np.zeros((4, 2)), 1, mask, (7, 11))
    ys, xs = np.nonzero(mask)
    want = np.stack([xs + 7, ys + 11], 1).astype(np.float64)
    got = _pixels(part)
    assert got.dtype == np.float64 and np.array_equal(got, want)
    ya, xa = int(rng.integers(0, h)), int(rng.integers(0, w))
    yb, xb = int(rng.integers(ya, h + 1)), int(rng.integers(xa, w + 1))
    xs2, ys2 = _nonzero_xy(mask[ya:yb, xa:xb])
    wys, wxs = np.nonzero(mask[ya:yb, xa:xb])
    assert np.array_equal(xs2, wxs) and np.array_equal(ys2, wys)


# -- the twelfth session: a piece of several components measured without its contour ----


def _blobs(rng: np.random.Generator) -> np.ndarray:
    """A 0/1 crop of two to five blobs (ellipses, polygons, bars at 0, 45, 90, 135 deg
    or any angle, squares, lines), some bitten: mostly several 8-connected components,
    as a shaft cut in two by another tool's, some of them touching or nested."""
    h, w = int(rng.integers(2, 120)), int(rng.integers(2, 120))
    m = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(2, 6))):
        kind = int(rng.integers(0, 5))
        if kind == 0:
            centre = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            axes = (int(rng.integers(0, 30)), int(rng.integers(0, 30)))
            cv2.ellipse(m, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        elif kind == 1:
            pts = rng.integers(-5, (w + 5, h + 5), (int(rng.integers(3, 8)), 2))
            cv2.fillPoly(m, [pts.astype(np.int32)], 1)
        elif kind == 2:
            angle = float(rng.choice([0, 45, 90, 135, float(rng.uniform(0, 180))]))
            size = (float(rng.integers(1, 60)), float(rng.integers(1, 15)))
            corners = cv2.boxPoints(((rng.uniform(0, w), rng.uniform(0, h)), size, angle))
            cv2.fillPoly(m, [np.round(corners).astype(np.int32)], 1)
        elif kind == 3:
            a, b = rng.integers(-5, max(h, w) + 5, (2, 2))
            cv2.line(m, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), 1, int(rng.integers(1, 5)))
        else:
            x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
            m[y : y + int(rng.integers(1, 10)), x : x + int(rng.integers(1, 10))] = 1
    if rng.random() < 0.3:  # bites and specks
        m[rng.random((h, w)) < 0.04] = 0
        m[rng.random((h, w)) < 0.01] = 1
    return m


@functools.cache
def _hull_of_rows() -> Any:
    """``fit_runs_box``'s hull of a crop's pixels from its rows' extremes
    (``boxes._row_chains``) and, for several kept components, put in their contours'
    order (``boxes._contour_order``): ``(kept, safe, x0, y0, hull)``, compiled once (the
    helpers are called from kernels)."""
    import numba

    from mistool.kernels import boxes as kb

    @numba.njit
    def hull_of_rows(ry, rx0, rx1, n, min_area):  # type: ignore[no-untyped-def]
        parent, area, kept, total, x0, y0, kh, kw, store, lo, hi, sx, sy = kb._kept_crop(
            ry, rx0, rx1, n, min_area
        )
        hv = np.empty((2 * kh + 2, 2), np.int32)
        m = kb._row_chains(lo, hi, kh, hv) if total else 0
        safe = m >= 3
        for k in range(m):
            if safe and kb._ring_arcs(store, kw, hv[k, 0], hv[k, 1]) != 1:
                safe = False
        if safe and kept > 1:
            m = kb._contour_order(hv, m, ry, rx0, rx1, parent, area, min_area, n, x0, y0, lo, hi)
        return kept, safe, x0, y0, hv[:m].copy()

    return hull_of_rows


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 3, 20]))
def test_several_components_hull_is_in_the_traced_contours_convex_hull_order(seed, min_area):
    """The hull of several kept components from their rows' extremes, put in the
    contours' order (``boxes._contour_order``: by component in reverse raster order,
    then by place from the union's first pixel), is ``cv2.convexHull(clockwise=False)``
    of their traced contours (``fit_runs``' points, OpenCV's order), vertex for vertex
    and from the same start: the start decides between rectangles of equal area."""
    from mistool.kernels.boxes import fit_runs, mask_runs

    mask = _blobs(np.random.default_rng(seed))
    ry, rx0, rx1, n = mask_runs(mask)
    kept, safe, x0, y0, hull = _hull_of_rows()(ry, rx0, rx1, n, min_area)
    if not safe or kept < 2:
        return
    _, _, points, _ = fit_runs(ry, rx0, rx1, n, min_area, 0, 0)
    want = cv2.convexHull(points, clockwise=False).reshape(-1, 2)
    assert np.array_equal(hull + (x0, y0), want)


def test_several_components_hull_order_covers_many_shapes():
    """Many of the shapes of the test above take the path it checks (several kept
    components, every hull vertex passed once: 135 of 400 here): it is not vacuous."""
    from mistool.kernels.boxes import mask_runs

    rng = np.random.default_rng(0)
    taken = 0
    for _ in range(400):
        ry, rx0, rx1, n = mask_runs(_blobs(rng))
        kept, safe, _, _, _ = _hull_of_rows()(ry, rx0, rx1, n, 0)
        taken += bool(safe and kept > 1)
    assert taken >= 100


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 3, 20]))
def test_a_piece_of_several_components_is_measured_as_from_its_contours(seed, min_area):
    """fit_runs_box of several kept components (a shaft piece cut in two by another
    tool's: since the twelfth session, from the rows' hull, without tracing) is the box
    of their traced contours (fit_runs + grown_box_of), bit for bit, at any offset."""
    from mistool.kernels.boxes import fit_runs, fit_runs_box, grown_box_of, mask_runs

    rng = np.random.default_rng(seed)
    ry, rx0, rx1, n = mask_runs(_blobs(rng))
    ox, oy = int(rng.integers(0, 700)), int(rng.integers(0, 500))
    info, crop, box, corners = fit_runs_box(ry, rx0, rx1, n, min_area, ox, oy)
    want_info, want_crop, points, hull = fit_runs(ry, rx0, rx1, n, min_area, ox, oy)
    assert info == want_info and np.array_equal(crop, want_crop)
    if want_info[0] == 0:
        assert box == (0.0,) * 5 and not corners.any()
        return
    want_corners = np.zeros((4, 2))
    want_box = grown_box_of(points, hull, want_corners)
    assert np.array_equal(np.array(box).view(np.int64), np.array(want_box).view(np.int64))
    assert np.array_equal(corners.view(np.int64), want_corners.view(np.int64))


@settings(max_examples=300, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.integers(1, 40),
    st.integers(1, 300),
    st.integers(0, 63),
    st.integers(0, 9),
    st.sampled_from(["random", "runs", "inverted runs"]),
)
def test_runs_from_the_packed_bits_are_mask_runs(seed, h, w, lead, tail, kind):
    """kernels.boxes.bits_runs: an (h, w) mask's row runs read from its ``np.packbits``
    bits (from any bit of a byte: 0-63 other bits before it, 0-9 bytes after it, none:
    the mask's last bits at the array's end) are exactly mask_runs' of the mask (rows of
    random pixels, of long runs, or of long gaps; widths 1-300: a row's last < 64 pixels
    read apart)."""
    from mistool.kernels.boxes import bits_runs, mask_runs

    rng = np.random.default_rng(seed)
    if kind == "random":
        mask = rng.random((h, w)) < rng.random()
    else:
        mask = np.zeros((h, w), bool)
        for _ in range(int(rng.integers(0, 3 * h + 1))):
            y, a = int(rng.integers(0, h)), int(rng.integers(0, w))
            mask[y, a : int(rng.integers(a, w + 1))] = True
        if kind == "inverted runs":
            mask = ~mask
    noise = rng.random(lead + 8 * tail) < 0.5
    bits = np.packbits(np.concatenate([noise[:lead], mask.ravel(), noise[lead:]]))
    want = mask_runs(mask.view(np.uint8))
    got = bits_runs(bits, lead, h, w)
    n = want[3]
    assert got[3] == n
    for a, b in zip(got[:3], want[:3], strict=True):
        assert a.dtype == b.dtype and np.array_equal(a[:n], b[:n])


def test_a_blobs_shaft_runs_come_from_its_bits_while_still_packed():
    """A worker's deferred frame unpacked by the caller (mistool.parallel): the blob's
    shaft is left packed, and BlobPixels reads its runs (and so its points) from the
    bits, the mask never unpacked; the same runs and points as from the mask."""
    from mistool import parallel
    from mistool.kernels.boxes import mask_runs

    rng = np.random.default_rng(11)
    mask = np.zeros((70, 230), np.uint8)
    for _ in range(3):
        a, b = rng.integers(0, 230, 2), rng.integers(0, 70, 2)
        cv2.line(mask, (int(a[0]), int(b[0])), (int(a[1]), int(b[1])), 1, 9)
    mask = mask.astype(bool)
    box = RotatedBox(0.0, 0.0, 1.0, 1.0, 0.0)
    head = PartObservation("wrist", box, np.zeros((4, 2)), 3, rng.random((3, 5)) < 0.5, (1, 2))
    shaft = PartObservation("shaft", box, np.zeros((4, 2)), int(mask.sum()), mask, (40, 9))
    inst = InstanceObservation(
        None, {"wrist": head, "shaft": shaft}, (0.0, 0.0), 9, (0, 0, 1, 1), (300, 400)
    )
    sent = parallel.FrameResult([inst], None, np.zeros(0, np.int64), (300, 400), deferred=True)
    (got,) = parallel.unpack_frames(parallel.pack_frames([sent]))
    blob = got.instances[0]
    assert "mask" in blob.parts["wrist"].__dict__  # (a head: unpacked with the batch)
    pixels = BlobPixels(blob)
    ry, rx0, rx1, n = pixels.shaft_runs()
    assert pixels.shaft_shape() == mask.shape
    assert "mask" not in blob.parts["shaft"].__dict__  # read from the bits
    wy, wx0, wx1, wn = mask_runs(mask.view(np.uint8))
    assert n == wn and np.array_equal(ry[:n], wy[:n]) and np.array_equal(rx0[:n], wx0[:n])
    assert np.array_equal(rx1[:n], wx1[:n])
    ys, xs = np.nonzero(mask)
    assert np.array_equal(pixels.shaft_points(), np.stack([xs + 40, ys + 9], 1).astype(float))
    assert np.array_equal(blob.parts["shaft"].mask, mask)  # (read: unpacked then)
