"""Offline relinking (mistool.tracking.relink): fragments absorbed, broken lives linked.

Constructed tables and mask sequences for the cases measured on ``scripts/eval_coverage.py``'s
sequences (docs/tracking.md, "Crowded scenes: fifth pass").
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from mistool.api import track
from mistool.assignment import gated_assignment
from mistool.config import config_from_dict
from mistool.model import TrackTable
from mistool.tracking.relink import (
    FRAGMENT_REACH_PX,
    HEAD_MOVE_MARGIN,
    HEAD_SWAP_KEEP_MARGIN,
    HEAD_SWAP_MARGIN,
    HEAD_SWAP_MIN_FRAMES,
    JUMP_PX,
    LINK_GATE,
    attachment_cost,
    box_gap,
    link_cost,
    move_heads,
    relink,
    sparse_gated_assignment,
    swap_heads,
)

MERGED = config_from_dict({"labels": "endovis17", "fps": 25.0})
SHAPE = (576, 720)


def _row(
    frame: int,
    name: str,
    part: str,
    cx: float,
    cy: float,
    length: float,
    width: float,
    angle: float = 0.0,
) -> dict[str, object]:
    u = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
    v = np.array([-u[1], u[0]])
    c = np.array([cx, cy])
    corners = [
        c + sa * 0.5 * length * u + sb * 0.5 * width * v
        for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1))
    ]
    row: dict[str, object] = dict(
        frame=frame,
        instrument=name,
        part=part,
        cx_px=cx,
        cy_px=cy,
        length_px=length,
        width_px=width,
        angle_deg=angle,
        area_px=length * width,
    )
    for k, (x, y) in enumerate(corners, 1):
        row[f"x{k}_px"], row[f"y{k}_px"] = float(x), float(y)
    return row


def _table(rows: list[dict[str, object]]) -> TrackTable:
    return TrackTable({k: [r[k] for r in rows] for k in rows[0]})


def _names(table: TrackTable, frame: int) -> dict[str, str]:
    """part -> instrument in one frame (one tool per part in these cases)."""
    return {
        str(p): str(i)
        for f, i, p in zip(table["frame"], table["instrument"], table["part"], strict=True)
        if f == frame
    }


def _tool_from_right(frame: int, name: str, x0: float, y: float) -> list[dict[str, object]]:
    """A tool along row ``y``: shaft from ``x0`` to the right border, wrist and jaws before."""
    shaft = 720.0 - x0
    return [
        _row(frame, name, "shaft", x0 + 0.5 * shaft, y, shaft, 40.0),
        _row(frame, name, "wrist", x0 - 15.0, y, 30.0, 24.0),
        _row(frame, name, "clasper", x0 - 50.0, y, 40.0, 16.0),
    ]


def test_box_gap_of_boxes_apart_touching_and_crossing():
    a = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    assert box_gap(a, a + [30, 0]) == pytest.approx(20.0)
    assert box_gap(a, a + [10, 0]) == pytest.approx(0.0)
    assert box_gap(a, a + [13, 14]) == pytest.approx(5.0)  # corner to corner (3, 4)
    cross = np.array([[-5, 4], [15, 4], [15, 6], [-5, 6]], float)  # no corner inside
    assert box_gap(a, cross) == 0.0


def test_a_head_entering_in_two_pieces_is_one_tool():
    """A tool entering head first, its head cut in two by an occluder (held-out seeds 6
    and 7): the piece got a name of its own for one frame. The metric matched the tool to
    that one-frame name (seed 7 72.4%); relinked, its rows are the tool's."""
    rows = []
    for f in range(12):
        rows.append(_row(f, "1", "wrist", 700.0 - 10 * f, 100.0, 30.0, 20.0))
        rows.append(_row(f, "1", "clasper", 660.0 - 10 * f, 100.0, 30.0, 12.0))
    rows.append(_row(0, "2", "clasper", 600.0, 104.0, 20.0, 10.0))  # 25 px beyond the jaws
    rows.append(_row(3, "3", "clasper", 300.0, 400.0, 20.0, 10.0))  # another, far: kept
    for f in range(4, 12):
        rows.append(_row(f, "3", "clasper", 300.0, 400.0, 20.0, 10.0))
    out = relink(_table(rows), 25.0)
    assert sorted(set(out["instrument"])) == ["1", "2"]
    # the piece's clasper row dropped (the tool shows its own jaws in that frame)
    assert out.num_rows == len(rows) - 1
    assert set(out[out["frame"] == 0]["instrument"]) == {"1"}
    far = out[np.asarray(out["cx_px"]) == 300.0]
    assert set(far["instrument"]) == {"2"} and far.num_rows == 9


