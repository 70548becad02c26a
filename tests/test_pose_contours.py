"""The pose's compiled OpenCV steps against OpenCV: the contour tracing
(``mistool.kernels.contours``: one piece, several), the convex hull and polygon fill
(``mistool.kernels.polygon``) and the quality IoU built on them; and the shaft's one-call
path (``measure._shaft_in_one_call``: one piece or several, a gap at the junction or
none) against the steps it joins.

All bit for bit: contour points, hull indices and filled pixels are integers, and the
one-call path runs the same kernels on the same points (only the Python between them is
gone)."""

from __future__ import annotations

import functools
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_pose import part_obs, unit
from test_pose_kernels import PINHOLE, SHAPE, scene

from mistool.kernels import pose as kp
from mistool.kernels.contours import CONTOURS_NESTED, external_contours, outer_contour
from mistool.kernels.polygon import convex_hull, fill_convex
from mistool.pose import measure as measure_mod
from mistool.pose.quality import Rims, rims_iou
from mistool.pose.raycast import render_instrument
from mistool.pose.silhouette import as_mask
from mistool.pose.status import reason_code

#: The fixed scenes the loops below share (each is a few ray-cast renders).
_fixed_scene = functools.lru_cache(maxsize=None)(scene)


def _opencv(mask: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(
        c.reshape(-1, 2)
        for c in cv2.findContours(mask.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    )


def _components(mask: np.ndarray) -> int:
    return int(cv2.connectedComponents(mask.view(np.uint8), connectivity=8)[0]) - 1


@st.composite
def masks(draw: st.DrawFn) -> np.ndarray:
    """Small random masks: noise of any density (one piece, several, pieces in holes,
    one-pixel lines, touching the crop's edges), or a blob with holes."""
    h, w = draw(st.integers(1, 14)), draw(st.integers(1, 14))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    if draw(st.booleans()):
        return rng.random((h, w)) < draw(st.floats(0.05, 0.95))
    m = np.zeros((h + 10, w + 10), np.uint8)
    cv2.ellipse(m, (m.shape[1] // 2, m.shape[0] // 2), (w // 2 + 3, h // 2 + 3), 30, 0, 360, 1, -1)
    m[rng.random(m.shape) < 0.08] = 0
    return m.astype(bool)


@settings(max_examples=600, deadline=None)
@given(masks())
def test_outer_contour_equals_opencv(mask: np.ndarray) -> None:
    """One piece: OpenCV's every point in its order; several: -1; none: 0."""
    pts = np.empty((4 * mask.size + 4, 2), np.int32)
    n = outer_contour(mask, pts)
    ref = _opencv(mask)
    pieces = _components(mask)
    if pieces == 0:
        assert n == 0 and not ref
    elif pieces > 1:
        assert n == -1
    else:
        assert len(ref) == 1 and np.array_equal(pts[:n], ref[0])


def _nested_boxes(mask: np.ndarray) -> bool:
    """Whether a component's bounding box holds another's strictly (8-connected)."""
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    boxes = [(x, y, x + w - 1, y + h - 1) for x, y, w, h, _ in stats[1:n]]
    return any(
        a[0] < b[0] and a[1] < b[1] and b[2] < a[2] and b[3] < a[3] for a in boxes for b in boxes
    )


@settings(max_examples=800, deadline=None)
@given(masks())
def test_external_contours_equal_opencv(mask: np.ndarray) -> None:
    """Any number of pieces: OpenCV's contours, every point in its order, and each run
    labelled with its piece's contour; -1 (ask OpenCV) only where a piece's box holds
    another's (a piece in a hole, which OpenCV leaves out, is one such case)."""
    pts = np.empty((4 * mask.size + 4, 2), np.int32)
    starts = np.empty(mask.size + 2, np.int64)
    n, runs = external_contours(mask, pts, starts)
    if n == CONTOURS_NESTED:
        assert _nested_boxes(mask)
        return
    ref = _opencv(mask)
    assert n == len(ref) and not _nested_boxes(mask)
    labels = np.zeros(mask.shape, np.int64)
    for y, x0, x1, k in runs:
        assert not labels[y, x0:x1].any()
        labels[y, x0:x1] = k
    assert np.array_equal(labels > 0, mask)
    _, comp = cv2.connectedComponents(mask.view(np.uint8), connectivity=8)
    for k, c in enumerate(ref):
        assert np.array_equal(pts[starts[k] : starts[k + 1]], c)
        x, y = c[0]
        assert np.array_equal(labels == k + 1, comp == comp[y, x])


def test_external_contours_are_bounded() -> None:
    """More pieces than ``starts`` holds: -3; a short point buffer: -2."""
    m = np.zeros((5, 9), bool)
    m[2, ::2] = True  # five single pixels
    starts = np.empty(5, np.int64)
    assert external_contours(m, np.empty((40, 2), np.int32), starts)[0] == -3
    assert external_contours(m, np.empty((3, 2), np.int32), np.empty(9, np.int64))[0] == -2


def test_the_gap_disk_rows_are_the_disk() -> None:
    """The kernels' form of the junction gap's disk (a half-width per row) is OpenCV's
    ellipse, row for row (each row centred and unbroken)."""
    g = measure_mod._JUNCTION_GAP_PX
    rows = measure_mod._GAP_ROWS
    disk = np.zeros((2 * g + 1, 2 * g + 1), np.uint8)
    for i, r in enumerate(rows):
        disk[i, g - r : g + r + 1] = 1
    assert np.array_equal(disk, measure_mod._GAP_DISK)


def test_outer_contour_on_a_long_border_and_a_short_buffer() -> None:
    """A comb's border is longer than ``4 (h + w)``: -2 with that buffer, OpenCV's
    points with the bound that always holds; a single pixel is one point."""
    comb = np.zeros((30, 40), bool)
    comb[0, :] = True
    comb[:, ::2] = True
    short = np.empty((4 * (30 + 40) + 16, 2), np.int32)
    assert outer_contour(comb, short) == -2
    full = np.empty((4 * comb.size + 4, 2), np.int32)
    n = outer_contour(comb, full)
    assert n > len(short) and np.array_equal(full[:n], _opencv(comb)[0])
    one = np.zeros((3, 3), bool)
    one[1, 2] = True
    assert outer_contour(one, full) == 1 and full[0].tolist() == [2, 1]


def test_the_longest_outline_is_opencvs_first_longest() -> None:
    """Several pieces go to OpenCV: the first of the longest, as ``max(..., key=len)``."""
    m = np.zeros((20, 30), bool)
    m[2:6, 2:6] = m[10:14, 20:24] = m[15:17, 2:4] = True
    got = measure_mod._longest_outline(m)
    assert got is not None and np.array_equal(got, max(_opencv(m), key=len))
    assert measure_mod._longest_outline(np.zeros((4, 4), bool)) is None


def _one_call_equals_steps(parts: dict, camera: object) -> object:
    """``measure._shaft_in_one_call`` against ``_shaft_points`` then ``shaft_pose``:
    the same results, quality cylinder's image, measured region and merged flag where
    the one call answers; where it does not, nothing written and a reason it may not
    (a piece's box holding another's, an outline without area, more than two other
    parts). Returns the one call's answer."""
    shaft = parts["shaft"]
    K = np.ascontiguousarray(camera.K, dtype=np.float64)  # type: ignore[attr-defined]
    res, rims = np.full(kp.OUT["size"], -7.0), Rims()
    got = measure_mod._shaft_in_one_call(parts, shaft, SHAPE, K, 4.0, res, rims)
    sp = measure_mod._shaft_points(parts, SHAPE, camera, False)  # type: ignore[arg-type]
    if got is None:  # asked for the Python path: nothing written, and it may not answer
        assert (res == -7.0).all()
        mask = as_mask(shaft.mask)
        assert (
            _nested_boxes(mask)
            or len(parts) > 3
            or isinstance(sp, str)
            or sum(cv2.moments(c)["m00"] for c in _opencv(sp.mask)) < 1.0
        )
        return got
    if isinstance(got, str):
        assert sp == got
        return got
    assert not isinstance(sp, str)
    ref, ref_rims = np.empty(kp.OUT["size"]), Rims()
    geo = np.array([*sp.offset, *sp.mask.shape, *SHAPE, measure_mod._QUALITY_MAX_PIXELS])
    kp.shaft_pose(
        sp.pix,
        sp.border,
        sp.centre,
        sp.moments,
        sp.bnd.bg,
        sp.bnd.other,
        K,
        4.0,
        measure_mod._params(),
        ref,
        geo,
        ref_rims.pts,
        ref_rims.shifted,
        ref_rims.canvas,
    )
    q = kp.OUT["quality"]  # the one call also gives the quality, shaft_pose does not
    assert np.array_equal(res[:q], ref[:q], equal_nan=True)
    if np.isnan(ref[kp.OUT["quality_a"]]):
        assert np.isnan(res[q])
    elif not res[kp.OUT["quality_opencv"]]:
        want = rims_iou(ref_rims, sp.mask, sp.offset)
        assert res[q] == want or (np.isnan(res[q]) and np.isnan(want))
    assert np.array_equal(rims.canvas, ref_rims.canvas)
    if rims.canvas[5]:
        assert np.array_equal(rims.pts, ref_rims.pts)
        assert np.array_equal(rims.shifted, ref_rims.shifted)
    assert got.offset == sp.offset and np.array_equal(got.mask, sp.mask)
    assert got.merged == sp.merged
    return got


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_shaft_in_one_call_equals_its_steps(seed: int) -> None:
    """Rendered scenes (one tool or two merged, holes, cuts, gaps at the junction, a
    wrist): the one call equals the steps it joins."""
    obs, camera, _ = scene(seed)
    if obs.parts.get("shaft") is None or camera.distorted:
        return
    _one_call_equals_steps(obs.parts, camera)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_a_shaft_in_pieces_in_one_call_equals_its_steps(seed: int) -> None:
    """Shafts in several pieces: cut across once or twice (one shaft, its pieces'
    union filled with their holes), two tools side by side (the larger measured alone),
    specks, holes in the pieces, a gap at the junction: the one call answers where no
    piece's box holds another's, and equals the steps."""
    rng = np.random.default_rng(seed)
    K = np.asarray(PINHOLE.K)
    labels = np.zeros(SHAPE, np.uint8)
    J = np.array([rng.uniform(-25, 25), rng.uniform(-20, 20), rng.uniform(50, 120)])
    a = unit([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.0, 1.0)])
    for k in range(1 + int(rng.random() < 0.5)):  # a second tool beside the first
        Jk = J + k * rng.uniform(9, 14) * unit(np.cross(a, [0.0, 0.0, 1.0]))
        tip = Jk + 10.0 * unit(a + 0.4 * rng.normal(size=3))
        labels = render_instrument(SHAPE, K, Jk - 300.0 * a, Jk, tip, 4.0, 0.6, out=labels)
    ys, xs = np.nonzero(labels == 160)
    if len(xs) == 0:
        return
    for _ in range(int(rng.integers(1, 3))):  # cuts across the shaft
        i = int(rng.integers(len(xs)))
        d = (np.array([-a[1], a[0]]) * 60).astype(int)
        p, q = (int(xs[i] - d[0]), int(ys[i] - d[1])), (int(xs[i] + d[0]), int(ys[i] + d[1]))
        cv2.line(labels, p, q, 0, int(rng.integers(2, 6)))
    for _ in range(int(rng.integers(0, 4))):  # holes, specks
        i = int(rng.integers(len(xs)))
        value = 0 if rng.random() < 0.7 else 160
        cv2.circle(labels, (int(xs[i]), int(ys[i])), int(rng.integers(1, 4)), value, -1)
    clasper = (labels == 70).view(np.uint8)
    if clasper.any() and rng.random() < 0.3:  # a gap between the shaft and its clasper
        near = cv2.dilate(clasper, np.ones((5, 5), np.uint8)) > 0
        labels[near & (labels == 160)] = 0
    parts = {}
    for name, value in (("shaft", 160), ("clasper", 70)):
        obs = part_obs(labels == value)
        if obs is not None:
            parts[name] = obs
    if "shaft" in parts:
        _one_call_equals_steps(parts, PINHOLE)


def test_the_one_call_answers_for_pieces_and_gaps() -> None:
    """The one call answers for a shaft in pieces (two tools: merged; one shaft cut
    across, a hole in a piece) and across a gap at the junction (else the tests above
    would prove little)."""
    canvas = np.zeros(SHAPE, np.uint8)
    cv2.line(canvas, (100, 500), (300, 300), 160, 24)  # one shaft, cut across, a hole
    cv2.line(canvas, (190, 430), (230, 370), 0, 4)
    cv2.circle(canvas, (150, 450), 3, 0, -1)
    cv2.circle(canvas, (310, 290), 8, 70, -1)
    one = {"shaft": part_obs(canvas == 160), "clasper": part_obs(canvas == 70)}
    got = _one_call_equals_steps(one, PINHOLE)
    assert not isinstance(got, str | None) and not got.merged
    two = canvas.copy()
    cv2.line(two, (160, 520), (360, 320), 160, 24)  # a second tool beside it: merged
    both = {"shaft": part_obs(two == 160), "clasper": part_obs(two == 70)}
    got = _one_call_equals_steps(both, PINHOLE)
    assert not isinstance(got, str | None) and got.merged
    gap = canvas.copy()
    gap[
        (cv2.dilate((canvas == 70).view(np.uint8), np.ones((5, 5), np.uint8)) > 0) & (canvas == 160)
    ] = 0
    apart = {"shaft": part_obs(gap == 160), "clasper": part_obs(gap == 70)}
    got = _one_call_equals_steps(apart, PINHOLE)
    assert not isinstance(got, str | None)


def test_the_one_call_path_is_the_common_one() -> None:
    """Most undistorted scenes' shafts are measured in the one call (else the test above
    would prove little)."""
    answered = tried = 0
    for seed in range(30):
        obs, camera, _ = _fixed_scene(seed)
        shaft = obs.parts.get("shaft")
        if shaft is None or camera.distorted:
            continue
        tried += 1
        res, rims = np.empty(kp.OUT["size"]), Rims()
        K = np.ascontiguousarray(camera.K, dtype=np.float64)
        got = measure_mod._shaft_in_one_call(obs.parts, shaft, SHAPE, K, 4.0, res, rims)
        answered += got is not None
    assert tried >= 6 and answered >= 0.6 * tried, (answered, tried)


@st.composite
def point_sets(draw: st.DrawFn) -> np.ndarray:
    """float32 points: a cloud, two rims (a cylinder's image: two ellipses, some nearly
    flat), integer points with repeats, or points on a line (float rounding decides)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    kind = draw(st.sampled_from(["cloud", "rims", "grid", "line"]))
    n = int(rng.integers(1, 49))
    if kind == "cloud":
        pts = rng.normal(0, 1, (n, 2)) * rng.uniform(0.5, 80) + rng.uniform(-20, 220, 2)
    elif kind == "rims":
        t = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
        c, r = rng.uniform(0, 200, (2, 2)), rng.uniform(0.0, 30.0, (2, 2))
        r[:, 1] *= rng.choice([1.0, 1e-3, 1e-6])  # a rim seen almost edge-on
        rot = rng.uniform(0, np.pi)
        rims = []
        for k in range(2):
            x, y = r[k, 0] * np.cos(t), r[k, 1] * np.sin(t)
            rims.append(
                c[k]
                + np.stack(
                    [x * np.cos(rot) - y * np.sin(rot), x * np.sin(rot) + y * np.cos(rot)], 1
                )
            )
        pts = np.concatenate(rims)
    elif kind == "grid":
        pts = rng.integers(0, 6, (n, 2)).astype(float)
    else:
        pts = rng.uniform(0, 1, (n, 1)) * rng.normal(size=2) * 50 + 100
    return np.ascontiguousarray(pts, dtype=np.float32)


@settings(max_examples=800, deadline=None)
@given(point_sets())
def test_convex_hull_equals_opencv_where_it_answers(pts: np.ndarray) -> None:
    """OpenCV's indices in its order, or -1 (ask OpenCV) only where float rounding could
    decide: equal points or a turn within 1e-6 of straight."""
    ref = cv2.convexHull(pts, returnPoints=False).reshape(-1)
    hull = np.empty(len(pts), np.int32)
    k = convex_hull(pts, hull)
    if k < 0:  # OpenCV answers (quality.rims_iou calls it then)
        return
    assert np.array_equal(hull[:k], ref)


def test_convex_hull_answers_for_points_in_general_position() -> None:
    rng = np.random.default_rng(7)
    for _ in range(300):
        pts = (rng.normal(0, 30, (48, 2)) + 100).astype(np.float32)
        hull = np.empty(48, np.int32)
        k = convex_hull(pts, hull)
        assert k > 0 and np.array_equal(hull[:k], cv2.convexHull(pts, returnPoints=False).ravel())


@settings(max_examples=800, deadline=None)
@given(point_sets(), st.integers(1, 90), st.integers(1, 90), st.integers(0, 2**32 - 1))
def test_fill_convex_equals_opencv(pts: np.ndarray, h: int, w: int, seed: int) -> None:
    """``cv2.fillConvexPoly(..., 1, LINE_8, shift=4)`` of a hull's points x16, also where
    the polygon leaves the image on any side."""
    off = np.random.default_rng(seed).uniform(-40, 40, 2)
    shifted = np.rint((pts - off) * 16.0).astype(np.int32)
    order = cv2.convexHull(pts, returnPoints=False).reshape(-1).astype(np.int32)
    ref = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(ref, shifted[order], 1, lineType=cv2.LINE_8, shift=4)
    got = np.zeros((h, w), np.uint8)
    fill_convex(got, shifted, order, len(order), 4)
    assert np.array_equal(got, ref)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_the_quality_iou_equals_opencvs(seed: int, edge_on: bool) -> None:
    """``quality.rims_iou`` (one kernel call, or OpenCV where the hull is unsure) gives the
    IoU of OpenCV's hull and fill: cylinders at random poses, some seen edge-on."""
    rng = np.random.default_rng(seed)
    K = np.array([[600.0, 0, 359.5], [0, 600.0, 287.5], [0, 0, 1]])
    p_a = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(40, 150)])
    d = unit(rng.normal(size=3))
    if edge_on:  # the axis across the viewing ray: the rims project to near segments
        d = unit(np.cross(p_a, rng.normal(size=3)))
    p_b = p_a + rng.uniform(2, 60) * d
    mask = rng.random((int(rng.integers(1, 80)), int(rng.integers(1, 80)))) < 0.6
    offset = (int(rng.integers(250, 450)), int(rng.integers(200, 350)))
    rims = Rims()
    rims.canvas[5] = kp.cylinder_outline(
        p_a,
        p_b,
        4.0,
        2.0,
        K,
        1.0,
        offset[0],
        offset[1],
        *mask.shape,
        *SHAPE,
        40000,
        rims.pts,
        rims.shifted,
        rims.canvas,
    )
    got = rims_iou(rims, mask, offset)
    x0, y0, step, rows, cols, found = rims.canvas.tolist()
    if found < 2:
        assert np.isnan(got)
        return
    rend = np.zeros((rows, cols), np.uint8)
    hull = cv2.convexHull(rims.pts, returnPoints=False).reshape(-1)
    cv2.fillConvexPoly(rend, rims.shifted[hull], 1, lineType=cv2.LINE_8, shift=4)
    ref = kp.iou_count(rend, mask, offset[0], offset[1], x0, y0, step)
    assert got == ref or (np.isnan(got) and np.isnan(ref))


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_clasper_in_one_call_equals_its_steps(seed: int) -> None:
    """``_tip_in_one_call`` (outline, jaw width, border flag, ``tip_pose`` and the
    quality in one kernel call) gives what ``_tip_in_steps`` gives, cell for cell; a
    clasper whose pieces' boxes nest is left to the steps."""
    obs, camera, length = scene(seed)
    parts = obs.parts
    clasper = parts.get("clasper")
    if clasper is None or camera.distorted:
        return
    K = np.ascontiguousarray(camera.K, dtype=np.float64)
    rng = np.random.default_rng(seed)
    joint = np.array([rng.uniform(-30, 30), rng.uniform(-20, 20), rng.uniform(40, 150)])
    a = unit(rng.normal(size=3))
    mask = as_mask(clasper.mask)
    length_mm = np.nan if length is None else float(length)
    tip1, tip2 = np.full(kp.TIP["size"], np.nan), np.full(kp.TIP["size"], np.nan)
    got1, q1 = measure_mod._tip_in_one_call(clasper, mask, joint, a, K, SHAPE, length_mm, 4.0, tip1)
    if got1 == kp.CLASPER_ASK_PYTHON:
        assert _nested_boxes(mask) and np.isnan(tip1).all()
        return
    got2, q2 = measure_mod._tip_in_steps(
        clasper, mask, joint, a, K, SHAPE, length_mm, 4.0, camera, False, tip2
    )
    assert got1 == got2
    assert np.array_equal(tip1, tip2, equal_nan=True)
    assert q1 == q2 or (np.isnan(q1) and np.isnan(q2))


@pytest.mark.parametrize("seed", range(12))
def test_a_clasper_in_pieces_in_one_call_equals_its_steps(seed: int) -> None:
    """A clasper cut across (two pieces or more, specks): the one call answers, on
    OpenCV's first longest outline, and gives what the steps give."""
    rng = np.random.default_rng(seed)
    K = np.asarray(PINHOLE.K)
    J = np.array([rng.uniform(-20, 20), rng.uniform(-15, 15), rng.uniform(40, 70)])
    a = unit([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.0, 0.6)])
    tip = J + 10.0 * unit(a + 0.4 * rng.normal(size=3))
    labels = render_instrument(SHAPE, K, J - 300.0 * a, J, tip, 4.0, 0.6)
    clasper = (labels == 70).astype(np.uint8)
    ys, xs = np.nonzero(clasper)
    i = int(rng.integers(len(xs)))
    d = rng.normal(size=2) * 30
    p, q = (int(xs[i] - d[0]), int(ys[i] - d[1])), (int(xs[i] + d[0]), int(ys[i] + d[1]))
    cv2.line(clasper, p, q, 0, int(rng.integers(1, 4)))
    obs = part_obs(clasper > 0)
    assert obs is not None
    mask = as_mask(obs.mask)
    tip1, tip2 = np.full(kp.TIP["size"], np.nan), np.full(kp.TIP["size"], np.nan)
    length = 10.0 if seed % 2 else np.nan
    got1, q1 = measure_mod._tip_in_one_call(obs, mask, J, a, K, SHAPE, length, 4.0, tip1)
    got2, q2 = measure_mod._tip_in_steps(
        obs, mask, J, a, K, SHAPE, length, 4.0, PINHOLE, False, tip2
    )
    if len(_opencv(mask)) > 1 and not _nested_boxes(mask):
        assert got1 != kp.CLASPER_ASK_PYTHON
    if got1 != kp.CLASPER_ASK_PYTHON:
        assert got1 == got2
        assert np.array_equal(tip1, tip2, equal_nan=True)
        assert q1 == q2 or (np.isnan(q1) and np.isnan(q2))


