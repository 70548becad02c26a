"""The data model: canonical rotated boxes and the track table."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.errors import TableError
from mistool.model import (
    COLUMN_NAMES,
    RotatedBox,
    TrackTable,
    empty_table,
    group_rows,
    require_columns,
)


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


def _groups_by_dict(*columns: np.ndarray) -> list[tuple[tuple, list[int]]]:
    """The definition: a dict keyed by each row's values, in order of first row."""
    seen: dict[tuple, list[int]] = {}
    for i, key in enumerate(zip(*columns, strict=True)):
        seen.setdefault(tuple(key), []).append(i)
    return list(seen.items())


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.tuples(st.sampled_from(["1", "2", "10", "b"]), st.integers(-2, 3)), max_size=40),
    st.sampled_from(["object", "str", "float"]),
)
def test_group_rows_is_the_dict_definition(rows, kind) -> None:
    """``group_rows`` (np.unique on text, integer and boolean columns) gives the groups
    of a dict keyed by each row's values: the same keys (value and type), in order of
    first row, the rows in order; float columns (each NaN its own key) as the dict."""
    names = np.array([r[0] for r in rows], dtype=object if kind == "object" else str)
    values = np.array([r[1] for r in rows], dtype=np.int64)
    if kind == "float":
        values = np.where(values < 0, np.nan, values.astype(float))
    got = [(k, idx.tolist()) for k, idx in group_rows(names, values)]
    want = _groups_by_dict(names, values)
    assert [idx for _, idx in got] == [idx for _, idx in want]
    for (k, _), (w, _) in zip(got, want, strict=True):
        assert [type(v) for v in k] == [type(v) for v in w]
        assert all(a == b or (a != a and b != b) for a, b in zip(k, w, strict=True))
    assert all(x.dtype == np.int64 for _, x in group_rows(names, values))


def test_concat_and_selection_keep_the_constructors_order_and_types() -> None:
    """Tables joined or selected without converting their columns again have the
    columns, order and dtypes the constructor gives the same columns."""
    a = TrackTable({"frame": [0], "instrument": ["a"], "part": ["shaft"], "extra": [1.0]})
    b = TrackTable({"frame": [1], "instrument": ["b"], "part": ["wrist"], "cx_px": [2.0]})
    joined = TrackTable.concat([a, b])
    again = TrackTable({c: joined[c] for c in joined.columns})
    assert joined.columns == again.columns == ("frame", "instrument", "part", "cx_px", "extra")
    for c in joined.columns:
        assert joined[c].dtype == again[c].dtype
    assert joined["instrument"].tolist() == ["a", "b"] and np.isnan(joined["cx_px"][0])
    picked = joined[np.array([1])]
    assert picked.columns == joined.columns and picked["part"].tolist() == ["wrist"]
    with pytest.raises(TableError, match="expected a 1-D array"):
        joined[0]
    dropped = joined.without("extra", "not_there")
    assert dropped.columns == ("frame", "instrument", "part", "cx_px")
    assert dropped["cx_px"] is joined["cx_px"]
    with pytest.raises(TableError, match="needs a 'part' column"):
        joined.without("part")