def test_a_head_entering_under_two_names_for_a_few_frames_is_one_tool():
    """Fresh seed 58 (65.4%): a tool entering head first was named "2" for three frames,
    a piece of it "3" in the middle one, and the tool went on as "3": the short-lived
    host of the piece is long enough (3 frames), the piece's name is absorbed and the
    tool's first three frames linked to the rest."""
    rows = []
    for f in range(44, 47):
        rows.append(_row(f, "2", "clasper", 700.0 - 10 * (f - 44), 100.0, 30.0, 12.0))
    rows.append(_row(45, "3", "clasper", 650.0, 104.0, 20.0, 10.0))
    for f in range(47, 80):
        rows.append(_row(f, "3", "clasper", 670.0 - 10 * (f - 47), 100.0, 30.0, 12.0))
    out = relink(_table(rows), 25.0)
    assert set(out["instrument"]) == {"1"}
    assert out.num_rows == len(rows) - 1


def test_a_piece_farther_than_an_occluder_or_beside_a_shaft_is_no_fragment():
    """A short-lived name beyond the fragment reach, or beside a tool showing its shaft
    (a cut-off head there joins its shaft in the grouping; a tool entering beside it is
    another), keeps its name."""
    far = FRAGMENT_REACH_PX + 20.0
    for with_shaft in (False, True):
        rows = []
        for f in range(12):
            rows.append(_row(f, "1", "wrist", 400.0, 100.0, 30.0, 20.0))
            if with_shaft:
                rows.append(_row(f, "1", "shaft", 560.0, 100.0, 290.0, 40.0))
        near = 415.0 + 20.0 + 10.0  # 20 px from the wrist's edge
        x = near if with_shaft else 415.0 + far + 10.0
        rows.append(_row(0, "2", "clasper", x, 100.0, 20.0, 10.0))
        out = relink(_table(rows), 25.0)
        assert set(out[out["frame"] == 0]["instrument"]) == {"1", "2"}, with_shaft


def test_jaws_cut_off_past_a_tools_wrist_are_that_tools():
    """Held-out seed 7, frame 29: a tool showing its shaft and wrist, its jaws cut off by
    an occluder and named apart for one frame, 50 px on beyond the wrist along the shaft:
    the tool's. The same piece off to the side of the tool keeps its name."""
    for dy, absorbed in ((0.0, True), (80.0, False)):
        rows = []
        for f in range(12):
            rows.append(_row(f, "1", "shaft", 560.0, 100.0, 290.0, 40.0))
            rows.append(_row(f, "1", "wrist", 400.0, 100.0, 30.0, 20.0))
        rows.append(_row(0, "2", "clasper", 335.0, 100.0 + dy, 40.0, 12.0))
        out = relink(_table(rows), 25.0)
        assert (set(out[out["frame"] == 0]["instrument"]) == {"1"}) == absorbed, dy


def test_a_tool_back_farther_than_the_online_search_gets_its_name_back():
    """A tool leaves the view at the right border and comes back 46 frames later with its
    shaft entering 150 px lower (four-tool leaving-view seeds 4 and 5: a new name, 80.3 /
    78.3%); another tool stays at the left all along."""
    rows = []
    for f in range(150):
        rows += [_row(f, "1", "shaft", 100.0, 300.0, 200.0, 40.0)]
    for f in range(20):
        rows += _tool_from_right(f, "2", 400.0 + 15 * f, 100.0)
    for f in range(66, 150):
        rows += _tool_from_right(f, "3", 690.0 - 2 * (f - 66), 250.0)
    out = relink(_table(rows), 25.0)
    assert sorted(set(out["instrument"])) == ["1", "2"]
    assert _names(out, 100)["clasper"] == "2"
    # the cost of that link, under the gate; from the opposite border it is not made
    assert link_cost(150.0, 46 / 25.0, 92.2, same_name=False) < LINK_GATE
    assert link_cost(650.0, 46 / 25.0, 92.2, same_name=False) > LINK_GATE