def test_the_shafts_quality_in_one_call_is_rims_iou() -> None:
    """The shaft's quality written by the one call is ``quality.rims_iou`` of its
    cylinder's image (a few undistorted scenes with a measured shaft)."""
    checked = 0
    for seed in range(30):
        obs, camera, _ = _fixed_scene(seed)
        shaft = obs.parts.get("shaft")
        if shaft is None or camera.distorted:
            continue
        K = np.ascontiguousarray(camera.K, dtype=np.float64)
        res, rims = np.empty(kp.OUT["size"]), Rims()
        got = measure_mod._shaft_in_one_call(obs.parts, shaft, SHAPE, K, 4.0, res, rims)
        if got is None or isinstance(got, str) or np.isnan(res[kp.OUT["quality_a"]]):
            continue
        assert not res[kp.OUT["quality_opencv"]]
        want = rims_iou(rims, got.mask, got.offset)
        q = res[kp.OUT["quality"]]
        assert q == want or (np.isnan(q) and np.isnan(want))
        checked += 1
    assert checked >= 4, checked


def _rows_equal(a: dict, b: dict) -> None:
    """Two instances' rows: the same parts and cells, in the same order, bit for bit
    (NaN equal to NaN)."""
    assert list(a) == list(b)
    for name in a:
        assert list(a[name]) == list(b[name])
        x, y = np.array(list(a[name].values())), np.array(list(b[name].values()))
        assert np.array_equal(x, y, equal_nan=True), (name, x, y)


