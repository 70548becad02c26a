"""The identity step's per-frame skeleton in plain floats equals the numpy definitions it
replaces, bit for bit (issue 13: the sequential identity step's cost): the cost of a
track for an instance, the far-head test, where a track's boxes and heads are expected,
a track's reference shape, the share of a box under another."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.model import InstanceObservation, PartObservation, RotatedBox
from mistool.tracking import identity
from mistool.tracking.identity import CostWeights, Track, TrackState, track_cost
from mistool.tracking.instances import angle_diff_deg, unit_vector
from mistool.tracking.motion import ConstantVelocity

SHAPE = (576, 720)


def _box(rng: np.random.Generator, length_max: float = 300.0) -> RotatedBox:
    length = float(rng.uniform(0.5, length_max))
    x, y = rng.uniform(-20, 740, 2)
    return RotatedBox(
        float(x), float(y), length, length * float(rng.uniform(0, 1)), float(rng.uniform(0, 180))
    )


def _instance(rng: np.random.Generator, shaft: bool = True) -> InstanceObservation:
    parts = {}
    for name in ("shaft", "wrist", "clasper"):
        if (name == "shaft" and shaft) or (name != "shaft" and rng.random() < 0.6):
            mask = np.ones((3, 4), bool)
            box = _box(rng, 300.0 if name == "shaft" else 60.0)
            offset = (int(rng.integers(0, 700)), int(rng.integers(0, 560)))
            parts[name] = PartObservation(name, box, box.corners(), 12, mask, offset)
    if not parts:
        parts["clasper"] = PartObservation(
            "clasper", _box(rng, 40), np.zeros((4, 2)), 5, np.ones((1, 5), bool), (3, 4)
        )
    x, y = rng.uniform(0, 720), rng.uniform(0, 576)
    bx, by = int(rng.integers(-1, 700)), int(rng.integers(-1, 560))
    return InstanceObservation(
        None,
        parts,
        (float(x), float(y)),
        int(rng.integers(1, 20000)),
        (bx, by, int(rng.integers(1, 100)), int(rng.integers(1, 100))),
        SHAPE if rng.random() < 0.9 else None,
    )


def _track(rng: np.random.Generator) -> Track:
    motion = ConstantVelocity(rng.uniform(-50, 750, 2), rng.normal(0, 8, 2))
    t = Track(
        name="1",
        motion=motion,
        last_frame=int(rng.integers(0, 60)),
        area=float(rng.uniform(0, 20000)),
        angle=float(rng.uniform(0, 180)) if rng.random() < 0.9 else None,
        elongation=float(rng.uniform(0, 1)),
        state=list(TrackState)[int(rng.integers(0, len(TrackState)))],
        size=float(rng.uniform(0, 200)),
        entry=rng.uniform(0, 700, 2) if rng.random() < 0.6 else None,
        in_blob=bool(rng.random() < 0.5),
    )
    t.boxes = {"shaft": _box(rng)} if rng.random() < 0.8 else None
    if t.boxes is not None:
        for p in ("wrist", "clasper"):
            if rng.random() < 0.5:
                t.boxes[p] = _box(rng, 60.0)
    t.boxes_frame = t.last_frame - int(rng.integers(0, 8))
    t.heads = {
        p: (_box(rng, 60.0), t.last_frame - int(rng.integers(0, 14)))
        for p in ("wrist", "clasper")
        if rng.random() < 0.7
    }
    return t


def _track_cost_before(
    t: Track,
    inst: InstanceObservation,
    frame: int,
    weights: CostWeights,
    fps: float,
    entry: np.ndarray | None = None,
) -> float:
    """``identity.track_cost`` as it was (commit ac466ae): the prediction and distances
    as numpy (2,) arrays."""
    gap = frame - t.last_frame
    lost = t.state is TrackState.LOST
    c = np.asarray(inst.centroid_px)
    scale = max(t.size, math.sqrt(inst.area_px), 10.0)
    if lost:
        if inst.image_shape is not None:
            scale = min(scale, weights.lost_scale_frac * math.hypot(*inst.image_shape))
        scale *= 1.0 + weights.lost_search_growth * (gap - identity.LOST_AFTER_FRAMES) / fps
    dist = float(np.hypot(*(c - t.predict(frame))))
    if lost and entry is not None and t.entry is not None and inst.image_shape is not None:
        moved = float(np.hypot(*(entry - t.entry)))
        if moved <= weights.entry_scale_frac * math.hypot(*inst.image_shape):
            dist = min(dist, moved)
    cost = dist / scale
    angle, elong = identity._appearance(inst)
    if angle is not None and t.angle is not None and not (lost and "shaft" not in inst.parts):
        w = min(elong, t.elongation)
        cost += weights.angle * w * angle_diff_deg(angle, t.angle) / 90.0
    if t.state is TrackState.TRACKED:
        cost += weights.area * abs(math.log(max(inst.area_px, 1) / max(t.area, 1.0)))
    cost += weights.gap * (gap - 1)
    if t.state is TrackState.HIDDEN:
        cost += weights.hidden_penalty
    if entry is not None and t.entry is not None and inst.image_shape is not None:
        diag = math.hypot(*inst.image_shape)
        dist = float(np.hypot(*(entry - t.entry)))
        cost += weights.entry * dist / (weights.entry_scale_frac * diag)
    return cost


def _far_head_before(t: Track, inst: InstanceObservation, frame: int, reach: float) -> bool:
    if not (t.in_blob or t.state.coasting) or "shaft" in inst.parts:
        return False
    c = np.asarray(inst.centroid_px)
    if float(np.hypot(*(c - t.predict(frame)))) <= identity.FAR_HEAD_SIZES * t.size:
        return False
    near_entry = t.entry is not None and float(np.hypot(*(c - t.entry))) <= reach
    return not (near_entry and identity._touches_border(inst))


def _expected_heads_before(t: Track, frame: int) -> dict[str, RotatedBox]:
    out = {}
    for p, (b, seen) in t.heads.items():
        gap = frame - seen
        if 0 < gap <= identity.HEAD_MEMORY_FRAMES:
            dx, dy = t.motion.velocity * min(gap, identity.SPLIT_STOP_FRAMES)
            out[p] = replace(b, cx=b.cx + float(dx), cy=b.cy + float(dy))
    return out


def _expected_boxes_before(t: Track, frame: int, steps: int | None) -> Any:
    if t.boxes is None or t.shaftless > identity.LOST_AFTER_FRAMES:
        return None
    gap = frame - t.boxes_frame
    move = gap if steps is None else min(gap, steps)
    velocity = t.motion.velocity
    dx, dy = velocity * move
    out = {p: replace(b, cx=b.cx + float(dx), cy=b.cy + float(dy)) for p, b in t.boxes.items()}
    s = out["shaft"]
    extra = 2.0 * abs(float(velocity @ unit_vector(s.angle_deg))) * (gap - move)
    out["shaft"] = replace(s, length=s.length + extra)
    return out


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_per_frame_skeleton_in_plain_floats_is_the_former_numpy(seed):
    """track_cost, _far_head, Track.expected_heads and _expected_boxes give the former
    numpy definitions' values bit for bit: every track state, lost tracks with and
    without entries, instances with and without a shaft or an image shape."""
    rng = np.random.default_rng(seed)
    t = _track(rng)
    inst = _instance(rng, shaft=bool(rng.random() < 0.7))
    frame = t.last_frame + int(rng.integers(1, 40))
    entry = rng.uniform(0, 700, 2) if rng.random() < 0.5 else None
    weights = CostWeights()
    got = track_cost(t, inst, frame, weights, 25.0, entry)
    want = _track_cost_before(t, inst, frame, weights, 25.0, entry)
    assert got == want or (math.isnan(got) and math.isnan(want))
    reach = float(rng.uniform(10, 100))
    assert identity._far_head(t, inst, frame, reach) == _far_head_before(t, inst, frame, reach)
    assert t.expected_heads(frame) == _expected_heads_before(t, frame)
    tracker = identity.IdentityTracker(_config())
    for steps in (identity.SPLIT_STOP_FRAMES, None):
        assert tracker._expected_boxes(t, frame, steps) == _expected_boxes_before(t, frame, steps)


def _config() -> Any:
    from mistool.config import config_from_dict

    return config_from_dict({"labels": "endovis17", "fps": 25.0})


def _reference_boxes_before(inst: InstanceObservation, runs: list) -> dict[str, RotatedBox]:
    """``split.reference_boxes`` as it was (commit ac466ae): numpy (2,) arrays."""
    from mistool.tracking.split import STUB_ANGLE_DEG

    boxes = {p: o.box for p, o in inst.parts.items()}
    heads = [b for p, b in boxes.items() if p != "shaft"]
    if "shaft" not in boxes or len(runs) != 1 or not heads:
        return boxes
    ends, run_px = runs[0]
    mid = ends[1]
    d = np.mean([[b.cx, b.cy] for b in heads], axis=0) - mid
    norm = float(np.hypot(*d))
    sb = boxes["shaft"]
    angle = math.degrees(math.atan2(d[1], d[0])) % 180.0
    diff = abs(sb.angle_deg - angle) % 180.0
    if norm <= 0 or min(diff, 180.0 - diff) <= STUB_ANGLE_DEG:
        return boxes
    d /= norm
    tangent = ends[2] - ends[0]
    tn = float(np.hypot(*tangent))
    sin = abs(float(tangent[0] * d[1] - tangent[1] * d[0])) / tn if tn > 0 else 1.0
    width = max(float(run_px) * sin, sb.width, 1.0)
    c = mid + 0.5 * width * d
    boxes["shaft"] = RotatedBox(float(c[0]), float(c[1]), width, width, angle)
    return boxes


@settings(max_examples=1500, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_reference_boxes_in_plain_floats_are_the_former_ones(seed):
    """split.reference_boxes redraws a stub's box as before, bit for bit (a stub across
    the line to its head, a shaft along it, one and two head parts, a zero-length
    border run)."""
    from mistool.tracking.split import reference_boxes

    rng = np.random.default_rng(seed)
    inst = _instance(rng)
    a = rng.uniform(0, 700, 2)
    b = a + (rng.uniform(-40, 40, 2) if rng.random() < 0.9 else 0.0)
    ends = np.stack([a, 0.5 * (a + b), b])
    runs = [(ends, int(rng.integers(6, 60)))] if rng.random() < 0.9 else []
    heads = [o.box for p, o in inst.parts.items() if p != "shaft"]
    if heads and rng.random() < 0.6:  # a thin stub across the line to its head
        hx = sum(h.cx for h in heads) / len(heads) - ends[1, 0]
        hy = sum(h.cy for h in heads) / len(heads) - ends[1, 1]
        across = (math.degrees(math.atan2(hy, hx)) + 90.0 + float(rng.normal(0, 10))) % 180.0
        shaft = inst.parts["shaft"]
        stub = RotatedBox(shaft.box.cx, shaft.box.cy, 40.0, 2.0, across)
        inst = replace(inst, parts={**inst.parts, "shaft": replace(shaft, box=stub)})
    got, want = reference_boxes(inst, runs), _reference_boxes_before(inst, runs)
    assert got == want


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_share_of_a_box_under_another_is_as_before(seed):
    from mistool.tracking import heads

    rng = np.random.default_rng(seed)
    a, b = _box(rng, 60.0), _box(rng, 60.0)
    if rng.random() < 0.5:
        b = replace(b, cx=a.cx + float(rng.normal(0, 10)), cy=a.cy + float(rng.normal(0, 10)))
    u = unit_vector(a.angle_deg)
    v = np.array([-u[1], u[0]])
    s, t = np.meshgrid(np.linspace(-0.5, 0.5, 5), np.linspace(-0.5, 0.5, 5))
    pts = (
        np.array([a.cx, a.cy])
        + (s.ravel() * a.length)[:, None] * u
        + (t.ravel() * a.width)[:, None] * v
    )
    assert heads._covered(a, b) == float((heads.box_distance(pts, b) <= 0.0).mean())


def _update_before(
    cv: ConstantVelocity,
    measured: np.ndarray,
    gap: int,
    continuous: bool,
    first: bool,
    unsure_along: np.ndarray | None,
) -> None:
    """``ConstantVelocity.update`` as it was (commit 7cc3df9): (2,) numpy arrays."""
    from mistool.tracking.motion import VELOCITY_GAIN

    if continuous:
        d = measured - cv.position
        if unsure_along is not None and not first:
            along = float(d @ unsure_along)
            most = abs(float(cv.velocity @ unsure_along)) * gap
            d = d + (max(-most, min(most, along)) - along) * unsure_along
        v = d / gap
        cv.velocity = v if first else VELOCITY_GAIN * v + (1.0 - VELOCITY_GAIN) * cv.velocity
    cv.position = np.asarray(measured, dtype=np.float64)


@settings(max_examples=400, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.booleans(), st.booleans())
def test_the_motion_update_in_plain_floats_is_the_former_numpy(seed, continuous, first, unsure):
    """ConstantVelocity.update (plain floats unless unsure along a direction) gives the
    former numpy update's position and velocity bit for bit."""
    rng = np.random.default_rng(seed)
    pos, vel = rng.uniform(-50, 750, 2), rng.normal(0, 8, 2)
    measured = rng.uniform(-50, 750, 2)
    gap = int(rng.integers(1, 12))
    along = unit_vector(float(rng.uniform(0, 180))) if unsure else None
    got, want = ConstantVelocity(pos.copy(), vel.copy()), ConstantVelocity(pos.copy(), vel.copy())
    got.update(measured, gap, continuous=continuous, first=first, unsure_along=along)
    _update_before(want, measured, gap, continuous, first, along)
    assert got.position.tolist() == want.position.tolist()
    assert got.velocity.tolist() == want.velocity.tolist()
    assert got.velocity.dtype == want.velocity.dtype == np.float64


