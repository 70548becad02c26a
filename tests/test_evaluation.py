"""mistool.evaluation: zero error on the truth, known shifts recovered, matching, coverage."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from mistool.errors import TableError
from mistool.evaluation import (
    evaluate,
    format_report,
    identity_coverage,
    linear_assignment,
    match_instruments,
)
from mistool.model import TrackTable


def _truth(frames: int = 20) -> TrackTable:
    """Two instruments, shaft + clasper, moving on known paths."""
    rows: dict[str, list] = {
        k: []
        for k in (
            "frame",
            "instrument",
            "part",
            "cx_px",
            "cy_px",
            "angle_deg",
            "area_px",
            "end_x_mm",
            "end_y_mm",
            "end_z_mm",
            "axis_x",
            "axis_y",
            "axis_z",
        )
    }
    for f in range(frames):
        for inst, x0 in (("1", 150.0), ("2", 550.0)):
            for part, dy in (("shaft", 0.0), ("clasper", 60.0)):
                ang = (170.0 + 3 * f) % 180.0
                a = np.array([math.cos(0.1 * f), math.sin(0.1 * f), 1.0]) / math.sqrt(2)
                vals = (
                    f,
                    inst,
                    part,
                    x0 + 5 * f,
                    200.0 + dy + 2 * f,
                    ang,
                    500.0,
                    x0 / 10 + f,
                    3.0 * f,
                    90.0 + f,
                    *a,
                )
                for k, v in zip(rows, vals, strict=True):
                    rows[k].append(v)
    return TrackTable(rows)


def test_truth_against_itself_is_exact():
    t = _truth()
    rep = evaluate({"self": t}, t)
    for part in ("shaft", "clasper"):
        s = rep.methods[0].parts[part]
        assert s["coverage"] == 1.0 and s["metric_coverage"] == 1.0 and s["extra"] == 0
        for key in ("x_px", "y_px", "theta_deg", "x_mm", "y_mm", "z_mm", "end_mm"):
            assert s[key]["mean"] == 0.0 and s[key]["sd"] == 0.0
        assert s["axis_deg"]["p90"] == pytest.approx(0.0, abs=1e-5)
    assert rep.methods[0].instrument_map == {"1": "1", "2": "2"}


def test_known_shift_is_recovered_with_renamed_instruments():
    t = _truth()
    rename = np.array(["B" if i == "1" else "A" for i in t["instrument"]], dtype=object)
    rot = math.radians(4.0)  # turn every axis by 4 degrees about the camera z axis
    ax, ay = t["axis_x"], t["axis_y"]
    p = t.with_columns(
        instrument=rename,
        cx_px=t["cx_px"] + 3.0,
        cy_px=t["cy_px"] - 2.0,
        angle_deg=(t["angle_deg"] + 15.0) % 180.0,  # wraps past 180
        end_z_mm=t["end_z_mm"] + 1.25,
        axis_x=ax * math.cos(rot) - ay * math.sin(rot),
        axis_y=ax * math.sin(rot) + ay * math.cos(rot),
    )
    rep = evaluate({"shifted": p}, t)
    m = rep.methods[0]
    assert m.instrument_map == {"B": "1", "A": "2"}
    for part in ("shaft", "clasper"):
        s = m.parts[part]
        assert s["x_px"]["mean"] == pytest.approx(3.0)
        assert s["y_px"]["mean"] == pytest.approx(2.0)
        assert s["theta_deg"]["mean"] == pytest.approx(15.0)
        assert s["theta_deg"]["sd"] == pytest.approx(0.0, abs=1e-9)
        assert s["z_mm"]["mean"] == pytest.approx(1.25)
        assert s["x_mm"]["mean"] == 0.0
        # the xy part of each axis has length 1/sqrt(2): its 4 degree turn moves the
        # axis by 2 asin(sin(2 deg) / sqrt(2)) in 3D
        expect = math.degrees(2 * math.asin(math.sin(math.radians(2.0)) / math.sqrt(2)))
        assert s["axis_deg"]["median"] == pytest.approx(expect, abs=1e-4)


@pytest.mark.parametrize(
    "truth_deg,pred_deg,err",
    [
        (179.0, 1.0, 2.0),
        (0.0, 179.5, 0.5),
        (90.0, 0.0, 90.0),
        (45.0, 135.0, 90.0),
        (10.0, 10.0, 0.0),
    ],
)
def test_angle_error_is_modulo_180(truth_deg, pred_deg, err):
    base = {"frame": [0], "instrument": ["1"], "part": ["shaft"], "cx_px": [1.0], "cy_px": [1.0]}
    t = TrackTable({**base, "angle_deg": [truth_deg]})
    p = TrackTable({**base, "angle_deg": [pred_deg]})
    s = evaluate({"p": p}, t).methods[0].parts["shaft"]
    assert s["theta_deg"]["mean"] == pytest.approx(err)


def test_coverage_counts_missing_rows_and_extra_rows():
    t = _truth(10)
    keep = ~((t["instrument"] == "1") & (t["part"] == "clasper") & (t["frame"] < 4))
    p = t[keep]
    extra = TrackTable(
        {
            "frame": [99],
            "instrument": ["1"],
            "part": ["shaft"],
            "cx_px": [0.0],
            "cy_px": [0.0],
            "angle_deg": [0.0],
        }
    )
    p = TrackTable.concat([p, extra])
    s = evaluate({"p": p}, t).methods[0].parts
    assert s["clasper"]["coverage"] == pytest.approx(16 / 20)
    assert s["shaft"]["coverage"] == 1.0 and s["shaft"]["extra"] == 1
    assert s["shaft"]["metric_coverage"] == 1.0  # the extra row has no truth row


def test_metric_coverage_ignores_rows_without_an_estimate():
    t = _truth(10)
    p = t.with_columns(end_x_mm=np.where(t["frame"] < 5, np.nan, t["end_x_mm"]))
    s = evaluate({"p": p}, t).methods[0].parts["shaft"]
    assert s["coverage"] == 1.0 and s["metric_coverage"] == 0.5
    assert s["x_mm"]["n"] == 10


def test_small_truth_rows_are_left_out():
    t = _truth(4)
    t = t.with_columns(area_px=np.where(t["frame"] == 0, 5.0, 500.0))
    p = t[t["frame"] > 0]
    s = evaluate({"p": p}, t, min_area_px=20).methods[0].parts["shaft"]
    assert s["n_truth"] == 6 and s["coverage"] == 1.0
    s = evaluate({"p": p}, t, min_area_px=0).methods[0].parts["shaft"]
    assert s["coverage"] == pytest.approx(6 / 8)


def test_side_by_side_report_lists_every_method_and_the_mapping():
    t = _truth(5)
    p = t.with_columns(cx_px=t["cx_px"] + 1.0)
    rep = evaluate({"paper": t, "metric": p}, t)
    text = format_report(rep)
    assert "Table 1" in text and "Table 2" in text
    assert text.count("paper") >= 3 and text.count("metric") >= 3
    assert "1.00 ± 0.00" in text
    per = rep.per_frame()
    assert per.num_rows == 2 * t.num_rows
    assert set(per["method"]) == {"paper", "metric"}
    d = rep.to_dict()
    assert d["methods"][1]["parts"]["shaft"]["x_px"]["mean"] == 1.0


def test_unmatchable_prediction_scores_zero_coverage():
    t = _truth(3)
    p = TrackTable(
        {
            "frame": [50],
            "instrument": ["x"],
            "part": ["shaft"],
            "cx_px": [1.0],
            "cy_px": [2.0],
            "angle_deg": [0.0],
        }
    )
    m = evaluate({"p": p}, t).methods[0]
    assert m.instrument_map == {}
    assert m.parts["shaft"]["coverage"] == 0.0 and m.parts["shaft"]["extra"] == 1
    assert "-" in format_report(evaluate({"p": p}, t))
    with pytest.raises(TableError):
        evaluate({}, t)
    with pytest.raises(TableError):
        evaluate({"p": p}, t[t["frame"] < 0])


def test_identity_switch_is_not_hidden_by_matching():
    t = _truth(10)
    inst = t["instrument"].copy()
    late = t["frame"] >= 5
    inst[late] = np.where(inst[late] == "1", "2", "1")  # ids swap half-way
    m = evaluate({"p": t.with_columns(instrument=inst)}, t).methods[0]
    assert m.parts["shaft"]["x_px"]["mean"] > 100  # half the rows are 400 px off


@pytest.mark.parametrize("shape", [(3, 3), (2, 5), (5, 2), (4, 4), (1, 3), (6, 6)])
def test_linear_assignment_matches_brute_force(shape):
    rng = np.random.default_rng(sum(shape))
    for _ in range(20):
        cost = rng.uniform(0, 10, shape)
        pairs = linear_assignment(cost)
        assert len(pairs) == min(shape)
        n, m = shape
        if n <= m:
            best = min(
                sum(cost[i, c] for i, c in enumerate(cols))
                for cols in itertools.permutations(range(m), n)
            )
        else:
            best = min(
                sum(cost[r, j] for j, r in enumerate(rows))
                for rows in itertools.permutations(range(n), m)
            )
        assert sum(cost[i, j] for i, j in pairs) == pytest.approx(best)


def test_match_instruments_by_nearest_boxes():
    t = _truth(5)
    inst = np.array(["left" if i == "1" else "right" for i in t["instrument"]], dtype=object)
    assert match_instruments(t.with_columns(instrument=inst), t) == {"left": "1", "right": "2"}


def test_a_new_identity_after_a_gap_is_a_fragment_of_the_same_tool():
    t = _truth(10)
    inst = t["instrument"].copy()
    inst[(inst == "1") & (t["frame"] >= 6)] = "7"  # the tracker renamed tool 1 at frame 6
    m = evaluate({"p": t.with_columns(instrument=inst)}, t).methods[0]
    assert m.instrument_map == {"1": "1", "2": "2", "7": "1"} and m.fragments == 1
    assert m.parts["shaft"]["coverage"] == 1.0 and m.parts["shaft"]["x_px"]["mean"] == 0.0
    assert "1 fragment(s)" in format_report(evaluate({"p": t.with_columns(instrument=inst)}, t))
    # a left-over instrument that overlaps in time with the matched one is not merged in
    dup = TrackTable.concat(
        [t, t[t["instrument"] == "1"].with_columns(instrument=np.array(["9"] * 20, dtype=object))]
    )
    m = evaluate({"p": dup}, t).methods[0]
    assert "9" not in m.instrument_map and m.parts["shaft"]["extra"] == 10


def test_identity_coverage_is_strict_one_to_one():
    t = _truth(10)  # 2 tools x 2 parts x 10 frames, every row visible
    exact = identity_coverage(t, t)
    assert exact.coverage == 1.0 and exact.parts == {"shaft": 1.0, "clasper": 1.0}
    assert (exact.names, exact.true_names) == (2, 2)
    inst = t["instrument"].copy()
    inst[(inst == "1") & (t["frame"] >= 6)] = "7"  # tool 1 renamed at frame 6: 4 frames lost
    renamed = identity_coverage(t.with_columns(instrument=inst), t)
    assert renamed.coverage == pytest.approx(1 - 4 * 2 / 40) and renamed.names == 3
    # the lenient evaluation joins the fragment back and counts every row
    assert evaluate({"p": t.with_columns(instrument=inst)}, t).methods[0].fragments == 1
    swapped = t["instrument"].copy()
    late = t["frame"] >= 7
    swapped[late] = np.where(swapped[late] == "1", "2", "1")  # names swap for 3 frames
    got = identity_coverage(t.with_columns(instrument=swapped), t)
    assert got.coverage == pytest.approx(0.7) and got.parts["shaft"] == pytest.approx(0.7)
    small = identity_coverage(t, t.with_columns(area_px=np.where(late, 5.0, 500.0)))
    assert small.coverage == 1.0  # rows below min_area_px are left out, not missed


def test_identity_coverage_among_the_rows_visible_in_the_masks():
    t = _truth(10)  # 40 rows; tool 2's clasper hidden in the masks in frames 0-4
    hidden = (t["instrument"] == "2") & (t["part"] == "clasper") & (t["frame"] < 5)
    truth = t.with_columns(mask_area_px=np.where(hidden, 0.0, t["area_px"]))
    pred = t[~hidden]  # the tracker finds every visible row, nothing else
    got = identity_coverage(pred, truth)
    assert got.coverage == pytest.approx(35 / 40) and got.ceiling == pytest.approx(35 / 40)
    assert got.visible == 1.0
    late = pred["frame"] >= 8  # names swapped in the last 2 frames: 8 visible rows lost
    names = pred["instrument"].copy()
    names[late] = np.where(names[late] == "1", "2", "1")
    got = identity_coverage(pred.with_columns(instrument=names), truth)
    assert got.visible == pytest.approx(27 / 35) and got.coverage == pytest.approx(27 / 40)
    assert math.isnan(identity_coverage(t, t).visible)  # no mask_area_px: unknown


def test_identity_coverage_of_nothing_found():
    t = _truth(4)
    got = identity_coverage(t[t["frame"] < 0], t)
    assert got.coverage == 0.0 and got.names == 0 and got.parts["shaft"] == 0.0


def test_tag_run_stacks_runs_without_collisions() -> None:
    from mistool.evaluation import RUN_FRAME_STRIDE, tag_run

    t = TrackTable(
        {
            "frame": np.array([0, 3]),
            "instrument": np.array(["1", "2"], dtype=object),
            "part": np.array(["shaft", "shaft"], dtype=object),
        }
    )
    a, b = tag_run(t, 0), tag_run(t, 7)
    assert list(a["frame"]) == [0, 3] and list(a["instrument"]) == ["0:1", "0:2"]
    assert list(b["frame"]) == [7 * RUN_FRAME_STRIDE, 7 * RUN_FRAME_STRIDE + 3]
    assert list(b["instrument"]) == ["7:1", "7:2"]
    both = TrackTable.concat([a, b])
    keys = set(zip(both["frame"], both["instrument"], strict=True))
    assert len(keys) == 4
    with pytest.raises(ValueError, match="frame_stride"):
        tag_run(t, 1, frame_stride=3)


def test_paper_3d_oracle_back_projects_a_depth_proportional_to_paper_z() -> None:
    from mistool.evaluation import paper_3d_oracle

    fx, fy, cx, cy = 500.0, 400.0, 320.0, 240.0
    end = np.array([[10.0, 5.0, 100.0], [-20.0, 3.0, 80.0], [4.0, -6.0, 120.0]])
    axis = np.array([[-1.0, 0.0, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])
    n = len(end)
    common = {
        "frame": np.arange(n),
        "instrument": np.array(["a"] * n, dtype=object),
        "part": np.array(["shaft"] * n, dtype=object),
        "cx_px": fx * end[:, 0] / end[:, 2] + cx,
        "cy_px": fy * end[:, 1] / end[:, 2] + cy,
    }
    truth = TrackTable(
        {
            **common,
            "end_x_mm": end[:, 0],
            "end_y_mm": end[:, 1],
            "end_z_mm": end[:, 2],
            "axis_x": axis[:, 0],
            "axis_y": axis[:, 1],
            "axis_z": axis[:, 2],
        }
    )
    pred = TrackTable(
        {
            **common,
            "instrument": np.array(["7"] * n, dtype=object),
            "paper_z": 0.25 * end[:, 2],  # proportional to depth: the oracle's scale is exact
            "paper_x_px": common["cx_px"],
            "paper_y_px": common["cy_px"],
            "angle_deg": np.array([30.0, 45.0, 120.0]),
        }
    )
    out = paper_3d_oracle(pred, truth, fx, fy, cx, cy)
    got = np.stack([out["end_x_mm"], out["end_y_mm"], out["end_z_mm"]], axis=1)
    np.testing.assert_allclose(got, end, rtol=1e-12)
    ax = np.stack([out["axis_x"], out["axis_y"], out["axis_z"]], axis=1)
    np.testing.assert_allclose(np.linalg.norm(ax, axis=1), 1.0)
    assert np.all(ax[:, 2] == 0)  # the box's long side, in the image plane
    assert np.all(np.sum(ax * axis, axis=1) >= 0)  # the truth's sign (the oracle)
    np.testing.assert_allclose(np.abs(ax[0]), [math.cos(math.radians(30)), 0.5, 0], atol=1e-12)


def test_identity_coverage_among_detected_rows():
    t = _truth(10)
    hidden = (t["instrument"] == "2") & (t["part"] == "clasper") & (t["frame"] >= 5)
    pred = t[~hidden]  # tool 2's clasper hidden in the masks for 5 frames: not detected
    got = identity_coverage(pred, t)
    assert got.coverage == pytest.approx(35 / 40) and got.detected == 1.0
    inst = pred["instrument"].copy()
    late = pred["frame"] >= 8
    inst[late] = np.where(inst[late] == "1", "2", "1")  # names swap in the last 2 frames
    got = identity_coverage(pred.with_columns(instrument=inst), t)
    # 35 rows detected (the swapped rows are still near a tool), 35 - 2 x 3 right
    assert got.detected == pytest.approx(29 / 35)
