"""The metric pose's faster pieces equal the definitions they replace, bit for bit
(issue 13: the per-frame pose's cost). Each ``_..._before`` is the code as it was at
commit 4f43a12."""

from __future__ import annotations

import math

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.pose.cylinder import cross3, pixel_rays, project, quat_from_z
from mistool.pose.measure import (
    _crop_bounds,
    _jaw_tips,
    _mean_rows,
    _near,
    _on_border,
    _window_max,
)
from mistool.pose.quality import hull_of_cylinder, iou_polygon_mask, perpendicular_basis
from mistool.pose.silhouette import (
    Boundary,
    Canvas,
    _tls_moments,
    add_rows,
    boundary_points,
    fit_line_robust,
    make_canvas,
    sub_rows,
    sum_rows,
    take_rows,
)


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


@settings(max_examples=200, deadline=None)
@given(_points(), st.integers(0, 2**32 - 1))
def test_take_sum_and_mean_of_rows_equal_numpy_indexing_and_sums(p: np.ndarray, seed: int) -> None:
    rng = np.random.default_rng(seed)
    sel = rng.random(len(p)) < 0.5
    idx = np.flatnonzero(sel)
    assert _same(take_rows(p, sel), p[sel])
    assert _same(take_rows(p, idx), p[idx])
    assert _same(take_rows(p[:, ::-1], idx), p[:, ::-1][idx])  # not C-contiguous
    assert _same(sum_rows(p), p.sum(axis=0))
    c = rng.normal(0.0, 300.0, 2)
    assert _same(sub_rows(p, c), p - c)
    shifted = p.copy()
    add_rows(shifted, (float(c[0]), float(c[1])))
    assert _same(shifted, p + (float(c[0]), float(c[1])))
    if sel.any():
        assert _same(_mean_rows(p, sel), p[sel].mean(axis=0))


def _near_before(pts: np.ndarray, other: np.ndarray) -> np.ndarray:
    lo, hi = other.min(axis=0) - 2.0, other.max(axis=0) + 2.0
    box = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))
    if not len(box):
        return box
    d2 = ((pts[box, None, :] - other[None, ::2, :]) ** 2).sum(axis=2)
    return box[d2.min(axis=1) < 4.0]