def test_a_tool_entering_elsewhere_is_not_linked_to_one_that_left():
    rows = []
    for f in range(20):
        rows += _tool_from_right(f, "1", 400.0 + 15 * f, 100.0)
    for f in range(66, 150):  # a shaft entering from the left border
        rows += [_row(f, "2", "shaft", 60.0, 400.0, 120.0, 40.0)]
    out = relink(_table(rows), 25.0)
    assert sorted(set(out["instrument"])) == ["1", "2"]


def test_a_name_given_back_to_the_wrong_tool_is_relinked():
    """Leaving-view seed 7: tool A left (frame 54) and its name went to tool B entering
    elsewhere 3 frames later; B left and came back under that name, and A came back under
    a new one. Relinked by where each shaft enters the view: A's lives are one name, B's
    another."""
    rows = []
    for f in range(0, 30):
        rows += _tool_from_right(f, "1", 500.0 + 5 * f, 100.0)  # A
    for f in range(33, 40):  # B at the top border, under A's name
        rows += [_row(f, "1", "shaft", 300.0, 40.0, 80.0, 40.0, 90.0)]
    for f in range(70, 150):  # A back, near where it left, under a new name
        rows += _tool_from_right(f, "2", 560.0, 130.0)
    for f in range(80, 150):  # B back, at the top border, under A's old name
        rows += [_row(f, "1", "shaft", 320.0, 40.0, 80.0, 40.0, 90.0)]
    out = relink(_table(rows), 25.0)
    assert _names(out, 10)["shaft"] == _names(out, 100)["clasper"]
    b = {str(i) for f, i in zip(out["frame"], out["instrument"], strict=True) if 33 <= f < 40}
    b_late = {
        str(i)
        for f, i, x in zip(out["frame"], out["instrument"], out["cx_px"], strict=True)
        if f >= 80 and x < 400
    }
    assert b == b_late and b != {_names(out, 10)["shaft"]}


def test_a_name_handed_to_a_tool_entering_elsewhere_is_cut_where_it_jumps():
    """Fresh seed 56 (72.9%): the identity step handed tool A's name "2" to tool B
    entering at the top border (300 px away) in the very frame A went on as "3"; the
    name runs on without a gap, so the tracklets met nowhere and the metric matched B
    to "3" (A's, then B's). Cut where the name jumps, A's frames are linked on into "3"
    and B keeps "2" from its first frame."""
    rows = []
    for f in range(30):
        rows += _tool_from_right(f, "2" if f < 10 else "3", 560.0 - 2 * f, 300.0)
    for f in range(10, 30):  # B, from the top border, under A's old name
        rows += [_row(f, "2", "shaft", 200.0, 40.0, 80.0, 40.0, 90.0)]
    out = relink(_table(rows), 25.0)
    a = {str(i) for i, x in zip(out["instrument"], out["cx_px"], strict=True) if x != 200.0}
    b = {str(i) for i, x in zip(out["instrument"], out["cx_px"], strict=True) if x == 200.0}
    assert len(a) == 1 and len(b) == 1 and a != b
    assert out.num_rows == len(rows)


def test_a_tool_moving_on_does_not_jump():
    """A name's boxes within :data:`JUMP_PX` of its boxes in the frame before (a tool
    moving, its head coming and going; jaws alone moving fast) are one tracklet: nothing
    is relinked."""
    rows = []
    for f in range(30):
        tool = _tool_from_right(f, "1", 400.0 - 10 * f, 300.0)
        rows += tool if f % 4 else tool[:1]  # the head unseen every fourth frame
    step = 40.0 + 0.9 * JUMP_PX  # jaws 40 px long: their boxes 0.9 JUMP_PX apart
    rows += [_row(f, "2", "clasper", 650.0 - step * f, 40.0, 40.0, 16.0) for f in range(8)]
    table = _table(rows)
    assert relink(table, 25.0) is table


def _heads_meeting(
    frame: int, swapped: tuple[str, ...], jaws_gain: float | None = None
) -> list[dict[str, object]]:
    """Tool "1" from the left border along y = 200 and tool "2" from the right along
    y = 300, their jaws meeting between them; the ``swapped`` head parts carry the other
    tool's name. ``jaws_gain``: the jaws lie on the line between the wrists, each nearer
    its own by ``jaws_gain / 4`` px (a swap of them gains ``jaws_gain`` px)."""
    other = {"1": "2", "2": "1"}
    rows = _heads_apart(frame, jaws_gain)
    for r in rows:
        if r["part"] in swapped:
            r["instrument"] = other[str(r["instrument"])]
    return rows


