"""Crowded merged masks: tools entering the view inside a pile-up of others.

Small constructed cases for the fixes measured on ``scripts/eval_coverage.py``'s
four-tool sequences (docs/tracking.md, "Crowded scenes").
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from mistool.config import config_from_dict
from mistool.model import InstanceObservation, RotatedBox
from mistool.tracking import IdentityTracker, observe_frame
from mistool.tracking.heads import hand_over_heads
from mistool.tracking.identity import REDONE_SHAPE_HEAD_PX, distinct_lanes
from mistool.tracking.instances import make_instance, part_observation
from mistool.tracking.split import (
    BlobPixels,
    border_entries,
    border_runs,
    fit_split,
    head_stop,
    reference_boxes,
    split_instance,
    split_on_entries,
)

MERGED = config_from_dict({"labels": "endovis17", "fps": 25.0})
SHAPE = (576, 720)


def _paint(rects: list[tuple[tuple[int, int, int, int], int]]) -> np.ndarray:
    img = np.zeros(SHAPE, np.uint8)
    for (x0, y0, x1, y1), v in rects:
        img[y0:y1, x0:x1] = v
    return img


def test_a_shaft_stub_at_the_border_points_at_its_head():
    """A tool entering from the bottom shows a 10 px sliver of shaft along the border
    under its wrist and jaws: its box lies along the border; the reference box points
    from the entry to the head, as wide as the entry."""
    img = _paint(
        [
            ((300, 566, 380, 576), 10),  # shaft stub on the bottom border
            ((310, 520, 370, 566), 20),  # wrist
            ((325, 470, 355, 520), 30),  # jaws
        ]
    )
    (inst,) = observe_frame(img, MERGED)
    assert inst.parts["shaft"].box.angle_deg == pytest.approx(0.0, abs=1.0)  # along the border
    boxes = reference_boxes(inst, border_runs(inst))
    shaft = boxes["shaft"]
    assert abs(shaft.angle_deg - 90.0) < 10.0
    assert shaft.length == shaft.width == pytest.approx(80.0, abs=2.0)
    assert shaft.cy < 576 and shaft.cy == pytest.approx(576 - 40, abs=3.0)
    assert boxes["clasper"] == inst.parts["clasper"].box
    # a shaft seen along its length keeps its own box
    long_img = _paint([((300, 376, 380, 576), 10), ((325, 326, 355, 376), 30)])
    (long_inst,) = observe_frame(long_img, MERGED)
    assert reference_boxes(long_inst, border_runs(long_inst)) == {
        p: o.box for p, o in long_inst.parts.items()
    }


def test_a_split_keeps_a_stubs_axis_across_the_border():
    """Splitting a blob between a long shaft and a stub entering from the bottom: the
    stub's pixels spread most along the border, but its axis stays near its expected
    direction (into the view), so the split is shaft-like."""
    img = _paint(
        [
            ((0, 280, 400, 320), 10),  # A: from the left border
            ((380, 556, 460, 576), 10),  # B: a stub 20 px into the view, 80 px wide
        ]
    )
    x0, y0 = 0, 0
    shaft = part_observation("shaft", np.where(img == 10, 255, 0).astype(np.uint8), x0, y0, 20)
    assert shaft is not None
    inst = make_instance(None, {"shaft": shaft}, SHAPE)
    expected = [
        {
            "shaft": RotatedBox(200.0, 300.0, 400.0, 40.0, 0.0),
            "clasper": RotatedBox(420.0, 300.0, 40.0, 20.0, 0.0),
        },
        {
            "shaft": RotatedBox(420.0, 536.0, 80.0, 80.0, 90.0),
            "clasper": RotatedBox(420.0, 470.0, 40.0, 20.0, 90.0),
        },
    ]
    fit = fit_split(BlobPixels(inst), expected, 20)
    assert fit is not None
    assert abs(float(fit.axes.dirs[1] @ np.array([0.0, 1.0]))) > math.cos(math.radians(30.0))
    assert abs(float(fit.axes.dirs[0] @ np.array([1.0, 0.0]))) > 0.99


def test_a_cut_off_head_joins_the_shaft_it_continues_not_the_nearest():
    """Jaws an occluder cut off from their wrist lie on their shaft's distal extension,
    50 px from it, while another tool's jaws are 32 px away beside them: they join the
    shaft they continue."""
    img = _paint(
        [
            ((0, 150, 380, 190), 10),  # A: shaft from the left border ...
            ((380, 160, 400, 180), 30),  # ... and its jaws
            ((400, 350, 440, 576), 10),  # B: shaft from the bottom border ...
            ((405, 320, 435, 350), 20),  # ... its wrist
            ((410, 210, 430, 270), 30),  # ... and its jaws, cut off (50 px above)
        ]
    )
    insts = observe_frame(img, MERGED)
    assert len(insts) == 2
    b = next(i for i in insts if i.parts["shaft"].box.cx > 400)
    a = next(i for i in insts if i is not b)
    assert b.parts["clasper"].box.cy == pytest.approx(240.0, abs=1.0)
    assert a.parts["clasper"].area_px == 20 * 20


def test_a_cut_off_head_joins_the_shaft_it_continues_beside_a_crossing_blob():
    """Jaws cut off 50 px beyond their shaft's end lie 25 px from a blob of two crossing
    shafts (whose box says nothing of either axis): they join the one straight shaft
    whose distal extension they lie on, not the nearer blob."""
    img = _paint(
        [
            ((420, 280, 720, 320), 10),  # A: shaft from the right border
            ((330, 290, 370, 310), 30),  # A's jaws, cut off
        ]
    )
    cv2.line(img, (40, 575), (300, 345), 10, 40)  # B and C cross: one blob
    cv2.line(img, (40, 345), (300, 575), 10, 40)
    insts = observe_frame(img, MERGED)
    assert len(insts) == 2
    a = next(i for i in insts if i.parts["shaft"].box.cx > 400)
    blob = next(i for i in insts if i is not a)
    assert "clasper" not in blob.parts
    assert a.parts["clasper"].box.cx == pytest.approx(350.0, abs=1.0)


def test_a_tool_entering_head_first_keeps_its_name_in_anothers_blob():
    """Jaws entering from the top border (no shaft in view yet) touch another tool's
    jaws: the blob is split, the shaft and its jaws to that tool, the entering jaws to
    their own track (before: no split, since that track had no shaft to fit)."""
    from mistool.tracking import IdentityTracker

    top = ((290, 0, 350, 60), 30)  # H: jaws at the top border
    tracker = IdentityTracker(MERGED)
    for k, y in enumerate((260, 200, 140, 100)):  # A rises from the bottom border
        img = _paint([((305, y, 325, 576), 10), ((305, y - 40, 325, y), 30), top])
        insts = observe_frame(img, MERGED)
        assert len(insts) == (1 if k == 3 else 2)
        out, names = tracker.resolve(k, insts)
        if k == 0:
            first = {
                n: i.parts["shaft"].box.cx if "shaft" in i.parts else None
                for n, i in zip(names, out, strict=True)
            }
            a = next(n for n, x in first.items() if x is not None)
            h = next(n for n, x in first.items() if x is None)
    got = dict(zip(names, out, strict=True))
    assert set(got) == {a, h}
    assert got[a].parts["shaft"].area_px == 20 * (576 - 100)
    assert "shaft" not in got[h].parts
    jaws = got[h].parts["clasper"]
    assert jaws.area_px > 0.5 * 60 * 60
    assert jaws.box.cx == pytest.approx(320.0, abs=6.0) and jaws.box.cy < 45.0


def test_two_tools_heads_meeting_while_their_shafts_are_hidden_keep_one_name():
    """Two tools seen apart with short shafts; then both shafts are hidden and their jaws
    touch: the blob has no shaft pixel at all. The tracker names it (no split: no tool
    has shaft support there; the first such frame keeps a known name) instead of
    failing (a KeyError on the blob's missing shaft, found by sweeping the identity
    step's constants on the crowded sets)."""
    tracker = IdentityTracker(MERGED)
    for k, gap in enumerate((30, 20, 10, 0, 0)):
        jaws_a = (240 - gap, 250, 300 - gap, 290)
        jaws_b = (300 + gap, 250, 360 + gap, 290)
        rects = [(jaws_a, 30), (jaws_b, 30)]
        if gap:
            rects += [((jaws_a[0] - 40, 262, jaws_a[0], 278), 10)]
            rects += [((jaws_b[2], 262, jaws_b[2] + 40, 278), 10)]
        insts = observe_frame(_paint(rects), MERGED)
        assert len(insts) == (2 if gap else 1)
        out, names = tracker.resolve(k, insts)
        assert len(out) == len(names) == len(insts)
        if k == 0:
            first = set(names)
        if k == 3:  # the first frame of the shaftless blob
            assert len(first) == 2 and names[0] in first
            assert "shaft" not in out[0].parts and out[0].parts["clasper"].area_px == 120 * 40


def test_a_tools_shape_is_forgotten_once_its_shaft_has_left_the_view():
    """A tool seen with its shaft, then for more than LOST_AFTER_FRAMES frames as jaws
    alone (its shaft out of view): its old shaft is no expected shape for a split (it
    would claim another tool's shaft pixels); seen with a shaft again, it is one."""
    from mistool.tracking import IdentityTracker
    from mistool.tracking.identity import LOST_AFTER_FRAMES

    tool = [((340, 300, 380, 576), 10), ((345, 260, 375, 300), 30)]
    jaws = [((345, 536, 375, 576), 30)]  # at the bottom border, the shaft below it
    tracker = IdentityTracker(MERGED)
    frames = [tool, tool] + [jaws] * (LOST_AFTER_FRAMES + 1) + [tool]
    expected = []
    for k, rects in enumerate(frames):
        (inst,) = observe_frame(_paint(rects), MERGED)
        tracker.resolve(k, [inst])
        (t,) = tracker.tracks
        expected.append(tracker._expected_boxes(t, k + 1, 5))
    assert expected[1] is not None  # (frames 2 .. 2 + LOST_AFTER_FRAMES: the jaws alone)
    assert expected[1 + LOST_AFTER_FRAMES] is not None  # jaws alone for LOST_AFTER frames
    assert expected[2 + LOST_AFTER_FRAMES] is None  # ... and one more
    assert expected[-1] is not None


def test_a_head_reaches_no_farther_than_it_was_seen():
    """A wide shaft whose short jaws were seen just past its end, and another tool's jaws
    115 px farther on its axis, on that tool's own axis: those jaws go to their own tool
    (a head reaches HEAD_SEEN_MARGIN x as far as it was seen, at least a shaft width;
    not 3.5 shaft widths, 280 px here)."""
    from mistool.tracking.split import split_pieces

    shaft = _paint([((280, 0, 360, 200), 10), ((0, 310, 300, 340), 10)])
    jaws = _paint([((305, 200, 335, 240), 30), ((300, 315, 340, 335), 30)])
    parts = {
        name: part_observation(name, np.where(m > 0, 255, 0).astype(np.uint8), 0, 0, 20)
        for name, m in (("shaft", shaft), ("clasper", jaws))
    }
    inst = make_instance(None, {k: v for k, v in parts.items() if v is not None}, SHAPE)
    expected = [
        {  # A: wide, from the top, jaws 40 px long
            "shaft": RotatedBox(320.0, 100.0, 200.0, 80.0, 90.0),
            "clasper": RotatedBox(320.0, 220.0, 40.0, 30.0, 90.0),
        },
        {  # B: from the left, its jaws beyond its end (300, 325)
            "shaft": RotatedBox(150.0, 325.0, 300.0, 30.0, 0.0),
            "clasper": RotatedBox(320.0, 325.0, 40.0, 20.0, 0.0),
        },
    ]
    pixels = BlobPixels(inst)
    fit = fit_split(pixels, expected, 20)
    assert fit is not None
    a, b = split_pieces(pixels, fit, 20)
    assert a.parts["clasper"].area_px == 30 * 40  # its own jaws, nothing of B's
    assert b.parts["clasper"].area_px >= 0.99 * 40 * 20  # (a corner pixel or two to A)


def test_a_tool_back_after_being_lost_has_no_old_shape():
    """A tool unseen for longer than LOST_AFTER_FRAMES that comes back keeps its name,
    but not its old shape as the expected one for a split (the shaft has moved since;
    the old box, stretched by its speed over the gap, had reached thousands of px)."""
    from mistool.tracking import IdentityTracker
    from mistool.tracking.identity import LOST_AFTER_FRAMES

    tool = [((340, 300, 380, 576), 10), ((345, 260, 375, 300), 30)]
    tracker = IdentityTracker(MERGED)
    k = 0
    for k in range(2):
        tracker.resolve(k, observe_frame(_paint(tool), MERGED))
    k += LOST_AFTER_FRAMES + 3  # unseen meanwhile
    back = [((345, 536, 375, 576), 30)]  # its jaws at the bottom border
    _, names = tracker.resolve(k, observe_frame(_paint(back), MERGED))
    (t,) = tracker.tracks
    assert names == [t.name]
    assert tracker._expected_boxes(t, k + 1, 5) is None
    _, names = tracker.resolve(k + 1, observe_frame(_paint(tool), MERGED))
    assert names == [t.name] and tracker._expected_boxes(t, k + 2, 5) is not None


def test_a_shaft_with_no_expected_axis_is_left_out_of_the_fit():
    """A blob holding two tools with expected shapes and a third whose shape is unknown
    (back in view after being lost): the third's shaft pixels, far from both fitted
    axes, are left out of the fit (which they would spoil) and given to it."""
    from mistool.tracking.split import HeadAnchor, split_with_heads

    shaft = _paint(
        [
            ((100, 0, 140, 250), 10),  # A from the top
            ((0, 400, 300, 440), 10),  # B from the left
            ((500, 300, 540, 576), 10),  # C from the bottom: no expected shape
        ]
    )
    part = part_observation("shaft", np.where(shaft > 0, 255, 0).astype(np.uint8), 0, 0, 20)
    assert part is not None
    inst = make_instance(None, {"shaft": part}, SHAPE)
    expected = [
        {"shaft": RotatedBox(120.0, 125.0, 250.0, 40.0, 90.0)},
        {"shaft": RotatedBox(150.0, 420.0, 300.0, 40.0, 0.0)},
    ]
    pixels = BlobPixels(inst)
    assert fit_split(pixels, expected, 20, min_tracks=1) is None  # C spoils the fit
    fit = fit_split(pixels, expected, 20, min_tracks=1, keep_d2=9.0)
    assert fit is not None
    anchor = HeadAnchor({}, np.array([520.0, 280.0]), 20.0)
    got = split_with_heads(pixels, fit, 20, [anchor])
    assert got is not None
    (a, b), (c,) = got
    assert a.parts["shaft"].area_px == 40 * 250 and b.parts["shaft"].area_px == 300 * 40
    assert c is not None and c.parts["shaft"].area_px == 40 * 276


def test_the_coverage_scripts_report_the_visible_rows(tmp_path):
    """scripts/eval_coverage.py prints the visible-rows share and the ceiling of a
    sequence with mask_areas.csv; scripts/identity_misses.py lists the missed rows by
    cause (smoke test on a short occluded sequence)."""
    import subprocess
    import sys
    from pathlib import Path

    from mistool.synth import Corruptions, synthesize

    res = synthesize(
        tmp_path / "s",
        frames=20,
        instruments=2,
        preset="endovis17",
        seed=0,
        corruptions=Corruptions(occluders=2),
    )
    scripts = Path(__file__).resolve().parents[1] / "scripts"
    for name, want in (
        ("eval_coverage.py", "visible rows"),
        ("identity_misses.py", "visible truth rows"),
    ):
        proc = subprocess.run(
            [sys.executable, str(scripts / name), str(res.path)],
            capture_output=True,
            text=True,
            timeout=300,
            check=True,
        )
        assert want in proc.stdout and "nan" not in proc.stdout, proc.stdout


def _two_tools(touching: bool) -> np.ndarray:
    """A from the left border with its jaws; B from the bottom with its jaws. Touching:
    an occluder hides A's shaft end and B has moved left against A's jaws."""
    img = _paint([((0, 100, 300, 140), 10), ((300, 110, 330, 130), 30)])
    bx = 330 if touching else 345
    img[110:576, bx : bx + 40] = 10
    img[60:110, bx + 10 : bx + 30] = 30
    if touching:
        img[90:150, 260:300] = 0
    return img


def test_jaws_touching_another_tool_go_back_to_their_own():
    """A's jaws, cut off from A's shaft by an occluder, touch B's shaft: the mask makes
    them B's. They lie where A's jaws were a frame ago, away from where B's are: they
    are handed back to A, and B keeps only its own."""
    tracker = IdentityTracker(MERGED)
    for f in range(3):
        insts, names = tracker.resolve(f, observe_frame(_two_tools(f == 2), MERGED))
    by_name = dict(zip(names, insts, strict=True))
    a = next(i for i in by_name.values() if i.parts["shaft"].box.cx < 300)
    b = next(i for i in by_name.values() if i is not a)
    assert a.parts["clasper"].area_px == 600
    assert a.parts["clasper"].box.cx == pytest.approx(315.0, abs=1.0)
    assert b.parts["clasper"].area_px == 1000
    assert b.parts["clasper"].box.cy == pytest.approx(85.0, abs=1.0)


def test_a_head_where_its_own_tool_expects_it_stays():
    """Pixels nearer to where their own tool's head is expected stay with it, also when
    they lie within reach of another tool's expected head; a tool showing its head where
    expected receives nothing."""
    img = _paint([((0, 100, 300, 140), 10), ((300, 100, 340, 140), 30)])
    (a,) = observe_frame(img, MERGED)
    b_img = _paint([((400, 200, 440, 576), 10), ((300, 150, 440, 200), 30)])
    (b,) = observe_frame(b_img, MERGED)
    a_only = make_instance(None, {"shaft": a.parts["shaft"]}, SHAPE)
    want_a = {"clasper": RotatedBox(320.0, 160.0, 40.0, 20.0, 0.0)}  # overlaps B's head
    want_b = {"clasper": RotatedBox(370.0, 175.0, 140.0, 50.0, 0.0)}
    got = hand_over_heads([a_only, b], [want_a, want_b], 20)
    assert got[0] is a_only and got[1] is b  # B's head is where B's is expected
    got = hand_over_heads([a_only, b], [want_a, {}], 20)  # B's head not expected
    assert got[0] is not None and got[0].parts["clasper"].area_px > 0
    assert got[1] is not None and got[1].parts["clasper"].area_px < b.parts["clasper"].area_px


def _crossing(f: int, head: bool, y0: float = 150.0) -> np.ndarray:
    """Two tools from the left and right borders at ``y0``, 10 deg down, their ends 25 px
    further in each frame (crossing from frame 2); ``head``: a third tool's jaws entering
    from the bottom border (``y0`` 150) or the top border (else)."""
    img = np.zeros(SHAPE, np.uint8)
    for x0, sign in ((0, 1), (719, -1)):
        d = np.array([sign * math.cos(math.radians(10)), math.sin(math.radians(10))])
        start = np.array([x0, y0])
        end = start + (300 + 25 * f) * d
        cv2.line(img, tuple(map(int, start)), tuple(map(int, end)), 10, 40)
        cv2.line(img, tuple(map(int, end + 22 * d)), tuple(map(int, end + 40 * d)), 30, 16)
    if head and y0 == 150.0:
        img[536:576, 300:420] = 30
    elif head:
        img[0:20, 300:330] = 30
    return img


def test_a_tool_in_a_blob_does_not_take_a_far_head_entering_the_view():
    """While two tools cross (one blob, split between them), a third tool's jaws enter
    from the bottom border, far from both: they get a new name; the crossing tools keep
    theirs (one of them, not matched to the blob, took the jaws' name before)."""
    tracker = IdentityTracker(MERGED)
    for f in range(9):
        insts, names = tracker.resolve(f, observe_frame(_crossing(f, False), MERGED))
    before = {n: i.centroid_px[0] < 360 for n, i in zip(names, insts, strict=True)}
    insts, names = tracker.resolve(9, observe_frame(_crossing(9, True), MERGED))
    assert len(names) == 3
    for n, inst in zip(names, insts, strict=True):
        if "shaft" in inst.parts:
            assert before[n] == (inst.centroid_px[0] < 360)
        else:
            assert n not in before


def test_a_tool_in_a_blob_does_not_take_a_head_entering_near_it():
    """The same with the jaws entering from the top border 110 px from the left tool's
    centre (less than its size, 151 px, more than half of it): a new name."""
    tracker = IdentityTracker(MERGED)
    for f in range(9):
        insts, names = tracker.resolve(f, observe_frame(_crossing(f, False, 60.0), MERGED))
    before = {n: i.centroid_px[0] < 360 for n, i in zip(names, insts, strict=True)}
    insts, names = tracker.resolve(9, observe_frame(_crossing(9, True, 60.0), MERGED))
    assert len(names) == 3
    for n, inst in zip(names, insts, strict=True):
        if "shaft" in inst.parts:
            assert before[n] == (inst.centroid_px[0] < 360)
        else:
            assert n not in before and inst.area_px == 600


def _stub_beside(b: bool) -> np.ndarray:
    """A from the left border, 22 deg down; ``b``: B's shaft entering from the top
    border 50 px deep, its wrist against A."""
    img = np.zeros(SHAPE, np.uint8)
    cv2.line(img, (0, 60), (420, 228), 10, 70)
    if b:
        img[0:50, 240:320] = 10
        img[50:140, 250:310] = 20
    return img


def test_a_stub_entering_beside_another_shaft_is_split_on_its_own_lane():
    """B enters from the top against A: one blob, two shafts entering. The pixels near
    B's entry are mostly A's, so B's fitted direction lay along the border and the
    split on entries failed (the blob kept A's name); B's direction from its own lane
    splits it: A keeps its name, B gets a new one."""
    tracker = IdentityTracker(MERGED)
    for f in range(2):
        tracker.resolve(f, observe_frame(_stub_beside(False), MERGED))
    insts, names = tracker.resolve(2, observe_frame(_stub_beside(True), MERGED))
    assert len(names) == 2
    a = next(i for n, i in zip(names, insts, strict=True) if n == "1")
    b = next(i for n, i in zip(names, insts, strict=True) if n != "1")
    assert a.parts["shaft"].box.cx < b.parts["shaft"].box.cx
    assert "wrist" in b.parts and "wrist" not in a.parts


def test_one_shaft_whose_border_contact_a_hole_cut_is_not_two_lanes():
    """A shaft entering from the top with a hole where it meets the border: two border
    runs, whose lanes are alike and side by side (one shaft: no lane split); B's stub
    beside A (above) gives two distinct lanes."""
    img = _paint([((300, 0, 380, 300), 10), ((320, 300, 360, 340), 20)])
    img[0:30, 330:350] = 0
    (one,) = observe_frame(img, MERGED)
    runs = border_runs(one)
    assert len(runs) == 2
    assert not distinct_lanes(border_entries(one, runs, lanes=True), runs)
    (two,) = observe_frame(_stub_beside(True), MERGED)
    runs = border_runs(two)
    assert distinct_lanes(border_entries(two, runs, lanes=True), runs)


def _stub_over(b: bool) -> np.ndarray:
    """A from the right border; ``b``: B's shaft entering from the top, 40 px deep, its
    wrist and jaws lying on A."""
    img = _paint([((330, 90, 720, 180), 10), ((300, 150, 330, 170), 30)])
    if b:
        img[0:40, 420:500] = 10
        img[40:90, 430:490] = 20
        img[60:90, 400:430] = 30
    return img


def test_a_lane_split_leaving_an_entering_stub_headless_is_refused():
    """B's stub enters from the top over A: its fullest lane runs diagonally on into A's
    shaft (the wrist between them is no shaft pixel), and the split on those lanes
    leaves B's piece a shaft without a head: refused (the blob keeps A's name, as
    before the lanes), rather than naming a piece of A's shaft B."""
    tracker = IdentityTracker(MERGED)
    for f in range(2):
        tracker.resolve(f, observe_frame(_stub_over(False), MERGED))
    insts, names = tracker.resolve(2, observe_frame(_stub_over(True), MERGED))
    assert names == ["1"]
    assert insts[0].parts["shaft"].area_px == 390 * 90 + 80 * 40


def _wrist_over_shaft() -> tuple[InstanceObservation, InstanceObservation, dict[str, RotatedBox]]:
    """A: a shaft from the right with a 60 x 55 px wrist (3,300 px) at x 350-410; B: a
    bare shaft far below; and where A's wrist is expected."""
    (a,) = observe_frame(_paint([((410, 150, 720, 210), 10), ((350, 150, 410, 205), 20)]), MERGED)
    (b,) = observe_frame(_paint([((0, 300, 300, 340), 10)]), MERGED)
    return a, b, {"wrist": RotatedBox(380.0, 179.0, 60.0, 50.0, 0.0)}


def test_a_head_expected_under_anothers_takes_none_of_it():
    """Two tools crossing, B's wrist gone under A's (A on top): B's expected wrist lies
    inside where A's is expected. The pixels of A's wrist nearer to B's expected box
    than to A's stay A's: a head hidden under another is not handed the other's (a
    2,500-frame two-tool crossing lost 15 points of identity coverage to this)."""
    a, b, want_a = _wrist_over_shaft()
    want_b = {"wrist": RotatedBox(383.0, 166.0, 40.0, 30.0, 0.0)}
    got = hand_over_heads([a, b], [want_a, want_b], 20)
    assert got[0] is a and got[1] is b
    # the same wrist expected for B beside A's (not under it) is handed over
    beside = {"wrist": RotatedBox(383.0, 140.0, 40.0, 30.0, 0.0)}
    got = hand_over_heads([a, b], [want_a, beside], 20)
    assert got[1] is not None and "wrist" in got[1].parts


def test_a_head_expected_three_fifths_under_anothers_takes_its_pixels_beside():
    """B's wrist expected three fifths under where A's is expected (15 of the 25 grid
    points of ``_covered``), the rest beside it: A's wrist pixels lying in B's box
    outside A's are handed to B (at 0.5 B took none: a head this far out from under
    the other's is not hidden by it); four fifths under, B still takes none."""
    a, b, want_a = _wrist_over_shaft()
    partly = {"wrist": RotatedBox(383.0, 158.0, 40.0, 30.0, 0.0)}
    got = hand_over_heads([a, b], [want_a, partly], 20)
    assert got[1] is not None and got[1].parts["wrist"].area_px == 176
    assert got[0] is not None and got[0].parts["wrist"].area_px == 3300 - 176
    mostly = {"wrist": RotatedBox(383.0, 162.0, 40.0, 30.0, 0.0)}
    got = hand_over_heads([a, b], [want_a, mostly], 20)
    assert got[0] is a and got[1] is b


def _shaft_from_left(x1: int, y: int, jaws: bool = True) -> np.ndarray:
    """One tool from the left border along row ``y``: shaft to ``x1``, jaws beyond."""
    img = np.zeros(SHAPE, np.uint8)
    img[y - 20 : y + 20, 0:x1] = 10
    if jaws:
        img[y - 8 : y + 8, x1 : x1 + 40] = 30
    return img


def test_a_crowded_pieces_slide_along_its_shaft_is_not_motion():
    """A tool seen apart moving 2 px a frame across its shaft (down), then given a piece
    of a blob split between three tools whose centroid lies 100 px further along its
    shaft (the cut between tools moved): its velocity along the shaft stays as slow as
    before, across it follows the piece; a piece of a two-tool split is measured as is."""

    def velocity_after_piece(crowded: bool) -> np.ndarray:
        tracker = IdentityTracker(MERGED)
        for f in range(4):
            tracker.resolve(f, observe_frame(_shaft_from_left(300, 200 + 2 * f), MERGED))
        (t,) = tracker.tracks
        (piece,) = observe_frame(_shaft_from_left(500, 210, jaws=False), MERGED)
        tracker._update(t, piece, 4, merged=False, apart=False, crowded=crowded)
        return t.motion.velocity

    vx, vy = velocity_after_piece(crowded=True)
    assert abs(vx) < 1.0  # the tool did not move along its shaft before
    assert vy == pytest.approx(0.5 * 2.0 + 0.5 * (210 - 206), abs=0.5)  # across: measured
    vx2, _ = velocity_after_piece(crowded=False)
    assert vx2 > 40.0  # two tools: as measured (their pieces are cut across the shafts)


def test_a_tool_seen_apart_does_not_take_a_piece_a_tenth_its_size():
    """A tool seen apart, then gone from where it was (in another's blob, say) while a
    14 x 14 px piece of some tool lies near where it is expected: the piece gets a new
    name. The same piece at the image border (a tool leaving the view shrinks there)
    keeps the tool's name."""

    def names_at_4(piece: tuple[int, int, int, int]) -> list[str]:
        tracker = IdentityTracker(MERGED)
        for f in range(4):
            tracker.resolve(f, observe_frame(_shaft_from_left(300 - 5 * f, 200), MERGED))
        x0, y0, x1, y1 = piece
        img = np.zeros(SHAPE, np.uint8)
        img[y0:y1, x0:x1] = 30
        return tracker.resolve(4, observe_frame(img, MERGED))[1]

    assert names_at_4((200, 193, 214, 207)) == ["2"]  # inside the view
    assert names_at_4((0, 193, 14, 207)) == ["1"]  # at the border where it was


def _from_right(x1: int, y: int = 200) -> np.ndarray:
    """One tool from the right border along row ``y``: shaft from ``x1``, jaws before."""
    img = np.zeros(SHAPE, np.uint8)
    if x1 < SHAPE[1]:
        img[y - 20 : y + 20, x1:] = 10
        img[y - 8 : y + 8, max(0, x1 - 40) : x1] = 30
    return img


def test_a_tool_back_through_where_it_left_gets_its_name_back():
    """A tool pulled out of the view fast (80 px a frame), back 46 frames later where its
    shaft left: its centroid, predicted on from its exit, lies far outside the view, but
    its shaft enters where it did: it gets its name back."""
    tracker = IdentityTracker(MERGED)
    f = 0
    for x1 in range(300, 720, 80):
        tracker.resolve(f, observe_frame(_from_right(x1), MERGED))
        f += 1
    _, names = tracker.resolve(f + 46, observe_frame(_from_right(600), MERGED))
    assert names == ["1"]


def _head_over_shaft() -> np.ndarray:
    """A from the top border: shaft 100 px deep, wrist, jaws resting on B's shaft; B
    from the right border under it, its wrist and jaws to the left: one blob."""
    return _paint(
        [
            ((400, 0, 460, 100), 10),  # A's shaft
            ((395, 100, 465, 140), 20),  # A's wrist
            ((415, 140, 445, 170), 30),  # A's jaws, touching B's shaft
            ((300, 170, 720, 230), 10),  # B's shaft
            ((260, 175, 300, 225), 20),  # B's wrist
            ((220, 185, 260, 215), 30),  # B's jaws
        ]
    )


def test_a_shaft_entering_ends_at_its_head_in_a_split_on_entries():
    """Two tools touching since they entered, split on their entries: A's half-line from
    the top runs on through its wrist and jaws (70 px, under the gap that ends a shaft)
    into B's shaft and took the B pixels nearer to it than to B's line. It now ends
    where A's head lies across it, and B keeps its whole shaft (held-out seed 26 frame
    90, seed 11 frames 46-66: the other tool's shaft or head given the entering one)."""
    (inst,) = observe_frame(_head_over_shaft(), MERGED)
    entries = border_entries(inst)
    assert len(entries) == 2
    pieces = split_on_entries(inst, entries, 20)
    assert pieces is not None
    a, b = sorted(pieces, key=lambda i: i.parts["shaft"].box.cy)
    assert a.parts["shaft"].area_px == 60 * 100
    assert b.parts["shaft"].area_px == 420 * 60
    assert a.parts["wrist"].area_px == 70 * 40 and b.parts["wrist"].area_px == 40 * 50


def _lane_points(img: np.ndarray, values: tuple[int, ...]) -> np.ndarray:
    ys, xs = np.nonzero(np.isin(img, values))
    return np.stack([xs, ys], 1).astype(np.float64)


@pytest.mark.parametrize(
    ("rects", "expected"),
    [
        # its own wrist and jaws at its end: the stop is there (within a quarter width)
        ([((300, 200, 380, 260), 20), ((380, 215, 420, 245), 30)], 300.0),
        # another tool's jaws lying across it, the shaft going on beyond: no stop
        ([((300, 180, 360, 280), 30)], None),
        # such jaws, then its own wrist half a width beyond: the stop is at its wrist
        ([((250, 180, 310, 280), 30), ((340, 200, 400, 260), 20)], 340.0),
    ],
)
def test_head_stop_is_the_head_at_the_shafts_end(rects, expected):
    """B's shaft from the left border (60 px wide, 600 px long unless its head ends it;
    heads painted over it)."""
    img = _paint([((0, 200, 600, 260), 10)])
    for (x0, y0, x1, y1), v in rects:
        if v == 20 and expected is not None:  # its own head ends the shaft
            img[200:260, x0:600] = 0
        img[y0:y1, x0:x1] = v
    got = head_stop(
        _lane_points(img, (20, 30)),
        _lane_points(img, (10,)),
        np.array([0.0, 229.5]),
        np.array([1.0, 0.0]),
        60.0,
        20,
    )
    if expected is None:
        assert got is None
    else:
        assert got is not None and expected - 15.0 <= got <= expected


def test_a_heads_two_pieces_entering_together_are_one_tool():
    """A tool entering head first at the right border shows its two jaws apart for a
    frame (two instances at the border, two names), then one blob with its wrist and
    shaft: the second jaw's name is absorbed, and the tool is tracked (its shape learnt),
    not coasting on behalf of a hidden piece for ever (held-out seed 6 frame 24)."""
    from mistool.tracking import TrackState

    def img(parts: list[tuple[tuple[int, int, int, int], int]]) -> np.ndarray:
        out = np.zeros(SHAPE, np.uint8)
        for (x0, y0, x1, y1), v in parts:
            out[y0:y1, x0:x1] = v
        return out

    frames = [img([((690, 170, 720, 186), 30), ((690, 240, 720, 256), 30)])]
    for k in range(8):  # the whole tool slides in from the right
        x = 680 - 25 * k
        shaft = ((x + 40, 195, 720, 235), 10)
        wrist = ((x, 200, x + 40, 230), 20)
        jaws = [((x - 30, 170, x, 200), 30), ((x - 30, 230, x, 256), 30)]
        frames.append(img([shaft, wrist, *jaws]))
    tracker = IdentityTracker(MERGED)
    names = [tracker.resolve(k, observe_frame(f, MERGED))[1] for k, f in enumerate(frames)]
    assert len(names[0]) == 2  # the jaws taken for two tools
    assert all(n == names[1] for n in names[1:]) and len(names[1]) == 1, names
    tool = next(t for t in tracker.tracks if t.name == names[1][0])
    piece = next(t for t in tracker.tracks if t is not tool)
    assert piece.state is TrackState.ABSORBED
    assert tool.state is TrackState.TRACKED and tool.boxes is not None


def test_a_new_tracks_first_crowded_piece_gives_it_no_velocity():
    """A tool first seen in one frame, then given a piece of a blob split between three
    tools whose centroid lies 61 px away (the cut between tools moved, not the tool): its
    velocity is not measured on it (held-out seed 6 frame 55: 70 px a frame carried its
    expected shaft out of the blob). A piece of a two-tool split is measured as is."""

    def velocity_after_piece(crowded: bool) -> np.ndarray:
        tracker = IdentityTracker(MERGED)
        tracker.resolve(0, observe_frame(_shaft_from_left(300, 200), MERGED))
        (t,) = tracker.tracks
        (piece,) = observe_frame(_shaft_from_left(440, 200, jaws=False), MERGED)
        tracker._update(t, piece, 1, merged=False, apart=False, crowded=crowded)
        return t.motion.velocity

    assert np.allclose(velocity_after_piece(crowded=True), 0.0)
    assert velocity_after_piece(crowded=False)[0] > 40.0


def _four_tools(
    a_end: int, d: bool = True, c: bool = True
) -> tuple[InstanceObservation, list[dict[str, RotatedBox]]]:
    """One blob of four tools: A from the left (jaws at ``a_end``), B from the top (its
    jaws touching A's shaft, its expected shaft reaching across A's), C from the top-left
    corner touching A (``c``), D from the bottom ending at A's lower edge (``d``); their
    expected boxes (A's and B's first)."""
    img = _paint(
        [
            ((0, 280, a_end, 320), 10),  # A: shaft from the left
            ((a_end, 285, a_end + 40, 315), 30),  # A: jaws
            ((340, 0, 380, 200), 10),  # B: shaft from the top
            ((340, 200, 380, 240), 20),  # B: wrist
            ((350, 240, 370, 280), 30),  # B: jaws, touching A's shaft
        ]
        + [((200, 320, 240, 576), 10)] * d  # D: shaft from the bottom, touching A's
    )
    if c:
        cv2.line(img, (0, 60), (150, 270), 10, 40)  # C: shaft from the top-left, touching A
    (inst,) = observe_frame(img, MERGED)
    ea = {
        "shaft": RotatedBox(a_end / 2, 300.0, float(a_end), 40.0, 0.0),
        "clasper": RotatedBox(a_end + 20.0, 300.0, 40.0, 30.0, 0.0),
    }
    eb = {
        "shaft": RotatedBox(360.0, 160.0, 320.0, 40.0, 90.0),
        "wrist": RotatedBox(360.0, 220.0, 40.0, 40.0, 90.0),
    }
    ec = {"shaft": RotatedBox(75.0, 165.0, 258.0, 40.0, 54.5)}
    ed = {"shaft": RotatedBox(220.0, 448.0, 256.0, 40.0, 90.0)}
    return inst, [ea, eb] + [ec] * c + [ed] * d


def test_a_shafts_reach_stops_where_another_shaft_passes_through_in_a_crowded_split():
    """B's expected shaft reaches across A's, which passes right through B's line: B's
    axis ends where its own points end (y 200), not at the far edge of A's band (y 319:
    a wedge of A's shaft was B's). Only in splits of three tools or more
    (SPLIT_THROUGH_AXES): in two-tool splits every form of the cut lowered other
    sequences."""
    inst, expected = _four_tools(620)
    fit = fit_split(BlobPixels(inst), expected, 20)
    assert fit is not None
    assert fit.axes.ends[1][1] == pytest.approx(200.0, abs=3.0)
    pieces = split_instance(inst, expected, 20)
    assert pieces is not None
    a, b, _, _ = pieces
    assert b.parts["shaft"].area_px == 40 * 200  # its own shaft only
    assert a.parts["shaft"].area_px >= 620 * 40 - 1000  # A keeps its crossing
    inst3, expected3 = _four_tools(620, d=False)
    three = fit_split(BlobPixels(inst3), expected3, 20)
    assert three is not None and three.axes.ends[1][1] == pytest.approx(200.0, abs=3.0)
    inst2, expected2 = _four_tools(620, d=False, c=False)
    two = fit_split(BlobPixels(inst2), expected2, 20)
    assert two is not None and two.axes.ends[1][1] > 300.0  # two tools: not cut


def test_a_shafts_reach_is_not_cut_where_another_shaft_ends():
    """A ends at B's line (its jaws there), it does not pass through it: A's reach is not
    cut back to the edge of B's band (unseen e17 seed 202 and the viewer tests' last
    frame lost heads when it was: docs/tracking.md, eleventh pass)."""
    inst, expected = _four_tools(380)
    fit = fit_split(BlobPixels(inst), expected, 20)
    assert fit is not None
    assert fit.axes.ends[0][0] == pytest.approx(376.0, abs=2.0)


def test_a_crowded_piece_whose_head_jumped_keeps_its_velocity():
    """A tool seen apart moving 2 px a frame down, then given a piece of a blob split
    between three tools whose shaft moved on as before but whose jaws lie 60 px below
    where its jaws are expected (another tool's, handed to it by the cut): the piece's
    centroid moved with the jaws, not the tool, and its velocity is kept. With its own
    jaws where expected, the piece's motion is measured."""

    def velocity_after_piece(jaws_dy: int) -> np.ndarray:
        tracker = IdentityTracker(MERGED)
        for f in range(4):
            tracker.resolve(f, observe_frame(_shaft_from_left(300, 200 + 2 * f), MERGED))
        (t,) = tracker.tracks
        img = _shaft_from_left(300, 208, jaws=False)
        img[200 + jaws_dy : 232 + jaws_dy, 300:360] = 30
        (piece,) = observe_frame(img, MERGED)
        tracker._update(t, piece, 4, merged=False, apart=False, crowded=True)
        return t.motion.velocity

    before = IdentityTracker(MERGED)
    for f in range(4):
        before.resolve(f, observe_frame(_shaft_from_left(300, 200 + 2 * f), MERGED))
    (t0,) = before.tracks
    kept = t0.motion.velocity.copy()
    assert np.array_equal(velocity_after_piece(60), kept)  # jumped: kept
    moved = velocity_after_piece(0)  # its own jaws: measured (across the shaft)
    assert not np.array_equal(moved, kept)


def test_a_head_box_spanning_two_tools_heads_is_no_part_of_a_tools_shape():
    """A wide tool seen apart while another tool's jaws touched its own in a row: its
    jaws box spans 300 px (more than HEAD_LENGTH_WIDTHS = 3.5 widths of its 80 px shaft:
    two tools' heads). Its shape for the splits leaves that box out (its wrist bounds
    its head's reach), so in a later crossing the other tool's jaws, 75 px past its
    wrist on its axis, go to their own tool; with that box kept, its head reached 3.5
    widths and took them (the test above's case, from a shape seen apart)."""
    from mistool.tracking.split import split_pieces

    seen = [((280, 0, 360, 200), 10), ((290, 200, 350, 240), 20), ((305, 240, 335, 540), 30)]
    tracker = IdentityTracker(MERGED)
    (inst,) = observe_frame(_paint(seen), MERGED)
    tracker.resolve(0, [inst])
    (t,) = tracker.tracks
    a = tracker._expected_boxes(t, 1, 5)
    assert a is not None and set(a) == {"shaft", "wrist"}
    assert a["wrist"] == inst.parts["wrist"].box
    # a tool whose jaws alone are that long keeps them (its head's only bound)
    alone = [((280, 0, 360, 200), 10), ((305, 200, 335, 500), 30)]
    (inst2,) = observe_frame(_paint(alone), MERGED)
    tracker2 = IdentityTracker(MERGED)
    tracker2.resolve(0, [inst2])
    (t2,) = tracker2.tracks
    assert t2.boxes == {p: o.box for p, o in inst2.parts.items()}

    blob = _paint(
        [
            ((280, 0, 360, 200), 10),  # A from the top ...
            ((290, 200, 350, 240), 20),  # ... its wrist
            ((0, 310, 300, 340), 10),  # B from the left ...
            ((300, 315, 340, 335), 30),  # ... its jaws on A's axis, 75 px past A's wrist
        ]
    )
    parts = {
        name: part_observation(name, np.where(blob == v, 255, 0).astype(np.uint8), 0, 0, 20)
        for name, v in (("shaft", 10), ("wrist", 20), ("clasper", 30))
    }
    both = make_instance(None, {k: v for k, v in parts.items() if v is not None}, SHAPE)
    b = {
        "shaft": RotatedBox(150.0, 325.0, 300.0, 30.0, 0.0),
        "clasper": RotatedBox(320.0, 325.0, 40.0, 20.0, 0.0),
    }
    pixels = BlobPixels(both)
    fit = fit_split(pixels, [a, b], 20)
    assert fit is not None
    got_a, got_b = split_pieces(pixels, fit, 20)
    assert "clasper" not in got_a.parts
    assert got_b.parts["clasper"].area_px >= 0.99 * 40 * 20


def test_a_head_box_over_another_tracks_remembered_head_is_no_part_of_a_tools_shape():
    """Tool A (80 px shaft from the top) and tool B (from the left, its jaws 20 px
    below A's) seen apart; in the next frame B is not seen and one jaws strip runs down
    A's axis over where B's jaws were: A's jaws box is 200 px long (2.5 widths: under
    HEAD_LENGTH_WIDTHS, over HEAD_OVER_OTHER_WIDTHS) and holds B's remembered jaws. A's
    shape for the splits leaves that box out (its wrist bounds its head's reach); the
    same box with no other track's head in it is kept (the only bound of a long head)."""
    a = [((280, 0, 360, 200), 10), ((290, 200, 350, 240), 20)]  # A's shaft, wrist
    b = [((0, 400, 250, 430), 10), ((250, 395, 290, 435), 20), ((290, 400, 330, 430), 30)]
    short, long = ((305, 240, 335, 380), 30), ((305, 240, 335, 440), 30)

    def a_after(first: list[tuple[tuple[int, int, int, int], int]]) -> dict[str, RotatedBox]:
        tracker = IdentityTracker(MERGED)
        tracker.resolve(0, observe_frame(_paint(first), MERGED))
        (inst,) = observe_frame(_paint([*a, long]), MERGED)
        assert inst.parts["clasper"].box.length == pytest.approx(200.0)
        tracker.resolve(1, [inst])
        (t,) = [t for t in tracker.tracks if t.last_frame == 1]
        assert t.boxes_frame == 1
        e = tracker._expected_boxes(t, 1, 5)
        assert e is not None and e["wrist"] == inst.parts["wrist"].box
        return e

    assert len(observe_frame(_paint([*a, short, *b]), MERGED)) == 2  # seen apart
    assert set(a_after([*a, short, *b])) == {"shaft", "wrist"}
    assert set(a_after([*a, short])) == {"shaft", "wrist", "clasper"}


def test_a_head_part_of_two_large_pieces_is_no_part_of_a_tools_shape():
    """Tool A (80 px shaft from the top) seen apart with another tool's wrist touching
    its jaws (grouped into A's instance): A's wrist part is two label components, its
    own 60 x 40 px and the other's 40 x 30 px, each of at least HEAD_PIECE_PX. A's shape
    for the splits leaves that wrist box out (its jaws bound its head's reach); with the
    second piece under HEAD_PIECE_PX (a wrist cut in two) the box is kept."""
    from mistool.tracking.identity import HEAD_PIECE_PX

    a = [((280, 0, 360, 200), 10), ((290, 200, 350, 240), 20), ((305, 240, 335, 300), 30)]

    def shape_with(piece: tuple[int, int, int, int]) -> tuple[set[str], int]:
        tracker = IdentityTracker(MERGED)
        (inst,) = observe_frame(_paint([*a, (piece, 20)]), MERGED)
        tracker.resolve(0, [inst])
        (t,) = tracker.tracks
        e = tracker._expected_boxes(t, 1, 5)
        assert e is not None and e["clasper"] == inst.parts["clasper"].box
        return set(e), inst.parts["wrist"].area_px

    got, area = shape_with((335, 270, 375, 300))  # the other tool's wrist: 40 x 30 px
    assert area == 60 * 40 + 40 * 30 and 40 * 30 >= HEAD_PIECE_PX
    assert got == {"shaft", "clasper"}
    got, area = shape_with((335, 280, 355, 300))  # 20 x 20 px
    assert area == 60 * 40 + 20 * 20 and 20 * 20 < HEAD_PIECE_PX
    assert got == {"shaft", "wrist", "clasper"}


def test_a_crowded_pieces_head_part_of_two_large_pieces_is_not_remembered():
    """Tool A seen apart (frame 0), then a piece of a blob split between three tools
    (frame 1) whose wrist is two label components of at least HEAD_PIECE_PX (A's own
    60 x 40 px and another tool's 40 x 30 px): A's remembered wrist stays frame 0's box
    (the hand-over's memory of A's head, not of two tools'). A piece of a two-tool
    crossing split, and a crowded piece with a wrist cut in two small pieces, renew it."""
    from mistool.tracking.identity import HEAD_PIECE_PX

    a = [((280, 0, 360, 200), 10), ((290, 200, 350, 240), 20), ((305, 240, 335, 300), 30)]

    def remembered(piece: tuple[int, int, int, int], crowded: bool) -> int:
        tracker = IdentityTracker(MERGED)
        (first,) = observe_frame(_paint(a), MERGED)
        tracker.resolve(0, [first])
        (t,) = tracker.tracks
        assert t.heads["wrist"] == (first.parts["wrist"].box, 0)
        (inst,) = observe_frame(_paint([*a, (piece, 20)]), MERGED)
        tracker._update(t, inst, 1, merged=False, apart=False, crowded=crowded)
        assert t.heads["clasper"][1] == 1  # (one component: renewed)
        box, seen = t.heads["wrist"]
        assert box == (first if seen == 0 else inst).parts["wrist"].box
        return seen

    assert 40 * 30 >= HEAD_PIECE_PX > 20 * 20
    assert remembered((335, 270, 375, 300), crowded=True) == 0  # the other's wrist
    assert remembered((335, 270, 375, 300), crowded=False) == 1  # two tools crossing
    assert remembered((335, 280, 355, 300), crowded=True) == 1  # 20 x 20 px: one tool's


def _facing(bx: int, a: bool = True, b: bool = True, heads: tuple[bool, bool] = (True, True)):
    """A (wide) from the left along row 200: shaft to x 400, wrist, jaws to 470; B from
    the right along the same row: jaws from ``bx``, wrist, shaft from ``bx + 70``."""
    img = np.zeros(SHAPE, np.uint8)
    if a:
        img[160:240, 0:400] = 10
    if heads[0]:
        img[178:222, 400:440] = 20
        img[190:210, 440:470] = 30
    if b:
        img[180:220, bx + 70 :] = 10
    if heads[1]:
        img[182:218, bx + 30 : bx + 70] = 20
        img[192:208, bx : bx + 30] = 30
    return img


def _after_entry_split(b_head_in_view: bool) -> dict[str, dict[str, int]]:
    """Two tools on one line seen apart, their jaws meeting in frame 7 (one blob, B too
    small a part of it to be looked for inside: the entry handler splits it), the split on
    entries giving A both heads and B its shaft alone (its half-line ran on through the
    heads, as in twox s1 frames 119-128; stood in for here). Each name's part areas."""
    tracker = IdentityTracker(MERGED)
    for f, bx in enumerate(range(540, 470, -10)):
        tracker.resolve(f, observe_frame(_facing(bx), MERGED))
    (blob,) = observe_frame(_facing(470, heads=(True, b_head_in_view)), MERGED)
    (a,) = observe_frame(_facing(470, b=False, heads=(True, b_head_in_view)), MERGED)
    (b,) = observe_frame(_facing(470, a=False, heads=(False, False)), MERGED)

    def entry_split(inst, runs, entries):  # type: ignore[no-untyped-def]
        assert inst is blob and len(entries) == 2
        return [a if e[0][0] < SHAPE[1] / 2 else b for e in entries]

    tracker._entry_split = entry_split  # type: ignore[method-assign]
    insts, names = tracker.resolve(7, [blob])
    pairs = zip(names, insts, strict=True)
    return {n: {p: o.area_px for p, o in i.parts.items()} for n, i in pairs}


def test_an_entry_split_leaving_a_tools_head_with_another_is_redone_by_the_crossing_split():
    """The split on entries left B (known, its reference shape with a wrist and jaws)
    headless and gave A both heads: the crossing split on the tools' reference shapes
    is taken instead, and B gets head pixels where its head lies (most of its 40 x 36
    wrist); A keeps its shaft."""
    got = _after_entry_split(b_head_in_view=True)
    assert got["1"]["shaft"] == 80 * 400 and got["2"]["shaft"] == 40 * 180
    assert got["2"].get("wrist", 0) > 0.8 * 40 * 36
    assert got["1"]["wrist"] < 44 * 40 + 0.2 * 40 * 36


def test_an_entry_split_is_kept_when_the_headless_tools_head_is_not_in_the_blob():
    """The same blob with B's head out of view: the crossing split finds no head for B,
    the split on entries stands."""
    got = _after_entry_split(b_head_in_view=False)
    assert got["2"] == {"shaft": 40 * 180}
    assert got["1"] == {"shaft": 80 * 400, "wrist": 44 * 40, "clasper": 20 * 30}


def test_a_redone_entry_pieces_shape_follows_its_tool_still_entering():
    """B's shape from the redone entry split above (its shaft entering, its head found
    by the crossing split) is renewed from a later two-tool crossing piece that shows
    its shaft grown (B still entering: 4-e17-occ-s4-150 frames 39-60, where the frozen
    256 px shape put B's wrist 150 px short and it took A's); a piece no longer than
    the shape, or a headless one, leaves the shape as it was."""
    tracker = IdentityTracker(MERGED)
    for f, bx in enumerate(range(540, 470, -10)):
        tracker.resolve(f, observe_frame(_facing(bx), MERGED))
    (blob,) = observe_frame(_facing(470), MERGED)
    (a,) = observe_frame(_facing(470, b=False), MERGED)
    (b,) = observe_frame(_facing(470, a=False, heads=(False, False)), MERGED)

    def entry_split(inst, runs, entries):  # type: ignore[no-untyped-def]
        return [a if e[0][0] < SHAPE[1] / 2 else b for e in entries]

    tracker._entry_split = entry_split  # type: ignore[method-assign]
    tracker.resolve(7, [blob])
    tb = next(t for t in tracker.tracks if t.name == "2")
    assert tb.boxes_frame == 7 and tb.boxes_entering
    before = tb.boxes
    assert before is not None
    # a piece of a crossing, B's shaft 40 px deeper with its head: its shape renewed
    (deeper,) = observe_frame(_facing(430, a=False), MERGED)
    tracker._update(tb, deeper, 8, merged=False, apart=False)
    assert tb.boxes_frame == 8 and tb.boxes_entering
    assert tb.boxes is not None and tb.boxes["shaft"].length > before["shaft"].length + 30
    # no deeper (and headless): kept
    kept = tb.boxes
    for f, img in enumerate((_facing(430, a=False), _facing(400, a=False, heads=(False, False)))):
        (piece,) = observe_frame(img, MERGED)
        tracker._update(tb, piece, 9 + f, merged=False, apart=False)
        assert tb.boxes_frame == 8 and tb.boxes == kept


def _redone_with_a_strip(rows: int) -> tuple[dict[str, int], int, set[str]]:
    """The blob of :func:`_after_entry_split` with B's head hidden but for a strip of
    wrist ``rows`` px high along row 200 (from A's jaws to B's shaft), the split on
    entries leaving B headless: B's part areas after the redo, its shape's frame and
    parts."""
    tracker = IdentityTracker(MERGED)
    for f, bx in enumerate(range(540, 470, -10)):
        tracker.resolve(f, observe_frame(_facing(bx), MERGED))

    def frame7(a: bool = True, b: bool = True) -> np.ndarray:
        img = _facing(470, a=a, b=b, heads=(a, False))
        if b:
            img[201 - rows : 201, 470:540] = 20
        return img

    (blob,) = observe_frame(frame7(), MERGED)
    (a,) = observe_frame(frame7(b=False), MERGED)
    (b,) = observe_frame(_facing(470, a=False, heads=(False, False)), MERGED)

    def entry_split(inst, runs, entries):  # type: ignore[no-untyped-def]
        return [a if e[0][0] < SHAPE[1] / 2 else b for e in entries]

    tracker._entry_split = entry_split  # type: ignore[method-assign]
    insts, names = tracker.resolve(7, [blob])
    got = {p: o.area_px for p, o in insts[names.index("2")].parts.items()}
    tb = next(t for t in tracker.tracks if t.name == "2")
    assert tb.boxes is not None
    return got, tb.boxes_frame, set(tb.boxes)


def test_a_redone_entry_piece_with_a_sliver_of_head_is_no_reference_shape():
    """The redo gives B the strip of wrist it shows (2 rows: 115 px), but a shape with
    that sliver of head would stand through the crossing that follows (dev seed 65
    frames 72-94: tool 4's 57 px wrist, then the split gave its wrist to tool 2): B
    keeps its shape from frame 6, wrist and jaws. A strip of 4 rows (236 px) is B's
    shape."""
    got, frame, parts = _redone_with_a_strip(2)
    assert got["shaft"] == 40 * 180 and 0 < got.get("wrist", 0) < REDONE_SHAPE_HEAD_PX
    assert frame == 6 and parts == {"shaft", "wrist", "clasper"}
    got, frame, parts = _redone_with_a_strip(4)
    assert got["wrist"] >= REDONE_SHAPE_HEAD_PX
    assert frame == 7 and parts == {"shaft", "wrist"}