def _match_before(tracker: Any, fr: Any) -> dict[int, int]:
    """``IdentityTracker._match`` as it was (commit 7cc3df9): ``track_cost`` of every
    pair into a numpy cost matrix."""
    from mistool.assignment import gated_assignment

    cost = np.full((len(fr.live), len(fr.instances)), np.inf)
    entries = [identity._one_entry(tracker._runs_of(inst)) for inst in fr.instances]
    for a, t in enumerate(fr.live):
        for b, inst in enumerate(fr.instances):
            if identity._far_head(
                t, inst, fr.index, tracker._entry_reach(inst)
            ) or identity._shrunk(t, inst, fr.index):
                continue
            cost[a, b] = tracker._cost(t, inst, fr.index, entries[b])
    return {b: a for a, b in gated_assignment(cost, tracker._weights.max_cost)}


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 4), st.integers(0, 4))
def test_the_assignment_from_terms_computed_once_is_the_former_one(seed, n_tracks, n_insts):
    """_match (each track's and instance's terms computed once per frame) makes the
    former assignment: the same pairs from the same costs."""
    rng = np.random.default_rng(seed)
    tracker = identity.IdentityTracker(_config())
    tracks = [_track(rng) for _ in range(n_tracks)]
    frame = max([t.last_frame for t in tracks], default=0) + int(rng.integers(1, 8))
    insts = [_instance(rng, shaft=bool(rng.random() < 0.7)) for _ in range(n_insts)]
    fr = identity._Frame(frame, insts, tracks)
    want = _match_before(tracker, fr)
    tracker._match(fr)
    assert fr.owner == want


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 4), st.integers(0, 4))
def test_the_costs_from_one_hypot_call_per_frame_are_those_of_each_pair(seed, n_tracks, n_insts):
    """IdentityTracker._costs (every pair's distances from one vectorised np.hypot call)
    gives each pair's track_cost bit for bit, inf where the far-head or shrunk tests
    forbid the pair, for lost, hidden and coasting tracks with and without entries."""
    rng = np.random.default_rng(seed)
    tracker = identity.IdentityTracker(_config())
    tracks = [_track(rng) for _ in range(n_tracks)]
    frame = max([t.last_frame for t in tracks], default=0) + int(rng.integers(1, 8))
    insts = [_instance(rng, shaft=bool(rng.random() < 0.7)) for _ in range(n_insts)]
    fr = identity._Frame(frame, insts, tracks)
    # border runs as a worker sends them: one (a shaft entering: an entry), none or two
    runs = [[(rng.uniform(0, 700, (3, 2)), 9)] * int(rng.integers(0, 3)) for _ in insts]
    tracker._runs = {id(i): (i, r) for i, r in zip(insts, runs, strict=True)}
    entries = [identity._one_entry(r) for r in runs]
    want = []
    for t in tracks:
        row = []
        for inst, entry in zip(insts, entries, strict=True):
            if identity._far_head(t, inst, frame, tracker._entry_reach(inst)) or identity._shrunk(
                t, inst, frame
            ):
                row.append(math.inf)
            else:
                row.append(_track_cost_before(t, inst, frame, tracker._weights, 25.0, entry))
        want.append(row)
    got = tracker._costs(fr)
    assert np.array(got).reshape(n_tracks, n_insts).view(np.int64).tolist() == (
        np.array(want).reshape(n_tracks, n_insts).view(np.int64).tolist()
    )