def _heads_apart(frame: int, jaws_gain: float | None) -> list[dict[str, object]]:
    if jaws_gain is not None:
        w1, w2 = np.array([330.0, 200.0]), np.array([390.0, 300.0])
        mid, u = 0.5 * (w1 + w2), (w2 - w1) / np.hypot(*(w2 - w1))
        j1, j2 = mid - 0.25 * jaws_gain * u, mid + 0.25 * jaws_gain * u
        return [
            _row(frame, "1", "shaft", 150.0, 200.0, 300.0, 60.0),
            _row(frame, "1", "wrist", 330.0, 200.0, 40.0, 40.0),
            _row(frame, "1", "clasper", float(j1[0]), float(j1[1]), 40.0, 16.0, 60.0),
            _row(frame, "2", "shaft", 570.0, 300.0, 300.0, 60.0, 180.0),
            _row(frame, "2", "wrist", 390.0, 300.0, 40.0, 40.0),
            _row(frame, "2", "clasper", float(j2[0]), float(j2[1]), 40.0, 16.0, 60.0),
        ]
    return [
        _row(frame, "1", "shaft", 150.0, 200.0, 300.0, 60.0),
        _row(frame, "1", "wrist", 330.0, 200.0, 40.0, 40.0),
        _row(frame, "1", "clasper", 360.0, 205.0, 40.0, 16.0, 20.0),
        _row(frame, "2", "shaft", 570.0, 300.0, 300.0, 60.0, 180.0),
        _row(frame, "2", "wrist", 390.0, 300.0, 40.0, 40.0),
        _row(frame, "2", "clasper", 365.0, 290.0, 40.0, 16.0, 160.0),
    ]


def _part_xy(table: TrackTable, frame: int, name: str, part: str) -> tuple[float, float]:
    (i,) = [
        k
        for k, (f, n, p) in enumerate(
            zip(table["frame"], table["instrument"], table["part"], strict=True)
        )
        if f == frame and n == name and p == part
    ]
    return float(table["cx_px"][i]), float(table["cy_px"][i])


def test_attachment_cost_along_and_across_a_shaft_and_to_a_wrist():
    end, u = np.array([300.0, 200.0]), np.array([1.0, 0.0])
    assert attachment_cost(np.array([330.0, 200.0]), end, u) == pytest.approx(15.0)
    assert attachment_cost(np.array([300.0, 240.0]), end, u) == pytest.approx(40.0)
    assert attachment_cost(np.array([330.0, 240.0]), end, None) == pytest.approx(50.0)


@pytest.mark.parametrize("parts", [("clasper",), ("wrist", "clasper"), ("wrist",)])
def test_heads_swapped_for_several_frames_go_back_to_the_shafts_they_hang_on(parts):
    """Two tools' jaws swapped where they touched, the head memory keeping the swap
    after they parted (held-out seed 13, frames 71-115: 84.5%): each head goes back to
    the tool whose shaft (wrist) it hangs on, through relink."""
    rows = []
    for f in range(12):
        rows += _heads_meeting(f, parts if 3 <= f < 3 + HEAD_SWAP_MIN_FRAMES + 2 else ())
    out = relink(_table(rows), 25.0)
    want = _table(sum((_heads_meeting(f, ()) for f in range(12)), []))
    for f in range(12):
        for name in ("1", "2"):
            for part in ("shaft", "wrist", "clasper"):
                assert _part_xy(out, f, name, part) == _part_xy(want, f, name, part)


def test_heads_swapped_for_two_frames_are_left_and_right_ones_untouched():
    """A swap seen in two frames is no evidence (fewer than HEAD_SWAP_MIN_FRAMES: where
    heads touch, merged heads' box centres lie between them, and a crossing's pieces'
    shaft boxes are off); heads already on their own tool give the very table back."""
    right = _table(sum((_heads_meeting(f, ()) for f in range(12)), []))
    assert swap_heads(right) is right
    rows = []
    for f in range(12):
        rows += _heads_meeting(f, ("clasper",) if f in (3, 4) else ())
    short = _table(rows)
    assert swap_heads(short) is short


