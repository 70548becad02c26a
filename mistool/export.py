"""Writing and reading motion tables (CSV) and writing any output file atomically.

CSV format: a header row with the column names in :data:`mistool.model.COLUMNS` order
(extras after), one row per (frame, instrument, part); NaN is written as an empty cell;
floats with at most 6 decimals, trailing zeros dropped.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from mistool.errors import InputPathError, TableError
from mistool.model import COLUMN_DTYPES, TrackTable, require_columns


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", **kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on success rename it over ``path``.

    On any exception the temporary file is removed and ``path`` is left untouched, so a
    failed command never leaves partial output.
    """
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    if not directory.is_dir():
        raise InputPathError(f"{target}: output folder {directory} does not exist")
    if target.is_dir():
        raise InputPathError(f"{target}: is a folder; expected an output file name")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise InputPathError(
            f"{target}: cannot write in {directory}: {exc.strerror or exc}"
        ) from None
    try:
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        try:
            os.replace(tmp, target)
        except OSError as exc:
            raise InputPathError(f"{target}: cannot write: {exc.strerror or exc}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def format_value(value: Any) -> str:
    """One CSV cell: NaN/None -> '', floats to <= 6 decimals without trailing zeros."""
    if value is None:
        return ""
    if isinstance(value, (float, np.floating)):
        if not math.isfinite(value):
            return "" if math.isnan(value) else ("inf" if value > 0 else "-inf")
        text = f"{float(value):.6f}".rstrip("0").rstrip(".")
        return "0" if text in ("-0", "") else text
    if isinstance(value, (np.integer, int)):
        return str(int(value))
    return str(value)


def table_to_csv_text(table: TrackTable) -> str:
    """The CSV text of a table (header + rows)."""
    buf = io.StringIO()
    write_table_csv(table, buf)
    return buf.getvalue()


def write_table_csv(table: TrackTable, out: IO[str]) -> None:
    """Write ``table`` as CSV to an open text stream."""
    names = list(table.columns)
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(names)
    cols = [table[c] for c in names]
    for i in range(table.num_rows):
        writer.writerow([format_value(col[i]) for col in cols])


def write_csv(table: TrackTable, path: str | Path) -> Path:
    """Write a motion table to ``path`` atomically, with every known column."""
    full = table.full()
    with atomic_write(path, "w", newline="", encoding="utf-8") as f:
        write_table_csv(full, f)
    return Path(path)


def read_csv(
    path: str | Path,
    required: tuple[str, ...] = ("frame", "instrument", "part"),
) -> TrackTable:
    """Read a motion table written by mistool (or any CSV with the contract columns).

    Known columns get their dtypes; extra columns are numeric when every cell parses as a
    number (empty cells -> NaN), text otherwise.
    """
    p = Path(path)
    if not p.is_file():
        raise InputPathError(f"{p}: no such file")
    try:
        with p.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as exc:
        raise TableError(f"{p}: cannot read as a CSV text file: {exc}") from None
    if not rows:
        raise TableError(
            f"{p}: empty file; expected a header row with frame, instrument, part, ..."
        )
    header, body = rows[0], rows[1:]
    require_columns({h: None for h in header}, required, str(p))
    for lineno, row in enumerate(body, start=2):
        if len(row) != len(header):
            raise TableError(f"{p}: line {lineno} has {len(row)} cells, header has {len(header)}")
    columns: dict[str, Any] = {}
    for j, name in enumerate(header):
        cells = [row[j] for row in body]
        dtype = COLUMN_DTYPES.get(name)
        if dtype is object:
            columns[name] = cells
            continue
        try:
            values = np.array(
                [float(c) if c.strip() != "" else np.nan for c in cells], dtype=np.float64
            )
        except ValueError:
            if dtype is not None:
                bad = next(i for i, c in enumerate(cells) if not _is_number(c))
                raise TableError(
                    f"{p}: line {bad + 2}, column {name!r}: expected a number, got {cells[bad]!r}"
                ) from None
            columns[name] = cells
            continue
        if dtype is np.int64:
            if np.isnan(values).any() or not np.all(values == np.round(values)):
                bad = int(np.flatnonzero(np.isnan(values) | (values != np.round(values)))[0])
                raise TableError(
                    f"{p}: line {bad + 2}, column {name!r}: expected an integer, got {cells[bad]!r}"
                )
            values = values.astype(np.int64)
        columns[name] = values
    return TrackTable(columns)


def _is_number(text: str) -> bool:
    if text.strip() == "":
        return True
    try:
        float(text)
    except ValueError:
        return False
    return True