class _NumpyVelocity:
    """``ConstantVelocity`` as it was (commit b752e53): (2,) numpy arrays."""

    def __init__(self, position: np.ndarray, velocity: np.ndarray) -> None:
        self.position = np.asarray(position, dtype=np.float64)
        self.velocity = np.asarray(velocity, dtype=np.float64)

    def predict(self, steps: float) -> np.ndarray:
        return self.position + self.velocity * steps

    def update(self, measured: Any, gap: int, continuous: bool, first: bool, along: Any) -> None:
        _update_before(self, np.asarray(measured, dtype=np.float64), gap, continuous, first, along)  # type: ignore[arg-type]

    def coast(self, steps: float) -> None:
        self.position = self.predict(steps)


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_motion_state_in_four_floats_is_the_former_arrays(seed):
    """ConstantVelocity (position and velocity as four floats) follows the former (2,)
    array model bit for bit through any sequence of updates (measured as an array or as
    the instance's centroid tuple; continuous or not, first or not, unsure along a
    direction or not), coasts, resets and predictions."""
    rng = np.random.default_rng(seed)
    pos, vel = rng.uniform(-50, 750, 2), rng.normal(0, 8, 2)
    got, want = ConstantVelocity(pos.copy(), vel.copy()), _NumpyVelocity(pos.copy(), vel.copy())
    for _ in range(int(rng.integers(1, 30))):
        op = rng.random()
        steps = int(rng.integers(0, 12))
        if op < 0.6:
            m = rng.uniform(-50, 750, 2)
            measured = (float(m[0]), float(m[1])) if rng.random() < 0.5 else m
            gap = int(rng.integers(1, 12))
            flags = rng.random(3) < (0.8, 0.2, 0.3)
            along = unit_vector(float(rng.uniform(0, 180))) if flags[2] else None
            kw = {"continuous": bool(flags[0]), "first": bool(flags[1])}
            got.update(measured, gap, unsure_along=along, **kw)
            want.update(measured, gap, kw["continuous"], kw["first"], along)
        elif op < 0.8:
            got.coast(steps)
            want.coast(steps)
        elif op < 0.85:
            got.reset_velocity()
            want.velocity = np.zeros(2)
        assert got.predict(steps).tolist() == want.predict(steps).tolist()
        assert got.predict_xy(steps) == tuple(want.predict(steps).tolist())
        assert got.position.tolist() == want.position.tolist()
        assert got.velocity.tolist() == want.velocity.tolist()
    assert got.velocity.dtype == got.position.dtype == np.float64