def _one_call(
    parts: dict, shaft: object, K: np.ndarray, radius: float, length: float | None
) -> dict | None:
    """``measure._instance_in_one_call``'s rows (the kernel's array) by part, as
    ``measure_instance`` gives them; None where it leaves the instance to the steps."""
    rows = np.full((3, measure_mod.ROW_LEN), -7.0)
    if not measure_mod._instance_in_one_call(parts, shaft, SHAPE, K, radius, length, rows):
        return None
    return {
        name: dict(zip(measure_mod.ROW_KEYS, rows[measure_mod.SLOT_OF[name]].tolist(), strict=True))
        for name in parts
    }


def _instance_one_call_equals_steps(parts: dict, camera: object, length: float | None) -> bool:
    """``measure._instance_in_one_call`` against ``_instance_in_steps`` (the former
    ``measure_instance``): the same rows where the one call answers; whether it did."""
    K = np.ascontiguousarray(camera.K, dtype=np.float64)  # type: ignore[attr-defined]
    got = _one_call(parts, parts["shaft"], K, 4.0, length)
    want = measure_mod._instance_in_steps(
        parts,
        parts["shaft"],
        SHAPE,
        camera,  # type: ignore[arg-type]
        K,
        False,
        4.0,
        length,
    )
    if got is None:
        return False
    _rows_equal(got, want)
    return True


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from(["all", "no clasper", "shaft first"]))
def test_the_instance_in_one_call_equals_its_steps(seed: int, variant: str) -> None:
    """Rendered scenes (one tool or two merged, holes, cuts, gaps at the junction, a
    wrist; without the clasper; parts in another order): ``instance_from_masks`` gives
    every row the steps give, cell for cell, reasons included."""
    obs, camera, length = scene(seed)
    parts = dict(obs.parts)
    if parts.get("shaft") is None or camera.distorted:
        return
    if variant == "no clasper":
        parts.pop("clasper", None)
    elif variant == "shaft first":
        parts = {"shaft": parts.pop("shaft"), **dict(reversed(list(parts.items())))}
    _instance_one_call_equals_steps(parts, camera, length)


