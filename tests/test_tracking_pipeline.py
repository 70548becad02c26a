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
        start_dirs=np.zeros((2, 2)),
        margin=np.zeros(2),
    )
    got = _owner_image(part, ax)
    cy, cx = np.nonzero(crop)
    p = np.stack([cx + x0, cy + y0], 1).astype(np.float64)
    want = nearest_axis(p, ax.ends, ax.dirs, ax.back, ax.radius)
    assert len(set(want.tolist())) == 2
    assert np.array_equal(got[cy, cx], want)


def test_distal_axis_of_a_shaft_alone_points_away_from_the_border():
    """A shaft seen without its head: its distal end is the one inside the image."""
    from mistool.model import RotatedBox
    from mistool.tracking.split import distal_axis

    box = RotatedBox(300.0, 476.0, 200.0, 30.0, 90.0)  # from the bottom border, upwards
    ax = distal_axis({"shaft": box}, (576, 720))
    assert ax.direction @ np.array([0.0, -1.0]) > 0.99
    assert ax.end == pytest.approx([300.0, 376.0])
    flipped = RotatedBox(300.0, 100.0, 200.0, 30.0, 90.0)  # from the top border
    assert distal_axis({"shaft": flipped}, (576, 720)).direction @ np.array([0.0, 1.0]) > 0.99


def test_head_pixels_go_to_the_shaft_they_continue():
    """A head lies beyond its own shaft's distal end: pixels there go to that shaft,
    although another shaft's body passes nearer (in its own half-widths)."""
    from mistool.tracking.split import _Axes, head_distance2

    ax = _Axes(
        ends=np.array([[300.0, 200.0], [320.0, 260.0]]),
        dirs=np.array([[1.0, 0.0], [-1.0, 0.0]]),
        back=np.array([math.inf, math.inf]),
        radius=np.array([10.0, 30.0]),  # the second shaft is wide (near the camera)
        limit_end=np.zeros((2, 2)),
        start_dirs=np.zeros((2, 2)),
        margin=np.zeros(2),
    )
    head = np.array([[330.0, 205.0], [350.0, 200.0]])  # beyond the first shaft's end
    assert head_distance2(head, ax).argmin(1).tolist() == [0, 0]
    assert ax.distance(head).argmin(1).tolist() == [1, 1]  # the body distance says 1


def _reference_entries(inst):
    """border_entries as it was (all shaft pixels, covariance eigenvectors)."""
    from mistool.tracking.split import _pixels, border_runs

    pts = _pixels(inst.parts["shaft"])
    out = []
    for ends, length in border_runs(inst):
        mid = ends[1]
        r = max(3.0 * length, 30.0)
        near = pts[np.einsum("nd,nd->n", pts - mid, pts - mid) <= r * r]
        c = near.mean(0)
        _, v = np.linalg.eigh(np.cov((near - c).T))
        d = v[:, 1] if v[:, 1] @ (c - mid) >= 0 else -v[:, 1]
        out.append((mid, d))
    return out


def test_border_entries_match_the_reference():
    from mistool.tracking import observe_frame
    from mistool.tracking.split import border_entries

    img = frame(((420.0, 300.0), 20.0), ((330.0, 260.0), 160.0), shaft_len=500.0)
    (inst,) = observe_frame(img, MERGED)
    got = border_entries(inst)
    want = _reference_entries(inst)
    assert len(got) == len(want) == 2
    for (p, d, width), (q, e) in zip(got, want, strict=True):
        assert np.allclose(p, q)
        assert float(d @ e) > 1.0 - 1e-9
        assert 15.0 < width < 30.0  # the drawn shafts are 22 px wide


def test_a_head_fragment_inside_its_tools_blob_is_absorbed():
    """A tool entering head first: its jaws, cut apart from its wrist, first look like
    a second instrument; when the tool's blob swallows them, that name is forgotten
    and the tool keeps its own."""
    from mistool.tracking import IdentityTracker, TrackState, observe_frame

    def img(parts):
        out = np.zeros((576, 720), np.uint8)
        for (x0, y0, x1, y1), v in parts:
            out[y0:y1, x0:x1] = v
        return out

    wrist = ((680, 200, 720, 230), 20)  # at the right border
    frames = [
        img([wrist]),
        img([wrist, ((560, 205, 600, 225), 30)]),  # jaws 80 px away, inside the view
    ]
    for k in range(8):  # the whole tool slides in from the right
        x = 620 - 25 * k
        frames.append(
            img(
                [
                    ((x, 195, 720, 235), 10),
                    ((x - 40, 200, x, 230), 20),
                    ((x - 80, 205, x - 40, 225), 30),
                ]
            )
        )
    tracker = IdentityTracker(MERGED)
    names = [tracker.resolve(k, observe_frame(f, MERGED))[1] for k, f in enumerate(frames)]
    assert names[1] == ["1", "2"]  # the jaws taken for a second tool
    assert all(n == ["1"] for n in names[2:]), names
    assert tracker.tracks[1].state is TrackState.ABSORBED
