"""mistool.tracking as a pipeline: the shared solver, track states, the pure cost, the
reach rules table, the package's import direction and complexity limit."""

from __future__ import annotations

import ast
import itertools
import math
import subprocess
import sys
from dataclasses import FrozenInstanceError
from pathlib import Path

import numpy as np
import pytest
from test_tracking import MERGED, crossing, frame

from mistool.assignment import gated_assignment, linear_assignment
from mistool.model import InstanceObservation as ModelInstance
from mistool.tracking import (
    REACH_RULES,
    CostWeights,
    IdentityTracker,
    InstanceObservation,
    TrackState,
    observe_frame,
    track_cost,
)

PACKAGE = Path(__file__).resolve().parents[1] / "mistool" / "tracking"


def _brute_gated(cost: np.ndarray, gate: float) -> float:
    """Least total over every partial matching (unmatched rows/columns cost the gate)."""
    n, m = cost.shape
    best = math.inf
    for k in range(min(n, m) + 1):
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                c = [cost[r, j] for r, j in zip(rows, cols, strict=True)]
                if all(x <= gate for x in c):
                    best = min(best, sum(c) + gate * (n + m - 2 * k))
    return best


@pytest.mark.parametrize("shape", [(1, 1), (2, 3), (3, 2), (4, 4), (5, 3)])
def test_gated_assignment_is_optimal_and_respects_the_gate(shape):
    rng = np.random.default_rng(sum(shape))
    gate = 3.0
    for _ in range(15):
        cost = rng.uniform(0, 5, shape)
        cost[rng.uniform(size=shape) < 0.2] = np.inf
        pairs = gated_assignment(cost, gate)
        assert len({r for r, _ in pairs}) == len(pairs) == len({c for _, c in pairs})
        assert all(cost[r, c] <= gate for r, c in pairs)
        total = sum(cost[r, c] for r, c in pairs) + gate * (sum(shape) - 2 * len(pairs))
        assert total == pytest.approx(_brute_gated(cost, gate))


def test_one_solver_for_evaluation_and_tracking():
    from mistool import evaluation

    assert evaluation.linear_assignment is linear_assignment
    assert linear_assignment(np.zeros((0, 3))) == []
    assert gated_assignment(np.zeros((2, 0)), 1.0) == []


def test_observation_types_live_in_the_model():
    assert InstanceObservation is ModelInstance
    insts = observe_frame(frame(((300.0, 300.0), 30.0)), MERGED)
    with pytest.raises(FrozenInstanceError):
        insts[0].area_px = 3  # type: ignore[misc]


def test_track_states_through_a_crossing_and_an_exit():
    """Tracked apart, one coasting and one hidden while merged, tracked again after;
    lost when unseen for more than LOST_AFTER_FRAMES frames."""
    tracker = IdentityTracker(MERGED)
    seen: list[set[TrackState]] = []
    frames = crossing()
    for k, tools in enumerate(frames):
        img = frame(*[(tip, ang) for _, tip, ang in tools])
        tracker.assign(k, observe_frame(img, MERGED))
        seen.append({t.state for t in tracker.tracks})
    assert seen[0] == {TrackState.TRACKED}
    assert {TrackState.COASTING, TrackState.HIDDEN} in seen  # while they overlap
    assert seen[-1] == {TrackState.TRACKED}
    n = len(frames)
    only_a = frame(*[(tip, ang) for name, tip, ang in frames[-1] if name == "A"])
    for k in range(n, n + 7):  # B leaves the view
        tracker.assign(k, observe_frame(only_a, MERGED))
    states = sorted(t.state.value for t in tracker.tracks)
    assert states == ["lost", "tracked"]


def test_cost_is_pure_and_weighted():
    tracker = IdentityTracker(MERGED)
    img = frame(((300.0, 300.0), 30.0))
    inst = observe_frame(img, MERGED)
    tracker.assign(0, inst)
    t = tracker.tracks[0]
    moved = observe_frame(frame(((330.0, 300.0), 30.0)), MERGED)[0]
    w = CostWeights()
    a = track_cost(t, moved, 1, w, 25.0)
    assert a == track_cost(t, moved, 1, w, 25.0) and a > 0
    assert track_cost(t, inst[0], 1, w, 25.0) < a  # nearer the prediction: cheaper
    assert track_cost(t, moved, 1, CostWeights(gap=1.0), 25.0) == pytest.approx(a)  # gap 1
    assert track_cost(t, moved, 3, CostWeights(gap=1.0), 25.0) > track_cost(t, moved, 3, w, 25.0)
    with pytest.raises(FrozenInstanceError):
        w.max_cost = 1.0  # type: ignore[misc]