def test_a_tracks_reference_shape_is_made_at_its_first_read(monkeypatch):
    """A track's boxes (split.reference_boxes of its last instance seen apart with a
    shaft) are made when first read, once, not at every update: the same boxes as
    made at the update."""
    from mistool.tracking import split

    made = []

    def counted(inst: InstanceObservation, runs: list) -> dict[str, RotatedBox]:
        made.append(inst)
        return split.reference_boxes(inst, runs)

    monkeypatch.setattr(identity, "reference_boxes", counted)
    rng = np.random.default_rng(5)
    inst = _instance(rng)
    stub = [(np.array([[0.0, 200.0], [0.0, 210.0], [0.0, 220.0]]), 21)]
    tracker = identity.IdentityTracker(_config())
    last = inst
    for k in range(6):
        last = replace(inst, centroid_px=(inst.centroid_px[0] + k, inst.centroid_px[1]))
        assert tracker.resolve(k, [last], [stub])[1] == ["1"]
    (t,) = tracker.tracks
    assert made == []  # (six updates, no boxes made)
    assert t.has_boxes and t.boxes_frame == 5
    assert t.boxes == split.reference_boxes(last, stub)
    assert t.boxes is t.boxes and made == [last]  # made once
    t.boxes = None
    assert not t.has_boxes and t.boxes is None