@settings(max_examples=200, deadline=None)
@given(_points(), _points())
def test_points_near_other_parts_as_before(pts: np.ndarray, other: np.ndarray) -> None:
    other = other[: max(1, len(other) // 4)] * 0.2 + 200.0  # a small cluster among pts
    assert np.array_equal(_near(pts, other), _near_before(pts, other))


_DX = np.array([1, -1, 0, 0])
_DY = np.array([0, 0, 1, -1])


def _boundary_before(canvas: Canvas, outline: np.ndarray) -> Boundary:
    lab = canvas.labels
    h, w = lab.shape
    pad = np.full((h + 2, w + 2), 1, dtype=np.uint8)
    pad[1:-1, 1:-1] = lab
    ij = np.asarray(outline, dtype=np.int64)
    x = ij[:, 0] - (canvas.x0 - 1)
    y = ij[:, 1] - (canvas.y0 - 1)
    nb = pad[y[None, :] + _DY[:, None], x[None, :] + _DX[:, None]]
    f = np.empty((4, len(x), 2))
    f[:, :, 0] = x[None, :] + (canvas.x0 - 1 + 0.5 * _DX[:, None])
    f[:, :, 1] = y[None, :] + (canvas.y0 - 1 + 0.5 * _DY[:, None])
    return Boundary(f[nb == 0], f[nb == 2])


def _paste_before(
    dst: np.ndarray, x0: int, y0: int, mask: np.ndarray, ox: int, oy: int, value: int
) -> None:
    h, w = dst.shape
    mh, mw = mask.shape
    xa, ya = max(ox, x0), max(oy, y0)
    xb, yb = min(ox + mw, x0 + w), min(oy + mh, y0 + h)
    if xa >= xb or ya >= yb:
        return
    dst[ya - y0 : yb - y0, xa - x0 : xb - x0][mask[ya - oy : yb - oy, xa - ox : xb - ox]] = value


def _canvas_before(
    part: np.ndarray,
    offset: tuple[int, int],
    others: list[tuple[np.ndarray, tuple[int, int]]],
    image_shape: tuple[int, int],
    margin: int = 2,
) -> Canvas:
    H, W = image_shape
    ox, oy = offset
    mh, mw = part.shape
    x0, y0 = max(ox - margin, 0), max(oy - margin, 0)
    x1, y1 = min(ox + mw + margin, W), min(oy + mh + margin, H)
    lab = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    for m, (px, py) in others:
        _paste_before(lab, x0, y0, m, px, py, 2)
    _paste_before(lab, x0, y0, part, ox, oy, 1)
    return Canvas(lab, x0, y0)


@st.composite
def _parts(
    draw: st.DrawFn,
) -> tuple[np.ndarray, tuple[int, int], list[tuple[np.ndarray, tuple[int, int]]]]:
    """A blob-like part mask (some at the image border) and up to two other parts'."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    masks = []
    for _ in range(int(rng.integers(1, 4))):
        h, w = (int(v) for v in rng.integers(3, 60, 2))
        m = np.zeros((h, w), np.uint8)
        for _ in range(int(rng.integers(1, 4))):
            c = (int(rng.integers(0, w)), int(rng.integers(0, h)))
            axes = (int(rng.integers(1, w)), int(rng.integers(1, h)))
            cv2.ellipse(m, c, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        if rng.random() < 0.3:
            m |= (rng.random((h, w)) < 0.1).astype(np.uint8)
        offset = (int(rng.integers(0, 60)), int(rng.integers(0, 40)))
        masks.append((m.view(bool), offset))
    return masks[0][0], masks[0][1], masks[1:]


@settings(max_examples=200, deadline=None)
@given(_parts())
def test_canvas_and_boundary_points_as_before(case: tuple) -> None:  # type: ignore[type-arg]
    part, offset, others = case
    # the part reaches the image's far border (pairs leaving the image give no point)
    shape = (offset[1] + part.shape[0], offset[0] + part.shape[1])
    others = [(m[: shape[0] - oy, : shape[1] - ox], (ox, oy)) for m, (ox, oy) in others]
    canvas = make_canvas(part, offset, others, shape)
    before = _canvas_before(part, offset, others, shape)
    assert (canvas.x0, canvas.y0) == (before.x0, before.y0)
    assert _same(canvas.labels, before.labels)
    contours, _ = cv2.findContours(part.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return
    outline = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64) + offset
    got, ref = boundary_points(canvas, outline), _boundary_before(canvas, outline)
    assert _same(got.bg, ref.bg) and _same(got.other, ref.other)


def _pixels_within_before(
    mask_u8: np.ndarray, offset: tuple[int, int], centre: np.ndarray, rad: float
) -> np.ndarray:
    h, w = mask_u8.shape
    cx, cy = float(centre[0]) - offset[0], float(centre[1]) - offset[1]
    x0, y0 = max(int(math.floor(cx - rad)), 0), max(int(math.floor(cy - rad)), 0)
    x1, y1 = min(int(math.ceil(cx + rad)) + 1, w), min(int(math.ceil(cy + rad)) + 1, h)
    if x0 >= x1 or y0 >= y1:
        return np.zeros((0, 2))
    ys, xs = np.nonzero(mask_u8[y0:y1, x0:x1])
    area = np.stack([xs + float(offset[0] + x0), ys + float(offset[1] + y0)], axis=1)
    dc = area - centre
    return area[np.einsum("ij,ij->i", dc, dc) <= rad * rad]


def _jaw_tips_before(
    mask_u8: np.ndarray, offset: tuple[int, int], jpx: np.ndarray, width_px: float
) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray], list[float]]:
    contours, _ = cv2.findContours(mask_u8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return [], [], [], []
    c = max(contours, key=len).reshape(-1, 2).astype(np.float64) + offset
    dj = c - jpx
    d = np.sqrt(np.einsum("ij,ij->i", dj, dj))
    n = len(c)
    win = int(max(2, min(n // 4, round(width_px))))
    padded = np.concatenate([d[-win:], d, d[:win]])
    local = _window_max(padded, 2 * win + 1)
    cand = np.flatnonzero((d >= local) & (d >= 0.5 * d.max()))
    cand = cand[np.argsort(-d[cand])]
    picks: list[int] = []
    for i in cand:
        if all(math.hypot(*(c[i] - c[j])) > 1.0 * width_px for j in picks):
            picks.append(int(i))
        if len(picks) == 2:
            break
    rad = 2.5 * width_px
    if len(picks) == 2:
        rad = min(rad, 0.5 * math.hypot(*(c[picks[0]] - c[picks[1]])))
    ends, nears, dirs, halfw = [], [], [], []
    for k in picks:
        nb = _pixels_within_before(mask_u8, offset, c[k], rad)
        if len(nb) < 3:
            continue
        m = nb.mean(axis=0)
        dd = nb - m
        cov = dd.T @ dd
        phi = 0.5 * math.atan2(2.0 * cov[0, 1], cov[0, 0] - cov[1, 1])
        e = np.array([math.cos(phi), math.sin(phi)])
        if e @ (c[k] - jpx) < 0:
            e = -e
        ends.append(m + (float((dd @ e).max()) + 0.5) * e)
        dirs.append(e)
        halfw.append(min(0.5 * float(np.ptp(dd @ np.array([-e[1], e[0]]))) + 0.5, width_px))
        dc = c - c[k]
        nears.append(c[np.einsum("ij,ij->i", dc, dc) <= rad * rad])
    return ends, nears, dirs, halfw


@settings(max_examples=200, deadline=None)
@given(_parts(), st.floats(2.0, 30.0), st.floats(-50.0, 150.0), st.floats(-50.0, 150.0))
def test_jaw_tips_as_before(case: tuple, width: float, ju: float, jv: float) -> None:  # type: ignore[type-arg]
    mask, offset, _ = case
    jpx = np.array([ju, jv])
    got = _jaw_tips(mask.view(np.uint8), offset, jpx, width)
    ref = _jaw_tips_before(mask.view(np.uint8), offset, jpx, width)
    assert len(got[0]) == len(ref[0])
    for g, r in zip(got[:3], ref[:3], strict=True):
        assert all(_same(a, b) for a, b in zip(g, r, strict=True))
    assert got[3] == ref[3]


_THETA = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)


def _basis_before(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ref = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = cross3(a, ref)
    e1 /= math.sqrt(float(e1 @ e1))
    return e1, cross3(a, e1)


def _hull_before(
    p_a: np.ndarray, p_b: np.ndarray, r_a: float, r_b: float, K: np.ndarray, min_z_mm: float = 1.0
) -> np.ndarray | None:
    d = p_b - p_a
    nd = math.sqrt(float(d @ d))
    if not math.isfinite(nd) or nd < 1e-6:
        return None
    e1, e2 = _basis_before(d / nd)
    ring = np.cos(_THETA)[:, None] * e1 + np.sin(_THETA)[:, None] * e2
    pts = np.concatenate([p_a + r_a * ring, p_b + r_b * ring])
    if pts[:, 2].min() < min_z_mm:
        return None
    uv = project(pts, K).astype(np.float32)
    return cv2.convexHull(uv).reshape(-1, 2)


def _iou_before(
    poly: np.ndarray | None,
    mask: np.ndarray,
    offset: tuple[int, int],
    image_shape: tuple[int, int],
    max_pixels: int = 40000,
) -> float:
    if poly is None:
        return float("nan")
    H, W = image_shape
    ox, oy = offset
    mh, mw = mask.shape
    x0 = int(max(0, min(ox, np.floor(poly[:, 0].min()))))
    y0 = int(max(0, min(oy, np.floor(poly[:, 1].min()))))
    x1 = int(min(W, max(ox + mw, np.ceil(poly[:, 0].max()) + 1)))
    y1 = int(min(H, max(oy + mh, np.ceil(poly[:, 1].max()) + 1)))
    if x1 <= x0 or y1 <= y0:
        return float("nan")
    st_ = 1 if (x1 - x0) * (y1 - y0) <= max_pixels else 2
    x0, y0 = x0 - x0 % st_, y0 - y0 % st_
    hc, wc = -(-(y1 - y0) // st_), -(-(x1 - x0) // st_)
    canvas = np.zeros((hc, wc), dtype=np.uint8)
    shifted = np.round((poly - np.array([x0, y0], dtype=np.float64)) * (16.0 / st_)).astype(
        np.int32
    )
    cv2.fillConvexPoly(canvas, shifted, 1, lineType=cv2.LINE_8, shift=4)
    rend = canvas.view(bool)
    obs = np.zeros_like(rend)
    ia, ja = max(0, -(-(oy - y0) // st_)), max(0, -(-(ox - x0) // st_))
    ib, jb = min(hc, -(-(oy + mh - y0) // st_)), min(wc, -(-(ox + mw - x0) // st_))
    if ia < ib and ja < jb:
        sub = mask[y0 + st_ * ia - oy :: st_, x0 + st_ * ja - ox :: st_]
        obs[ia:ib, ja:jb] = sub[: ib - ia, : jb - ja]
    inter = np.count_nonzero(rend & obs)
    union = np.count_nonzero(rend | obs)
    return inter / union if union else float("nan")


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_perpendicular_basis_hull_and_iou_as_before(seed: int, axis_like: bool) -> None:
    rng = np.random.default_rng(seed)
    K = np.array([[600.0, 0.0, 359.5], [0.0, 600.0, 287.5], [0.0, 0.0, 1.0]])
    a = rng.normal(size=3)
    if axis_like:  # near +-x, +-y, +-z, and exact axes
        a = np.eye(3)[rng.integers(3)] * rng.choice([-1.0, 1.0]) + rng.choice([0.0, 1e-3]) * a
    a /= np.linalg.norm(a)
    for g, r in zip(perpendicular_basis(a), _basis_before(a), strict=True):
        assert _same(g, r)
    p_a = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(-5, 150)])
    p_b = p_a + rng.uniform(5, 150) * a
    r = float(rng.uniform(0.5, 6.0))
    poly, ref = hull_of_cylinder(p_a, p_b, r, 0.5 * r, K), _hull_before(p_a, p_b, r, 0.5 * r, K)
    assert (poly is None and ref is None) or (
        poly is not None and ref is not None and _same(poly, ref)
    )
    if poly is None:
        return
    h, w = (int(v) for v in rng.integers(1, 300, 2))
    mask = rng.random((h, w)) < rng.uniform(0.0, 1.0)
    offset = (int(rng.integers(0, 720 - w)), int(rng.integers(0, 576 - h)))
    for max_pixels in (40000, 100):
        got = iou_polygon_mask(poly, mask, offset, (576, 720), None, max_pixels)
        want = _iou_before(poly, mask, offset, (576, 720), max_pixels)
        assert got == want or (math.isnan(got) and math.isnan(want))


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


def _fit_before(
    pts: np.ndarray,
    along: np.ndarray,
    thresh_px: float = 1.5,
    iters: int = 12,
    max_points: int = 192,
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """``fit_line_robust`` (fixed draws) as it was."""
    n = len(pts)
    if n < 8:
        return None
    keep = None
    if n > max_points:
        keep = np.arange(max_points) * (n - 1) // (max_points - 1)
        pts, along = pts[keep], along[keep]
        n = max_points
    ox, oy = (pts.sum(axis=0) * (1.0 / n)).tolist()
    X = np.empty((3, n))
    X[:2] = (pts - (ox, oy)).T
    X[2] = 1.0
    x, y = X[0], X[1]
    order = np.argsort(along)
    half = n // 2
    draws = np.random.default_rng(12345).random((2, 64))
    pick_i = (draws[0, :iters] * half).astype(np.int64)
    pick_j = n - half + (draws[1, :iters] * half).astype(np.int64)
    i = order[pick_i]
    j = order[pick_j]
    H = np.empty((len(i), 3))
    H[:, 0] = y[i] - y[j]
    H[:, 1] = x[j] - x[i]
    ln = np.sqrt(H[:, 0] * H[:, 0] + H[:, 1] * H[:, 1])
    if ln.min() <= 1e-9:
        ok = ln > 1e-9
        if not ok.any():
            return None
        H, ln, i = H[ok], ln[ok], i[ok]
    H[:, :2] /= ln[:, None]
    H[:, 2] = -(H[:, 0] * x[i] + H[:, 1] * y[i])
    res = np.abs(H @ X)
    best = int(np.argmin(np.minimum(res, thresh_px).sum(axis=1)))
    inl = res[best] < thresh_px
    if np.count_nonzero(inl) < 6:
        return None
    line = _tls_moments(X[:, inl] @ X[:, inl].T)
    scale = thresh_px
    r = line @ X
    for _ in range(2):
        u = r * (1.0 / (2.5 * scale))
        w = np.maximum(1.0 - u * u, 0.0)
        w *= w
        if w.sum() < 6:
            break
        line = _tls_moments((X * w) @ X.T)
        r = line @ X
        ra = np.abs(r)
        core = ra[ra < 2.5 * scale]
        if len(core):
            scale = min(
                max(1.4826 * float(np.partition(core, len(core) // 2)[len(core) // 2]), 0.3),
                thresh_px,
            )
    inl = np.flatnonzero(np.abs(r) < max(2.5 * scale, 0.75))
    ri = r[inl]
    sigma = math.sqrt(float(ri @ ri) / len(inl)) if len(inl) else float("inf")
    line[2] -= line[0] * ox + line[1] * oy
    return line, (inl if keep is None else keep[inl]), sigma


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([8, 9, 30, 191, 192, 193, 700]), st.booleans())
def test_robust_line_fit_as_before(seed: int, n: int, pixels: bool) -> None:
    rng = np.random.default_rng(seed)
    t = np.sort(rng.uniform(0.0, 300.0, n))
    phi = rng.uniform(0.0, math.pi)
    pts = np.stack([100 + t * math.cos(phi), 200 + t * math.sin(phi)], axis=1)
    pts += rng.normal(0.0, 0.4, pts.shape)
    out = rng.random(n) < 0.2
    pts[out] += rng.normal(0.0, 8.0, (int(out.sum()), 2))  # outliers
    if pixels:
        pts = np.round(2.0 * pts) / 2.0
    along = pts @ np.array([math.cos(phi), math.sin(phi)])
    got, ref = fit_line_robust(pts, along), _fit_before(pts, along)
    assert (got is None) == (ref is None)
    if got is not None and ref is not None:
        assert _same(got[0], ref[0]) and _same(got[1], ref[1]) and got[2] == ref[2]


@settings(max_examples=200, deadline=None)
@given(_parts())
def test_border_test_within_a_crop_as_before(case: tuple) -> None:  # type: ignore[type-arg]
    mask, (ox, oy), _ = case
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    px = np.stack([xs + float(ox), ys + float(oy)], axis=1)
    for shape in ((oy + h, ox + w), (oy + h + 5, ox + w + 5), (576, 720)):
        H, W = shape
        before = (px[:, 0] <= 0) | (px[:, 1] <= 0) | (px[:, 0] >= W - 1) | (px[:, 1] >= H - 1)
        assert np.array_equal(_on_border(px, shape, _crop_bounds(mask, (ox, oy))), before)
        assert np.array_equal(_on_border(px, shape), before)
    # the jaw ends without the outline points near them: the same ends
    jpx = np.array([ox - 5.0, oy + 0.5 * h])
    full, bare = (
        _jaw_tips(mask.view(np.uint8), (ox, oy), jpx, 4.0),
        _jaw_tips(mask.view(np.uint8), (ox, oy), jpx, 4.0, with_nears=False),
    )
    assert bare[1] == [] and len(full[1]) == len(full[0])
    for g, r in zip((bare[0], bare[2]), (full[0], full[2]), strict=True):
        assert all(_same(a, b) for a, b in zip(g, r, strict=True))
    assert bare[3] == full[3]


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