def test_reach_rules_table():
    names = [r.name for r in REACH_RULES]
    assert len(names) == len(set(names)) >= 4
    head = next(r for r in REACH_RULES if r.name == "head of a shaft")
    assert head.reach(100.0, 40000.0) == pytest.approx(max(head.base_px, head.frac * 200.0))
    inner = next(r for r in REACH_RULES if r.name == "head cut off")
    assert inner.reach(1e8, 1.0) == inner.cap_px  # scaled by the piece, capped
    border = next(r for r in REACH_RULES if r.name == "head at the border")
    assert border.piece == "border head" and border.reach(1.0, 1e8) == border.base_px


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_package_imports_flow_one_way():
    order = ["instances", "motion", "split", "identity"]
    for k, mod in enumerate(order):
        later = {f"mistool.tracking.{m}" for m in order[k + 1 :]} | {"mistool.tracking"}
        assert not _imports(PACKAGE / f"{mod}.py") & later, mod


def test_tracking_meets_the_complexity_limit():
    proc = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--select", "C901", str(PACKAGE)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.parametrize("k, back", [(2, [math.inf, math.inf]), (2, [math.inf, 80.0]), (3, None)])
def test_nearest_axis_matches_the_segment_distances(k, back):
    from mistool.tracking.split import _segment_distance, nearest_axis

    rng = np.random.default_rng(k)
    p = rng.uniform(0, 400, (3000, 2))
    ends = rng.uniform(100, 300, (k, 2))
    dirs = rng.normal(size=(k, 2))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    b = np.array(back if back is not None else rng.uniform(20, 200, k))
    r = rng.uniform(5, 15, k)
    want = _segment_distance(p, ends, dirs, b, r).argmin(1)
    assert np.array_equal(nearest_axis(p, ends, dirs, b, r), want)


def test_principal_direction_closed_form():
    from mistool.tracking.split import _principal_direction

    rng = np.random.default_rng(3)
    t = 0.7
    q = (
        rng.normal(size=(500, 2))
        * [9.0, 1.0]
        @ np.array([[math.cos(t), math.sin(t)], [-math.sin(t), math.cos(t)]])
    )
    c, d = _principal_direction(q + [5.0, -2.0])
    _, v = np.linalg.eigh(np.cov(q.T))
    assert np.allclose(c, q.mean(0) + [5.0, -2.0])
    assert abs(abs(float(d @ v[:, 1])) - 1.0) < 1e-12


def test_rasterised_owner_image_matches_per_pixel_nearest_axis():
    """The crossing split's shaft owner image equals the per-pixel nearest axis."""
    from mistool.model import PartObservation, RotatedBox
    from mistool.tracking.split import _Axes, _owner_image, nearest_axis

    img = frame(((420.0, 300.0), 20.0), ((330.0, 260.0), 160.0), shaft_len=500.0)
    mask = img == 10  # both shafts, crossing
    ys, xs = np.nonzero(mask)
    y0, x0 = int(ys.min()), int(xs.min())
    crop = mask[y0 : ys.max() + 1, x0 : xs.max() + 1]
    part = PartObservation("shaft", RotatedBox(0, 0, 1, 1, 0), np.zeros((4, 2)), 1, crop, (x0, y0))
    t = np.radians([20.0, 160.0])
    dirs = np.stack([np.cos(t), np.sin(t)], 1)
    ax = _Axes(
        ends=np.array([[380.0, 285.0], [370.0, 245.0]]),
        dirs=dirs,
        back=np.array([math.inf, 300.0]),
        radius=np.array([11.0, 11.0]),
        limit_end=np.zeros((2, 2)),
        margin=np.zeros(2),
    )
    got = _owner_image(part, ax)
    cy, cx = np.nonzero(crop)
    p = np.stack([cx + x0, cy + y0], 1).astype(np.float64)
    want = nearest_axis(p, ax.ends, ax.dirs, ax.back, ax.radius)
    assert len(set(want.tolist())) == 2
    assert np.array_equal(got[cy, cx], want)