def _head_part(rng: np.random.Generator, name: str, x: float, y: float) -> PartObservation:
    h, w = (1, 1) if rng.random() < 0.1 else (int(rng.integers(2, 18)), int(rng.integers(2, 18)))
    mask = rng.random((h, w)) < 0.8
    mask[h // 2, w // 2] = True
    x0, y0 = int(round(x - w / 2)), int(round(y - h / 2))
    box = RotatedBox(
        x0 + (w - 1) / 2, y0 + (h - 1) / 2, max(h, w), min(h, w), 0.0 if w >= h else 90.0
    )
    return PartObservation(name, box, box.corners(), int(mask.sum()), mask, (x0, y0))


def _heads_scene(rng: np.random.Generator) -> tuple[list[InstanceObservation], list[Track], int]:
    """Two or three named tools whose head parts lie near where the others' are
    expected (0-40 px from the expected boxes' edges)."""
    frame = 20
    centre = rng.uniform(100, 500, 2)
    insts, tracks = [], []
    for k in range(int(rng.integers(2, 4))):
        heads, parts = {}, {}
        for name in ("wrist", "clasper"):
            if rng.random() < 0.8:
                cx, cy = centre + rng.normal(0, 25, 2)
                length = float(rng.uniform(2, 40))
                box = RotatedBox(
                    float(cx), float(cy), length, length * float(rng.uniform(0.1, 1)),
                    float(rng.uniform(0, 180)),
                )  # fmt: skip
                heads[name] = (box, frame - int(rng.integers(0, 13)))
            if rng.random() < 0.8:
                x, y = centre + rng.normal(0, 25, 2)
                parts[name] = _head_part(rng, name, float(x), float(y))
        if not parts:
            parts["clasper"] = _head_part(rng, "clasper", *map(float, centre))
        area = sum(p.area_px for p in parts.values())
        insts.append(
            InstanceObservation(None, parts, tuple(map(float, centre)), area, (0, 0, 1, 1), SHAPE)
        )
        motion = ConstantVelocity(centre, rng.normal(0, 3, 2))
        t = Track(
            name=str(k),
            motion=motion,
            last_frame=frame - 1,
            area=float(area),
            angle=None,
            elongation=0.0,
        )
        t.heads = heads
        tracks.append(t)
    return insts, tracks, frame


def test_no_head_within_reach_means_no_head_handed_over():
    """Where identity._heads_within_reach says no tool's expected head lies within
    HEAD_CLAIM_PX of another instance's crop of that part, hand_over_heads returns the
    very instances it was given (so _hand_over skips it); over scenes with heads at
    every distance round that reach, both answers occur and hand-overs happen."""
    from mistool.tracking.heads import hand_over_heads

    counts = {"far": 0, "near": 0, "handed": 0}
    for seed in range(600):
        rng = np.random.default_rng(seed)
        insts, tracks, frame = _heads_scene(rng)
        expected = [t.expected_heads(frame) for t in tracks]
        got = hand_over_heads(insts, expected, 3)
        if identity._heads_within_reach(insts, tracks, frame):
            counts["near"] += 1
            counts["handed"] += any(a is not b for a, b in zip(got, insts, strict=True))
        else:
            counts["far"] += 1
            assert all(a is b for a, b in zip(got, insts, strict=True)), seed
    assert min(counts.values()) >= 20, counts


def test_heads_far_apart_skip_the_hand_over(monkeypatch):
    """Two tools seen apart, their heads far from each other: the frame's hand-over is
    not attempted (hand_over_heads not called; it was called on every frame with two
    named instances)."""
    from mistool.tracking import heads

    calls = []
    monkeypatch.setattr(
        identity, "hand_over_heads", lambda *a: calls.append(a) or heads.hand_over_heads(*a)
    )
    rng = np.random.default_rng(3)
    tracker = identity.IdentityTracker(_config())
    for k in range(4):
        insts = []
        for x in (150.0, 550.0):
            parts = {"clasper": _head_part(rng, "clasper", x + k, 300.0)}
            insts.append(InstanceObservation(None, parts, (x + k, 300.0), 50, (0, 0, 1, 1), SHAPE))
        assert tracker.resolve(k, insts, [[], []])[1] == ["1", "2"]
    assert calls == []
    # the same tools' heads within reach of each other: attempted
    near = [replace(insts[0], parts={"clasper": _head_part(rng, "clasper", 545.0, 300.0)})]
    tracker.resolve(4, near + insts[1:], [[], []])
    assert len(calls) == 1


def _hand_over_heads_before(  # noqa: C901 - as it was (b752e53)
    instances: list[InstanceObservation], expected: list[dict[str, RotatedBox]], min_area: int
) -> list[InstanceObservation | None]:
    """``heads.hand_over_heads`` as it was (commit b752e53): the moved pixels as (N, 2)
    lists, the new masks made from them."""
    from mistool.model import PARTS
    from mistool.tracking import heads
    from mistool.tracking.instances import make_instance, part_observation

    def with_part(inst: InstanceObservation, part: str, xy: np.ndarray) -> Any:
        parts = {p: o for p, o in inst.parts.items() if p != part}
        if len(xy) >= min_area:
            ij = xy.astype(np.int64)
            xs, ys = ij[:, 0], ij[:, 1]
            x0, y0 = int(xs.min()), int(ys.min())
            x1, y1 = int(xs.max()) + 1, int(ys.max()) + 1
            m = np.zeros((y1 - y0, x1 - x0), np.uint8)
            m[ij[:, 1] - y0, ij[:, 0] - x0] = 255
            obs = part_observation(part, m, int(x0), int(y0), min_area)
            if obs is not None:
                parts[part] = obs
        if not parts:
            return None
        return make_instance(
            inst.label, {p: parts[p] for p in PARTS if p in parts}, inst.image_shape
        )

    def own_and_theirs(inst: InstanceObservation, part: str, theirs: Any) -> Any:
        if part not in inst.parts:
            return np.zeros((0, 2)), np.zeros((0, 2))
        xy = heads._pixels(inst, part)
        if theirs is None:
            return xy, xy[:0]
        back = heads.box_distance(xy, theirs) <= heads.HEAD_CLAIM_PX
        return xy[~back], xy[back]

    out: list[Any] = list(instances)
    for r, mine in enumerate(out):
        if mine is None:
            continue
        for part in heads.HEAD_PARTS:
            want = expected[r].get(part)
            if want is None or heads._shows(mine, part, want, min_area):
                continue
            for d, donor in enumerate(out):
                if d == r or donor is None or part not in donor.parts:
                    continue
                own = expected[d].get(part)
                if own is not None and heads._covered(want, own) >= heads.HEAD_UNDER_FRAC:
                    continue
                xy = heads._pixels(donor, part)
                to_me = heads.box_distance(xy, want)
                to_own = (
                    heads.box_distance(xy, own) if own is not None else np.full(len(xy), np.inf)
                )
                move = (to_me <= heads.HEAD_CLAIM_PX) & (to_me < to_own)
                if int(move.sum()) < min_area:
                    continue
                kept, back = own_and_theirs(mine, part, own)
                got = with_part(mine, part, np.concatenate([kept, xy[move]]))
                left = with_part(donor, part, np.concatenate([xy[~move], back]))
                if got is None or left is None:
                    continue
                out[r], out[d] = got, left
                mine = got
                break
    return out


def _same_instance(a: InstanceObservation | None, b: InstanceObservation | None) -> bool:
    if a is None or b is None:
        return a is b
    if (a.label, a.centroid_px, a.area_px, a.bbox_xywh, a.image_shape) != (
        b.label, b.centroid_px, b.area_px, b.bbox_xywh, b.image_shape,
    ):  # fmt: skip
        return False
    if list(a.parts) != list(b.parts):
        return False
    for p, q in zip(a.parts.values(), b.parts.values(), strict=True):
        if (p.part, p.box, p.area_px, p.offset) != (q.part, q.box, q.area_px, q.offset):
            return False
        if p.corners.tobytes() != q.corners.tobytes() or p.mask.dtype != q.mask.dtype:
            return False
        if p.mask.shape != q.mask.shape or not np.array_equal(p.mask, q.mask):
            return False
    return True


def test_heads_handed_over_on_painted_masks_are_the_former_pixel_lists():
    """hand_over_heads with the moved pixels painted straight into the new masks
    (kernels.split.hand_over_pixels) gives the former instances (pixel lists, masks made
    from them): the same parts, boxes, corners, areas, masks and offsets, in scenes of
    two or three tools whose heads lie round each other's (tools with and without the
    part, donors with and without their own expected box, one-pixel parts)."""
    from mistool.tracking.heads import hand_over_heads

    handed = 0
    for seed in range(500):
        rng = np.random.default_rng(seed)
        insts, tracks, frame = _heads_scene(rng)
        expected = [t.expected_heads(frame) for t in tracks]
        min_area = int(rng.integers(1, 6))
        got = hand_over_heads(insts, expected, min_area)
        want = _hand_over_heads_before(insts, expected, min_area)
        assert all(_same_instance(a, b) for a, b in zip(got, want, strict=True)), seed
        handed += any(a is not b for a, b in zip(got, insts, strict=True))
    assert handed >= 30, handed


def _windowed_scene(rng: np.random.Generator) -> tuple[Any, ...]:
    """A head part's crop much larger than a box near it or far from it (the windows of
    the head kernels cut it), and a second (own) box."""
    h, w = int(rng.integers(1, 120)), int(rng.integers(1, 120))
    mask = (rng.random((h, w)) < rng.uniform(0.0, 1.0)).astype(np.uint8)
    if rng.random() < 0.2:  # one pixel: its one-point order
        mask[:] = 0
        mask[int(rng.integers(0, h)), int(rng.integers(0, w))] = 1
    x0, y0 = int(rng.integers(0, 600)), int(rng.integers(0, 450))

    def box() -> tuple[float, ...]:
        length = float(rng.uniform(0.0, 50.0))
        width = length * float(rng.uniform(0.0, 1.0))
        cx = x0 + float(rng.uniform(-40, w + 40))
        cy = y0 + float(rng.uniform(-40, h + 40))
        if rng.random() < 0.05:
            cx = float(rng.choice([np.nan, np.inf, -np.inf]))
        u = unit_vector(float(rng.uniform(0, 180)))
        return cx, cy, float(u[0]), float(u[1]), 0.5 * length, 0.5 * width

    return mask, x0, y0, box(), box()


def _distances(xy: np.ndarray, b: tuple[float, ...]) -> np.ndarray:
    from mistool.kernels.split import box_distances

    out = np.empty(len(xy))
    box_distances(np.ascontiguousarray(xy, np.float64), *b, out)
    return out


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans())
def test_the_head_kernels_looking_at_the_boxes_windows_count_every_pixel(seed, has_own):
    """kernels.split.claimed and hand_over_pixels, which measure only the pixels within
    a box's bounds grown by the reach + 1 px (and the second distance only within
    reach), give what every pixel's box_distance gives (the definition they replace):
    the count moved, and the two new masks with their counts and bounds, on crops much
    larger than the boxes, boxes far off, non-finite centres and one-pixel parts."""
    from mistool.kernels.split import claimed, hand_over_pixels
    from mistool.tracking.heads import HEAD_CLAIM_PX as reach

    rng = np.random.default_rng(seed)
    dmask, dx0, dy0, want, own = _windowed_scene(rng)
    mmask, mx0, my0, _, _ = _windowed_scene(rng)
    if rng.random() < 0.3:
        mmask = np.zeros((0, 0), np.uint8)
    dys, dxs = np.nonzero(dmask)
    dxy = np.stack([dxs + dx0, dys + dy0], 1).astype(np.float64)
    to_me = _distances(dxy, want)
    to_own = _distances(dxy, own) if has_own else np.full(len(dxy), np.inf)
    move = (to_me <= reach) & (to_me < to_own)
    o = own if has_own else want
    assert claimed(dmask, dx0, dy0, *want, has_own, *o, reach) == int(move.sum())
    mys, mxs = np.nonzero(mmask)
    mxy = np.stack([mxs + mx0, mys + my0], 1).astype(np.float64)
    back = (_distances(mxy, o) <= reach) if has_own else np.zeros(len(mxy), bool)
    x0, y0 = min(dx0, mx0) if mmask.size else dx0, min(dy0, my0) if mmask.size else dy0
    x1 = max(dx0 + dmask.shape[1], mx0 + mmask.shape[1]) if mmask.size else dx0 + dmask.shape[1]
    y1 = max(dy0 + dmask.shape[0], my0 + mmask.shape[0]) if mmask.size else dy0 + dmask.shape[0]
    got = np.zeros((y1 - y0, x1 - x0), np.uint8)
    left = np.zeros_like(got)
    bounds = np.zeros(12, np.int64)
    bounds[:2] = x0, y0
    moved = hand_over_pixels(
        mmask, mx0, my0, dmask, dx0, dy0, *want, has_own, *o, reach, got, left, bounds
    )
    assert moved == int(move.sum())
    for canvas, xy, k in (
        (got, np.concatenate([mxy[~back], dxy[move]]), 2),
        (left, np.concatenate([dxy[~move], mxy[back]]), 7),
    ):
        want_canvas = np.zeros_like(canvas)
        ij = xy.astype(np.int64)
        want_canvas[ij[:, 1] - y0, ij[:, 0] - x0] = 255
        assert np.array_equal(canvas, want_canvas)
        assert bounds[k] == len(xy)
        if len(xy):
            assert bounds[k + 1 : k + 5].tolist() == [
                ij[:, 0].min(),
                ij[:, 1].min(),
                ij[:, 0].max() + 1,
                ij[:, 1].max() + 1,
            ]


