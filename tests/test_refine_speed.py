"""The refinement's faster pieces against the code they replace (``tests/refine_before.py``,
commit b752e53), bit for bit: the median, the noise scale, the trocar's line distances
and intersection, and the head swaps found as column arithmetic over the frames where
two tools show a head part (frame by frame in the others)."""

from __future__ import annotations

import math

import numpy as np
import refine_before as before
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.model import TrackTable
from mistool.pose import filtering, trocar
from mistool.tracking import relink

_SPECIAL = [0.0, -0.0, 1.0, -1.0, 0.5, math.nan, math.inf, -math.inf, 1e-300, 1e300]


@settings(max_examples=400, deadline=None)
@given(
    st.lists(
        st.one_of(st.sampled_from(_SPECIAL), st.floats(allow_nan=True, allow_infinity=True)),
        min_size=1,
        max_size=40,
    )
)
def test_median_is_numpys_to_the_sign_of_zero(values):
    x = np.array(values, dtype=np.float64)
    want = float(np.median(x))
    got = filtering.median(x.copy())
    if math.isnan(want):
        assert math.isnan(got)
    else:
        assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want)


def test_median_of_zeros_and_series_is_numpys():
    rng = np.random.default_rng(0)
    for n in range(1, 60):
        for x in (np.zeros(n), -np.zeros(n), rng.normal(size=n), np.round(rng.normal(size=n))):
            want, got = float(np.median(x)), filtering.median(x)
            assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 300), st.sampled_from([1e-4, 0.05, 3.0]))
def test_noise_scale_is_the_former(seed, n, floor):
    rng = np.random.default_rng(seed)
    y = np.cumsum(rng.normal(size=n)) * rng.uniform(0, 5)
    if seed % 3 == 0:
        y = np.round(y)  # ties and zero second differences
    if seed % 5 == 0 and n:
        y[rng.integers(0, n, 3)] = np.nan
    assert filtering.noise_scale(y, floor) == before.noise_scale(y, floor)


def test_norms_are_numpys():
    rng = np.random.default_rng(1)
    v = rng.normal(size=(20000, 3)) * 10.0 ** rng.integers(-150, 150, size=(20000, 1))
    assert np.array_equal(trocar._norms(v), np.linalg.norm(v, axis=1))


def _bundle(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Lines through a trocar with noise and outliers, or random ones; NaN rows."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    point = rng.normal(size=3) * 60.0
    p = point + rng.normal(size=(n, 3)) * rng.uniform(5.0, 150.0)
    a = rng.normal(size=(n, 3))
    if seed % 4:
        a = p - point + rng.normal(size=(n, 3)) * rng.uniform(0.0, 20.0)
    if seed % 9 == 0:
        a = np.repeat(a[:1], n, axis=0)  # parallel: no trocar
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    if seed % 7 == 0:
        p[rng.integers(0, n, 3)] = np.nan
    return p, a


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_trocar_is_the_former(seed):
    p, a = _bundle(seed)
    ok = np.isfinite(p).all(axis=1)
    r = trocar.distances_to_lines(p[0] * 0.5 + 1.0, p, a)
    assert np.array_equal(r, before.distances_to_lines(p[0] * 0.5 + 1.0, p, a), equal_nan=True)
    if ok.sum() >= 2:
        s0, s1 = trocar._lmeds_start(p[ok], a[ok]), before.lmeds_start(p[ok], a[ok])
        assert (s0 is None) == (s1 is None)
        assert s0 is None or np.array_equal(s0, s1)
    got, want = trocar.intersect_lines(p, a), before.intersect_lines(p, a)
    assert (got is None) == (want is None)
    if got is not None and want is not None:
        assert np.array_equal(got.point, want.point)
        assert np.array_equal(got.inliers, want.inliers)
        assert np.array_equal(got.cov, want.cov)
        assert (got.rms_mm, got.spread_deg) == (want.rms_mm, want.spread_deg)


def _tools_table(seed: int) -> TrackTable:
    """Two to five tools from the borders, their heads near their shafts' inner ends,
    parts missing at random; runs of frames where head parts carry another tool's name
    (swaps to undo, some short, some ambiguous), names that are not numbers, NaN boxes,
    a repeated row, rows in any order."""
    rng = np.random.default_rng(seed)
    tools = int(rng.integers(2, 6))
    frames = int(rng.integers(1, 40))
    names = [str(k + 1) for k in range(tools)]
    if seed % 5 == 0:
        names[-1] = "tool-b"
    angle = rng.uniform(0.0, 180.0, tools)
    centre = rng.uniform([100.0, 100.0], [620.0, 476.0], size=(tools, 2))
    swap_at = {int(f): rng.permutation(tools) for f in rng.integers(0, frames, frames // 2)}
    cols: dict[str, list[object]] = {c: [] for c in ("frame", "instrument", "part")}
    num: dict[str, list[float]] = {c: [] for c in relink_columns()}
    for f in range(frames):
        perm = swap_at.get(f - f % 4, np.arange(tools))  # runs of four frames
        for k in range(tools):
            a = math.radians(angle[k] + rng.normal() * 3.0)
            u = np.array([math.cos(a), math.sin(a)])
            c = centre[k] + rng.normal(size=2) * 4.0 + f * rng.normal(size=2)
            inner = c + 150.0 * u
            for part, at, size in (
                ("shaft", c, (300.0, 60.0)),
                ("wrist", inner + 20.0 * u, (40.0, 40.0)),
                ("clasper", inner + 50.0 * u, (40.0, 16.0)),
            ):
                if part != "shaft" and rng.random() < 0.15:
                    continue
                owner = names[perm[k]] if part != "shaft" and seed % 3 else names[k]
                if part == "clasper" and seed % 2:
                    owner = names[k]
                xy = at + rng.normal(size=2) * rng.uniform(0.0, 40.0)
                cols["frame"].append(f)
                cols["instrument"].append(owner)
                cols["part"].append(part)
                _box(num, xy, size, math.degrees(a) % 180.0)
    table = TrackTable({**cols, **num})
    if seed % 7 == 0 and table.num_rows:
        ang = np.array(table["angle_deg"], copy=True)
        ang[rng.integers(0, table.num_rows, 2)] = np.nan
        table = table.with_columns(angle_deg=ang)
    if seed % 4 == 0 and table.num_rows:
        order = rng.permutation(table.num_rows)
        table = table[np.concatenate([order, order[:1]])]
    return table


def relink_columns() -> tuple[str, ...]:
    corners = tuple(f"{c}{k}_px" for k in (1, 2, 3, 4) for c in ("x", "y"))
    return ("cx_px", "cy_px", "length_px", "width_px", "angle_deg", "area_px", *corners)


def _box(num: dict[str, list[float]], xy: np.ndarray, size: tuple[float, float], ang: float):
    u = np.array([math.cos(math.radians(ang)), math.sin(math.radians(ang))])
    v = np.array([-u[1], u[0]])
    num["cx_px"].append(float(xy[0]))
    num["cy_px"].append(float(xy[1]))
    num["length_px"].append(size[0])
    num["width_px"].append(size[1])
    num["angle_deg"].append(ang)
    num["area_px"].append(size[0] * size[1])
    for k, (sa, sb) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1)), 1):
        x, y = xy + sa * 0.5 * size[0] * u + sb * 0.5 * size[1] * v
        num[f"x{k}_px"].append(float(x))
        num[f"y{k}_px"].append(float(y))


