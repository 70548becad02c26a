"""CSV export: golden header and cell formatting, atomic writes, reading back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.errors import InputPathError, TableError
from mistool.export import atomic_write, format_value, read_csv, table_to_csv_text, write_csv
from mistool.model import CONTRACT_COLUMNS, TrackTable

# The motion table's header, written out by hand: changing the column order or a name is a
# breaking change for every user's scripts, so it must show up here as a failing test.
GOLDEN_HEADER = (
    "frame,time_s,instrument,part,cx_px,cy_px,length_px,width_px,angle_deg,area_px,"
    "x1_px,y1_px,x2_px,y2_px,x3_px,y3_px,x4_px,y4_px,dx_px,dy_px,dz,droll_deg,dpitch_deg,"
    "dyaw_deg,paper_x_px,paper_y_px,paper_z,paper_roll_deg,paper_pitch_deg,paper_yaw_deg,"
    "end_x_mm,end_y_mm,end_z_mm,axis_x,axis_y,axis_z,start_x_mm,start_y_mm,start_z_mm,"
    "qw,qx,qy,qz,quality,trocar_x_mm,trocar_y_mm,trocar_z_mm,pose_status"
)


def _table() -> TrackTable:
    return TrackTable(
        {
            "frame": [0, 0, 1],
            "instrument": ["1", "1", "2"],
            "part": ["shaft", "clasper", "shaft"],
            "cx_px": [10.5, 20.0, 1.0 / 3.0],
            "angle_deg": [0.0, 179.9999999, -0.0000001],
            "end_z_mm": [math.nan, 55.25, math.nan],
            "my_extra": [1.0, 2.0, 3.0],
        }
    )


def test_golden_header_and_rows(tmp_path: Path) -> None:
    out = write_csv(_table(), tmp_path / "m.csv")
    lines = out.read_text(encoding="utf-8").splitlines()
    assert lines[0] == GOLDEN_HEADER + ",my_extra"
    assert all(c in lines[0].split(",") for c in CONTRACT_COLUMNS)
    cells = dict(zip(lines[0].split(","), lines[1].split(","), strict=True))
    assert cells["frame"] == "0" and cells["instrument"] == "1" and cells["part"] == "shaft"
    assert cells["cx_px"] == "10.5" and cells["angle_deg"] == "0"
    assert cells["end_z_mm"] == "" and cells["dx_px"] == ""  # unknown: empty, never 0
    row3 = dict(zip(lines[0].split(","), lines[3].split(","), strict=True))
    assert row3["cx_px"] == "0.333333" and row3["angle_deg"] == "0"  # "-0" is written 0
    assert len(lines) == 4


@pytest.mark.parametrize(
    "value, text",
    [
        (1.0, "1"),
        (2.5, "2.5"),
        (1e-7, "0"),
        (-1e-7, "0"),
        (123456.1234567, "123456.123457"),
        (math.nan, ""),
        (None, ""),
        (math.inf, "inf"),
        (np.int64(7), "7"),
        ("a b", "a b"),
    ],
)
def test_format_value(value: object, text: str) -> None:
    assert format_value(value) == text


def test_round_trip(tmp_path: Path) -> None:
    table = _table()
    back = read_csv(write_csv(table, tmp_path / "m.csv"))
    assert back.num_rows == 3 and back["frame"].dtype == np.int64
    np.testing.assert_allclose(back["cx_px"], np.round(table["cx_px"], 6))
    assert np.isnan(back["end_z_mm"][0]) and back["end_z_mm"][1] == 55.25
    assert back["instrument"].tolist() == ["1", "1", "2"]
    assert table_to_csv_text(back.full()).splitlines()[0] == GOLDEN_HEADER + ",my_extra"


def test_atomic_write_leaves_nothing_on_error(tmp_path: Path) -> None:
    target = tmp_path / "out.csv"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(target) as f:
        f.write("partial")
        raise RuntimeError("boom")
    assert target.read_text() == "old"  # untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]  # no temp file left
    with atomic_write(target) as f:
        f.write("new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]


def test_atomic_write_missing_folder_or_folder_target(tmp_path: Path) -> None:
    with pytest.raises(InputPathError, match="does not exist"):
        write_csv(_table(), tmp_path / "nope" / "m.csv")
    (tmp_path / "dir").mkdir()
    with pytest.raises(InputPathError, match="is a folder"):
        write_csv(_table(), tmp_path / "dir")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty file"),
        ("frame,part\n0,shaft\n", "missing column.*instrument"),
        ("frame,instrument,part\n0,1\n", "line 2 has 2 cells"),
        ("frame,instrument,part,cx_px\n0,1,shaft,abc\n", "line 2, column 'cx_px'"),
        ("frame,instrument,part\n0.5,1,shaft\n", "expected an integer"),
    ],
)
def test_read_csv_errors(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(TableError, match=message):
        read_csv(path)


def test_read_csv_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputPathError, match="no such file"):
        read_csv(tmp_path / "none.csv")


def test_csv_blocks_write_the_same_text_as_cell_by_cell(monkeypatch: pytest.MonkeyPatch) -> None:
    """write_table_csv formats a block of rows per column; the text is format_value's."""
    import csv as csv_module
    import io

    from mistool import export

    vals = [float("nan"), float("inf"), -float("inf"), -0.0, 0.0, -1e-9, 5e-7, -5e-7, 1e300]
    vals += [123.4567895, 2.5, -7.0, 1 / 3]
    n = len(vals)
    table = TrackTable(
        {
            "frame": np.arange(n),
            "instrument": ["a,b"] * n,
            "part": ["shaft"] * n,
            "cx_px": np.array(vals),
            "count": np.arange(n, dtype=np.int32) - 5,
        }
    )
    expected = io.StringIO()
    writer = csv_module.writer(expected, lineterminator="\n")
    writer.writerow(table.columns)
    for i in range(n):
        writer.writerow([export.format_value(table[c][i]) for c in table.columns])
    monkeypatch.setattr(export, "CSV_BLOCK_ROWS", 4)  # blocks of 4 rows: 4 blocks
    assert export.table_to_csv_text(table) == expected.getvalue()