@pytest.mark.parametrize(
    "cost", [0.0, 1.5, 3.0, math.nextafter(3.0, 4.0), 3.5, -1.0, math.inf, -math.inf, math.nan]
)
def test_one_track_and_one_instance_are_paired_as_the_assignment_pairs_them(cost, monkeypatch):
    """_match's shortcut for one track and one instance (the usual frame with one tool)
    makes the pair exactly when :func:`gated_assignment` does: at the gate, beyond it,
    non-finite."""
    from mistool.assignment import gated_assignment

    tracker = identity.IdentityTracker(_config())
    rng = np.random.default_rng(0)
    fr = identity._Frame(5, [_instance(rng)], [_track(rng)])
    monkeypatch.setattr(tracker, "_costs", lambda fr: [[cost]])
    tracker._match(fr)
    want = {b: a for a, b in gated_assignment([[cost]], tracker._weights.max_cost)}
    assert fr.owner == want
    assert fr.owner == ({0: 0} if 0 <= cost <= 3.0 or cost < 0 and math.isfinite(cost) else {})


def _tracks_state(tracker: identity.IdentityTracker) -> list[str]:
    """Every field of every track, its motion's four floats included."""
    return [
        repr(t) + repr((t.motion.x, t.motion.y, t.motion.vx, t.motion.vy)) for t in tracker.tracks
    ]


