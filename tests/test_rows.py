"""RowBuilder: rows in growing numpy columns, metric columns appearing late, take()."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mistool.model import RotatedBox
from mistool.rows import BASE_COLUMNS, INITIAL_ROWS, RowBuilder


@dataclass
class _Obs:
    box: RotatedBox
    corners: np.ndarray
    area_px: int


@dataclass
class _Inst:
    parts: dict[str, _Obs] = field(default_factory=dict)


def _inst(i: int, parts: tuple[str, ...] = ("shaft", "clasper")) -> _Inst:
    box = RotatedBox(10.0 + i, 20.0, 30.0, 8.0, 45.0)
    return _Inst({p: _Obs(box, box.corners() + k, 100 + i) for k, p in enumerate(parts)})


def test_rows_grow_past_the_initial_capacity_and_keep_every_value() -> None:
    rows = RowBuilder(fps=10.0)
    n = INITIAL_ROWS * 3
    for i in range(n):  # parts given distal first: rows still come proximal to distal
        rows.add_frame(i, ["a", "b"], [_inst(i, ("clasper", "shaft")), _inst(-i)], [None, None])
    assert rows.num_rows == 4 * n
    t = rows.take()
    assert t.columns == BASE_COLUMNS and t.num_rows == 4 * n and rows.num_rows == 0
    assert t["frame"].dtype == np.int64 and t["frame"][-1] == n - 1
    np.testing.assert_array_equal(t["time_s"][:4], [0.0] * 4)
    assert t["time_s"][-1] == (n - 1) / 10.0
    assert t["instrument"].tolist()[:4] == ["a", "a", "b", "b"]
    assert t["part"].tolist()[:4] == ["shaft", "clasper", "shaft", "clasper"]
    last = _inst(n - 1, ("clasper", "shaft"))  # the clasper got offset 0 there
    assert t["cx_px"][-4] == last.parts["shaft"].box.cx
    assert t["area_px"][-1] == 100 - (n - 1)
    np.testing.assert_array_equal(
        [t[f"{a}{k}_px"][-3] for k in range(1, 5) for a in "xy"],
        (last.parts["clasper"].corners).ravel(),
    )


def test_metric_columns_appear_late_with_nan_and_empty_text_before() -> None:
    rows = RowBuilder(fps=25.0)
    rows.add_frame(0, ["1"], [_inst(0)], [None])
    metric = {"shaft": {"end_x_mm": 1.5, "quality": None, "pose_status": "ok"}}
    rows.add_frame(1, ["1"], [_inst(1)], [metric])
    t = rows.take()
    assert t.num_rows == 4
    assert math.isnan(t["end_x_mm"][0]) and t["end_x_mm"][2] == 1.5
    assert np.isnan(t["quality"]).all()
    assert t["pose_status"].tolist() == ["", "", "ok", ""]
    rows.add_frame(2, ["1"], [_inst(2)], [None])
    again = rows.take()  # emptied, and no value of the earlier rows leaks in
    assert again["frame"].tolist() == [2, 2] and np.isnan(again["end_x_mm"]).all()
    assert again["pose_status"].tolist() == ["", ""]
