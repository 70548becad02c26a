"""The data model: canonical rotated boxes and the track table."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mistool.errors import TableError
from mistool.model import COLUMN_NAMES, RotatedBox, TrackTable, empty_table, require_columns


def _shoelace(c: np.ndarray) -> float:
    x, y = c[:, 0], c[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@pytest.mark.parametrize("angle", [0.0, 30.0, 89.9, 90.0, 135.0, 179.9])
def test_box_corners(angle: float) -> None:
    box = RotatedBox(cx=10.0, cy=-4.0, length=8.0, width=2.0, angle_deg=angle)
    c = box.corners()
    assert c.shape == (4, 2) and c.dtype == np.float64
    np.testing.assert_allclose(c.mean(axis=0), [10.0, -4.0], atol=1e-12)
    assert _shoelace(c) == pytest.approx(16.0)
    edge = c[1] - c[0]  # the first edge runs along the long side, in the box's direction
    assert np.hypot(*edge) == pytest.approx(8.0)
    assert math.degrees(math.atan2(edge[1], edge[0])) % 180.0 == pytest.approx(angle)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"length": 1.0, "width": 2.0, "angle_deg": 0.0},
        {"length": 2.0, "width": 1.0, "angle_deg": 180.0},
        {"length": 2.0, "width": 1.0, "angle_deg": -0.1},
    ],
)
def test_box_rejects_non_canonical(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        RotatedBox(cx=0.0, cy=0.0, **kwargs)


def _table() -> TrackTable:
    return TrackTable(
        {
            "part": ["clasper", "shaft", "shaft", "wrist"],
            "frame": [1, 1, 0, 1],
            "instrument": ["b", "b", "a", "a"],
            "cx_px": [1.0, 2.0, 3.0, 4.0],
            "extra": [9, 8, 7, 6],
        }
    )


def test_table_columns_keep_the_fixed_order() -> None:
    t = _table()
    assert t.columns == ("frame", "instrument", "part", "cx_px", "extra")
    assert t.num_rows == 4 and t["frame"].dtype == np.int64
    assert t["instrument"].dtype == object
    assert np.isnan(t["end_z_mm"]).all() and len(t["end_z_mm"]) == 4  # known, absent
    with pytest.raises(KeyError):
        t["nope"]


def test_table_selection_sort_concat_groups() -> None:
    t = _table()
    s = t.sorted()
    assert s["frame"].tolist() == [0, 1, 1, 1]
    assert list(zip(s["instrument"], s["part"], strict=True))[1:] == [
        ("a", "wrist"),
        ("b", "shaft"),
        ("b", "clasper"),
    ]
    assert t[t["frame"] == 1].num_rows == 3 and t[1:3]["cx_px"].tolist() == [2.0, 3.0]
    c = TrackTable.concat(
        [t, TrackTable({"frame": [5], "instrument": ["c"], "part": ["shaft"], "dz": [0.5]})]
    )
    assert c.num_rows == 5 and np.isnan(c["cx_px"][4]) and np.isnan(c["dz"][0])
    assert c["dz"][4] == 0.5
    groups = dict(t.groups("instrument"))
    assert groups[("b",)].tolist() == [0, 1] and groups[("a",)].tolist() == [2, 3]


def test_table_validation() -> None:
    with pytest.raises(TableError, match="has 1 rows, expected 2"):
        TrackTable({"frame": [0, 1], "instrument": ["a"], "part": ["shaft", "shaft"]})
    with pytest.raises(TableError, match="needs a 'part' column"):
        TrackTable({"frame": [0], "instrument": ["a"]})
    with pytest.raises(TableError, match="missing column"):
        require_columns(_table(), ["frame", "dz"], "x.csv")


def test_empty_table_is_typed_and_full() -> None:
    e = empty_table()
    assert e.num_rows == 0 and e.columns == COLUMN_NAMES
    assert e["frame"].dtype == np.int64 and e["cx_px"].dtype == np.float64
    assert e.sorted().num_rows == 0 and TrackTable().full().columns == COLUMN_NAMES
    assert TrackTable.concat([]).num_rows == 0