def test_the_instance_in_one_call_is_the_common_path() -> None:
    """The one call answers for most undistorted scenes and for each way a row ends
    (measured, the tip not found, no clasper, merged, a shaft reason), so that the test
    above proves something; and ``measure_instance`` takes it."""
    answered = tried = 0
    statuses: set[float] = set()
    for seed in (*range(40), 56, 113, 190):  # (56: rejected, 113: merged, 190: occluded)
        obs, camera, length = _fixed_scene(seed)
        if obs.parts.get("shaft") is None or camera.distorted:
            continue
        for parts in (obs.parts, {k: v for k, v in obs.parts.items() if k != "clasper"}):
            tried += 1
            if _instance_one_call_equals_steps(parts, camera, length):
                answered += 1
                rows = measure_mod.measure_instance(
                    SimpleNamespace(parts=parts),  # type: ignore[arg-type]
                    SHAPE,
                    camera,
                    8.0,
                    length,
                )
                statuses |= {row["aux_status"] for row in rows.values()}
    assert tried >= 12 and answered >= 0.8 * tried, (answered, tried)
    reasons = ("no clasper", "merged", "one silhouette line", "rejected", "occluded")
    assert {reason_code(r) for r in reasons} <= statuses, statuses


def test_the_instance_in_one_call_when_the_tip_or_the_shaft_is_not_found() -> None:
    """Drawn: a clasper of two pixels (the tip not found), a shaft crop without pixels
    (not visible), and a clean tool (every row measured): the rows the steps give."""
    canvas = np.zeros(SHAPE, np.uint8)
    cv2.line(canvas, (100, 500), (300, 300), 160, 24)
    cv2.circle(canvas, (310, 290), 8, 70, -1)
    tool = {"shaft": part_obs(canvas == 160), "clasper": part_obs(canvas == 70)}
    assert _instance_one_call_equals_steps(tool, PINHOLE, 10.0)
    K = np.ascontiguousarray(PINHOLE.K, dtype=np.float64)
    rows = _one_call(tool, tool["shaft"], K, 4.0, 10.0)
    assert rows is not None and all(np.isnan(row["aux_status"]) for row in rows.values())
    assert np.isfinite(rows["clasper"]["end_z_mm"]) and np.isfinite(rows["shaft"]["quality"])
    ys, xs = np.nonzero(canvas == 160)
    end = np.argsort(xs - ys)[-4::3]  # two pixels of the shaft's distal end, 3 apart
    speck = np.zeros(SHAPE, bool)
    speck[ys[end] - 1, xs[end] + 1] = True  # a clasper of a pixel beyond each
    assert speck.sum() == 2 and not (speck & (canvas == 160)).any()
    tool["clasper"] = part_obs(speck)
    assert _instance_one_call_equals_steps(tool, PINHOLE, None)
    rows = _one_call(tool, tool["shaft"], K, 4.0, None)
    assert rows is not None and rows["clasper"]["aux_status"] == reason_code("tip not found")
    empty = SimpleNamespace(mask=np.zeros((3, 4), bool), offset=(5, 6), box=None)
    none = {"shaft": empty, "clasper": tool["clasper"]}
    assert _instance_one_call_equals_steps(none, PINHOLE, 10.0)
    rows = _one_call(none, empty, K, 4.0, 10.0)
    assert rows is not None and rows["clasper"]["aux_status"] == reason_code("not visible")