def test_a_swap_goes_on_where_the_heads_are_still_close():
    """Jaws swapped for 7 frames: 4 far from the other tool's wrist, then 3 where both
    lie near the middle (a swap of them gains between HEAD_SWAP_KEEP_MARGIN and
    HEAD_SWAP_MARGIN shaft widths, 60 px): the run goes back over those too. Held alone,
    such frames are no swap (held-out seed 0, two-tool seed 0: jaws kept swapped while
    they part)."""
    gain = 0.5 * (HEAD_SWAP_KEEP_MARGIN + HEAD_SWAP_MARGIN) * 60.0
    rows = []
    for f in range(12):
        near = 7 <= f < 10
        rows += _heads_meeting(f, ("clasper",) if 3 <= f < 10 else (), gain if near else None)
    out = swap_heads(_table(rows))
    for f in range(12):
        want = _table(_heads_meeting(f, (), gain if 7 <= f < 10 else None))
        for name in ("1", "2"):
            assert _part_xy(out, f, name, "clasper") == _part_xy(want, f, name, "clasper")
    near_only = []
    for f in range(12):
        near_only += _heads_meeting(f, ("clasper",) if 3 <= f < 10 else (), gain)
    table = _table(near_only)
    assert swap_heads(table) is table


def _head_on_the_other(
    frame: int, on_other: bool, wrist_xy: tuple[float, float] = (390.0, 300.0)
) -> list[dict[str, object]]:
    """:func:`_heads_apart`'s two tools; ``on_other``: tool 1's head is hidden and tool
    2's wrist (at ``wrist_xy``) and jaws carry name "1", name "2" showing its shaft
    alone."""
    rows = _heads_apart(frame, None)
    if not on_other:
        return rows
    rows = [r for r in rows if r["instrument"] == "1" and r["part"] == "shaft"]
    rows += [r for r in _heads_apart(frame, None) if r["instrument"] == "2"]
    for r in rows:
        if r["part"] == "wrist":
            r["cx_px"], r["cy_px"] = wrist_xy
        if r["part"] != "shaft":
            r["instrument"] = "1"
    return rows


def test_a_wrist_on_another_names_shaft_goes_to_it_with_its_jaws():
    """Tool 2's wrist and jaws named "1" for 6 frames (tool 1's own head hidden; held-out
    seed 6 frames 60-63: a name's wrist 200 px from its tool's, on the shaft of a name that
    shows none), through relink: they go to "2", whose shaft they hang on; the other
    frames are untouched."""
    rows = []
    for f in range(12):
        rows += _head_on_the_other(f, 3 <= f < 9)
    table = _table(rows)
    out = relink(table, 25.0)
    assert out.num_rows == table.num_rows
    for f in range(12):
        got = {
            (str(n), str(p))
            for g, n, p in zip(out["frame"], out["instrument"], out["part"], strict=True)
            if g == f
        }
        if 3 <= f < 9:
            assert got == {("1", "shaft"), ("2", "shaft"), ("2", "wrist"), ("2", "clasper")}
            assert _part_xy(out, f, "2", "wrist") == (390.0, 300.0)
        else:
            assert _part_xy(out, f, "1", "wrist") == _part_xy(table, f, "1", "wrist")
            assert len(got) == 6


def test_a_wrist_moved_for_two_frames_or_by_a_small_gain_is_left():
    """Fewer than HEAD_SWAP_MIN_FRAMES frames are no evidence; nor is a wrist that hangs
    on the other shaft better by at most HEAD_MOVE_MARGIN of its widths (here it lies
    between the shafts' ends, 40 px nearer "2"'s across their axes)."""
    short = _table(sum((_head_on_the_other(f, f in (3, 4)) for f in range(12)), []))
    assert move_heads(short) is short
    # "1"'s shaft ends at (300, 200) going right, "2"'s at (420, 300) going left: a wrist
    # at (360, 270) hangs on "1" at 70 + 0.5 * 60, on "2" at 30 + 0.5 * 60: a gain of 40
    rows = sum((_head_on_the_other(f, 3 <= f < 9, (360.0, 270.0)) for f in range(12)), [])
    moved = move_heads(_table(rows))  # 2's shaft 60 px wide: a margin of 30 px
    assert HEAD_MOVE_MARGIN * 60.0 < 40.0 <= HEAD_MOVE_MARGIN * 100.0
    assert _part_xy(moved, 5, "2", "wrist") == (360.0, 270.0)
    wide = [dict(r) for r in rows]
    for r in wide:
        if r["part"] == "shaft" and r["instrument"] == "2":
            r["width_px"] = 100.0  # a margin of 50 px: more than the gain
    table = _table(wide)
    assert move_heads(table) is table