def _cell_by_cell(table: TrackTable) -> str:
    """The former writer: ``csv.writer`` over :func:`format_value` of every cell."""
    import csv as csv_module
    import io

    expected = io.StringIO()
    writer = csv_module.writer(expected, lineterminator="\n")
    writer.writerow(table.columns)
    for i in range(table.num_rows):
        writer.writerow([format_value(table[c][i]) for c in table.columns])
    return expected.getvalue()


_NAMES = ["1", "a,b", 'say "hi"', "two\nlines", "", "ünï", "tab\tx", "cr\r"]


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.floats(allow_nan=True, allow_infinity=True, width=64),
            st.floats(-1e4, 1e4),
            st.integers(-(10**12), 10**12).map(lambda k: k / 2**20),  # exact ties at 6 places
            st.integers(-(10**9), 10**9).map(lambda k: k / 10**6 + 5e-7),  # near-ties
        ),
        min_size=1,
        max_size=40,
    ),
    st.lists(st.integers(-(2**63), 2**63 - 1), min_size=40, max_size=40),
    st.lists(st.sampled_from(_NAMES), min_size=40, max_size=40),
)
def test_compiled_csv_rows_are_the_cell_by_cell_text(
    floats: list[float], ints: list[int], names: list[str]
) -> None:
    """Any float (NaN, infinities, -0, exact and near ties at the sixth decimal, huge
    ones left to Python), any int64, any text (commas, quotes, line breaks, non-ASCII):
    the compiled formatter writes what csv.writer over format_value wrote."""
    n = len(floats)
    table = TrackTable(
        {
            "frame": np.array(ints[:n], np.int64),
            "instrument": names[:n],
            "part": ["shaft"] * n,
            "cx_px": np.array(floats),
            "cy_px": -np.array(floats[::-1]),
            "count": np.array(ints[:n], np.int64) % 1000,
        }
    )
    assert table_to_csv_text(table) == _cell_by_cell(table)