def test_the_instance_in_one_call_leaves_other_parts_to_the_steps() -> None:
    """A part other than the shaft, the clasper and the wrist, or more than three parts:
    the steps answer (the one call writes three rows)."""
    obs, camera, length = next(
        s
        for s in map(_fixed_scene, range(40))
        if "clasper" in s[0].parts and "shaft" in s[0].parts and not s[1].distorted
    )
    K = np.ascontiguousarray(camera.K, dtype=np.float64)
    parts = {"shaft": obs.parts["shaft"], "jaw": obs.parts["clasper"]}
    assert _one_call(parts, parts["shaft"], K, 4.0, length) is None


def _former_measure_instance(
    parts: dict, camera: object, diameter: float | None, length: float | None
) -> dict:
    """``measure.measure_instance`` as it was before the rows became one array (its
    dicts built part by part; the one call's rows are the steps', tested above)."""
    shaft = parts.get("shaft")
    if camera is None or shaft is None or diameter is None or not diameter > 0:
        out = {name: measure_mod._nan_row() for name in parts}
        if camera is None:
            measure_mod._why(out, "no camera")
        elif shaft is None or not shaft.mask.any():
            measure_mod._why(out, "not visible")
        else:
            measure_mod._why(out, "no shaft diameter")
        return out
    K, distorted = measure_mod._camera(camera)  # type: ignore[arg-type]
    return measure_mod._instance_in_steps(
        parts,
        shaft,
        SHAPE,
        camera,  # type: ignore[arg-type]
        K,
        distorted,
        0.5 * diameter,
        length,
    )