def test_a_tool_with_its_own_wrist_keeps_it_when_the_other_shows_none():
    """Two tools apart, tool 2's head hidden for 6 frames (a crossing, an occluder): tool
    1's wrist hangs on its own shaft: nothing moves."""
    rows = []
    for f in range(12):
        rows += [
            r
            for r in _heads_apart(f, None)
            if not (3 <= f < 9 and r["instrument"] == "2" and r["part"] != "shaft")
        ]
    table = _table(rows)
    assert move_heads(table) is table
    assert relink(table, 25.0) is table


def test_nothing_to_relink_gives_the_table_back():
    rows = []
    for f in range(30):
        rows += _tool_from_right(f, "1", 400.0, 100.0)
        rows += [_row(f, "2", "shaft", 60.0, 400.0, 120.0, 40.0)]
    table = _table(rows)
    assert relink(table, 25.0) is table


def _from_right(x1: int, y: int) -> np.ndarray:
    """One tool from the right border along row ``y``: shaft from ``x1``, jaws before."""
    img = np.zeros(SHAPE, np.uint8)
    if x1 < SHAPE[1]:
        img[y - 20 : y + 20, x1:] = 10
        img[y - 8 : y + 8, max(0, x1 - 40) : x1] = 30
    return img


def test_track_relinks_a_tool_back_through_another_place():
    """End to end (``mistool.track`` refines with the relinking): a tool pulled out of
    the view, back 46 frames later with its shaft entering 150 px lower, has one name;
    the identity step alone gave it a second."""
    frames = [_from_right(x1, 200) for x1 in range(300, 720, 60)]
    frames += [_from_right(720, 200)] * 45
    frames += [_from_right(x1, 350) for x1 in range(700, 500, -20)]
    out = track(frames, MERGED, metric=False)
    assert set(out["instrument"]) == {"1"}


@pytest.mark.parametrize("seed", range(20))
def test_the_sparse_assignment_makes_the_dense_ones_pairs(seed):
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 9, size=2)
    cost = rng.uniform(0.0, 4.0, size=(n, m))
    cost[rng.uniform(size=(n, m)) < 0.4] = np.inf
    gate = 2.5
    pairs = [(i, j, float(cost[i, j])) for i in range(n) for j in range(m) if cost[i, j] <= gate]
    got = sparse_gated_assignment(pairs, int(n), int(m), gate)
    want = gated_assignment(cost, gate)

    def total(ps: list[tuple[int, int]]) -> float:
        return sum(cost[i, j] for i, j in ps) + gate * (n + m - 2 * len(ps))

    assert total(got) == pytest.approx(total(want))
    assert all(cost[i, j] <= gate for i, j in got)


def test_a_long_sequence_of_many_tracklets_is_relinked():
    """An hour-long table's tracklets are too many for one dense assignment: four tools,
    each unseen for two frames every 40 (a blob) and renamed after each gap by the
    identity step (the worst case), 20,000 frames: every tool gets one name back."""
    ys = (80.0, 200.0, 320.0, 440.0)
    n = 20_000
    frame = np.repeat(np.arange(n), 4)
    tool = np.tile(np.arange(4), n)
    seen = (frame % 40) < 38
    frame, tool = frame[seen], tool[seen]
    name = (frame // 40) * 4 + tool + 1  # a new name after every gap
    cx = np.full(len(frame), 600.0)
    cy = np.array(ys)[tool]
    cols: dict[str, object] = dict(
        frame=frame,
        instrument=name.astype(str).astype(object),
        part=np.full(len(frame), "shaft", dtype=object),
        cx_px=cx,
        cy_px=cy,
        length_px=np.full(len(frame), 240.0),
        width_px=np.full(len(frame), 40.0),
        angle_deg=np.zeros(len(frame)),
        area_px=np.full(len(frame), 9600.0),
    )
    for k, (sx, sy) in enumerate(((-1, -1), (1, -1), (1, 1), (-1, 1)), 1):
        cols[f"x{k}_px"] = cx + sx * 120.0
        cols[f"y{k}_px"] = cy + sy * 20.0
    out = relink(TrackTable(cols), 25.0)
    assert sorted(set(out["instrument"])) == ["1", "2", "3", "4"]
    by_tool = {(str(i), float(y)) for i, y in zip(out["instrument"], out["cy_px"], strict=True)}
    assert len(by_tool) == 4