def _same(a: TrackTable, b: TrackTable) -> bool:
    return a.columns == b.columns and all(
        np.array_equal(a[c], b[c], equal_nan=a[c].dtype != object) for c in a.columns
    )


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_head_swaps_are_the_formers(seed):
    table = _tools_table(seed)
    got, want = relink.swap_heads(table), before.swap_heads(table)
    assert (got is table) == (want is table)
    assert _same(got, want)


def test_head_swaps_found_both_ways_are_the_formers():
    """Over many tables, swaps made in frames of two tools (column arithmetic) and of
    more (frame by frame), with NaN boxes among them: the same as before."""
    kinds = {"pair": 0, "frame": 0}
    pair, frame = relink._pair_candidates, relink._frame_candidates

    def count_pair(*args):  # type: ignore[no-untyped-def]
        out = pair(*args)
        kinds["pair"] += len(out[0])
        return out

    def count_frame(*args):  # type: ignore[no-untyped-def]
        out = frame(*args)
        kinds["frame"] += len(out)
        return out

    swapped = 0
    try:
        relink._pair_candidates, relink._frame_candidates = count_pair, count_frame
        for seed in range(300):
            table = _tools_table(seed)
            got, want = relink.swap_heads(table), before.swap_heads(table)
            assert _same(got, want)
            swapped += want is not table
    finally:
        relink._pair_candidates, relink._frame_candidates = pair, frame
    assert swapped > 30 and kinds["pair"] > 100 and kinds["frame"] > 100


def test_the_lmeds_start_passes_over_a_candidate_that_cannot_win(monkeypatch) -> None:
    """A candidate point with fewer than half its distances below the best median so far
    is passed over without its median (the same start: test_trocar_is_the_former):
    lines through a trocar with a third of outliers take fewer medians than candidates."""
    calls = []
    monkeypatch.setattr(trocar, "median", lambda r: calls.append(1) or filtering.median(r))
    rng = np.random.default_rng(3)
    n = 300
    p = rng.normal(size=(n, 3)) * 80.0
    a = p - np.array([10.0, -20.0, 40.0]) + rng.normal(size=(n, 3))
    a[: n // 3] = rng.normal(size=(n // 3, 3))  # outliers
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    got = trocar._lmeds_start(p, a)
    assert got is not None and np.array_equal(got, before.lmeds_start(p, a))
    assert 0 < len(calls) < 40  # of 60 candidates