@settings(max_examples=40, deadline=None)
@given(
    st.integers(0, 2**32 - 1),
    st.sampled_from(["all", "no clasper", "shaft first", "no camera", "no diameter", "empty"]),
)
def test_the_rows_array_holds_the_former_dicts_on_every_path(seed: int, variant: str) -> None:
    """``measure_rows`` (one array, what the workers send) on rendered scenes, lenses with
    and without distortion (the one call, and the steps copied in), without camera,
    diameter or shaft pixels: each part's row is the former ``measure_instance``'s
    dict, cell for cell and in order; ``measure_instance`` is that array by part."""
    obs, camera, length = scene(seed)
    parts = dict(obs.parts)
    diameter: float | None = 8.0
    if parts.get("shaft") is None:
        return
    if variant == "no clasper":
        parts.pop("clasper", None)
    elif variant == "shaft first":
        parts = {"shaft": parts.pop("shaft"), **dict(reversed(list(parts.items())))}
    elif variant == "no camera":
        camera = None
    elif variant == "no diameter":
        diameter = None if seed % 2 else 0.0
    elif variant == "empty":
        shaft = parts["shaft"]
        parts["shaft"] = SimpleNamespace(mask=np.zeros_like(shaft.mask), offset=shaft.offset)
    inst = SimpleNamespace(parts=parts)
    want = _former_measure_instance(parts, camera, diameter, length)
    out = np.full((3, measure_mod.ROW_LEN), -7.0)
    got = measure_mod.measure_rows(inst, SHAPE, camera, diameter, length, out)  # type: ignore[arg-type]
    assert got is out
    by_part = {
        name: dict(zip(measure_mod.ROW_KEYS, out[measure_mod.SLOT_OF[name]].tolist(), strict=True))
        for name in parts
    }
    _rows_equal(by_part, want)
    _rows_equal(measure_mod.measure_instance(inst, SHAPE, camera, diameter, length), want)  # type: ignore[arg-type]