def test_the_usual_frames_updates_are_the_general_loops(monkeypatch):
    """_update_all's path for a frame with nothing split, hidden or handed over names the
    instances and updates the tracks as the general loop does: two tools crossing (apart,
    one blob split between them, apart again), one tool alone, one entering and one
    leaving; both paths taken."""
    from test_tracking import MERGED, crossing, frame

    from mistool.tracking import observe_frame

    frames = [[("A", (150.0 + 9 * k, 300.0), 60.0)] for k in range(8)]  # one tool
    frames += crossing(40)  # two, crossing
    frames += [[("B", (600.0 - 3 * k, 320.0), 120.0)] for k in range(6)]  # one left
    observed = [observe_frame(frame(*[(t, a) for _, t, a in f]), MERGED) for f in frames]
    general = identity.IdentityTracker._update_all_general
    taken = {"usual": 0, "general": 0}

    def counted(self, fr, handed):
        taken["general"] += 1
        return general(self, fr, handed)

    def always_general(self, fr):
        return general(self, fr, self._hand_over(fr))

    results = []
    in_usual = 0
    for how in ("usual", "general"):
        monkeypatch.setattr(identity.IdentityTracker, "_update_all_general", counted)
        if how == "general":
            monkeypatch.setattr(identity.IdentityTracker, "_update_all", always_general)
        tracker = identity.IdentityTracker(MERGED)
        out = []
        for k, insts in enumerate(observed):
            got, names = tracker.resolve(k, insts)
            state = _tracks_state(tracker)
            out.append((got is insts, [i.centroid_px for i in got], names, state))
        results.append(out)
        if how == "usual":
            taken["usual"] = len(observed) - taken["general"]
            in_usual = taken["general"]
    assert results[0] == results[1]
    assert taken["usual"] > 20 and in_usual > 5  # (the crossing's blob frames)
