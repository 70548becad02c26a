"""Motion tables as columnar files (``.npz``, ``.parquet``) besides the CSV contract.

- ``.npz``: numpy's own zip of arrays (no new dependency); every column exact (float64
  bit for bit, where the CSV keeps 6 decimals); text columns as fixed-width unicode
  arrays, so reading never unpickles anything (``allow_pickle=False``). The column order
  is stored in the ``__columns__`` array.
- ``.parquet``: needs ``pyarrow`` (``pip install "mistool[parquet]"``); one row group per
  table, NaN kept as NaN (an unknown estimate), text columns as strings.

:func:`write_table` and :func:`read_table` choose the format by the file's suffix
(``.csv``, ``.npz``, ``.parquet``); writing is atomic (a temporary file renamed), and
every known column is written, as in the CSV (:meth:`~mistool.model.TrackTable.full`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from mistool.errors import ConfigError, InputPathError, TableError
from mistool.export import atomic_write, read_csv, write_csv
from mistool.model import TrackTable, require_columns

#: The output formats, by file suffix.
FORMATS: tuple[str, ...] = (".csv", ".npz", ".parquet")

_ORDER_KEY = "__columns__"
_REQUIRED = ("frame", "instrument", "part")


def table_format(path: str | Path) -> str:
    """The format of ``path`` by its suffix: ``".csv"``, ``".npz"`` or ``".parquet"``.

    Raises:
        ConfigError: another suffix.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ConfigError(
            f"{path}: unknown table format {suffix or '(no suffix)'!r}; "
            f"use one of {', '.join(FORMATS)}"
        )
    return suffix


def _pyarrow() -> tuple[Any, Any]:
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ModuleNotFoundError:
        raise ConfigError(
            '.parquet output needs pyarrow: pip install "mistool[parquet]" (or use .npz/.csv)'
        ) from None
    return pa, pq


def _text(values: np.ndarray) -> np.ndarray:
    return np.asarray([str(v) for v in values], dtype=str) if len(values) else np.zeros(0, "U1")


def write_table(table: TrackTable, path: str | Path) -> Path:
    """Write a motion table to ``path`` atomically, in the format of its suffix."""
    fmt = table_format(path)
    if fmt == ".csv":
        return write_csv(table, path)
    full = table.full()
    if fmt == ".npz":
        arrays = {c: (_text(v) if v.dtype == object else v) for c, v in full.items()}
        arrays[_ORDER_KEY] = np.asarray(list(full.columns), dtype=str)
        savez: Any = np.savez  # (numpy's stub reads **arrays as its allow_pickle flag)
        with atomic_write(path, "wb") as f:
            savez(f, **arrays)
        return Path(path)
    pa, pq = _pyarrow()
    data = {c: (v.tolist() if v.dtype == object else v) for c, v in full.items()}
    with atomic_write(path, "wb") as f:
        pq.write_table(pa.table(data), f)
    return Path(path)


def read_table(path: str | Path) -> TrackTable:
    """Read a motion table written by mistool (CSV, ``.npz`` or ``.parquet``).

    Raises:
        InputPathError: no such file.
        TableError: not a readable table of that format, or the contract's key columns
            (frame, instrument, part) are missing.
    """
    p = Path(path)
    fmt = table_format(p)
    if fmt == ".csv":
        return read_csv(p)
    if not p.is_file():
        raise InputPathError(f"{p}: no such file")
    columns: dict[str, Any] = {}
    if fmt == ".npz":
        try:
            with np.load(p, allow_pickle=False) as z:
                order = [str(c) for c in z[_ORDER_KEY]] if _ORDER_KEY in z else list(z.files)
                for c in order:
                    v = z[c]
                    columns[c] = v.astype(object) if v.dtype.kind == "U" else v
        except (OSError, ValueError, KeyError) as exc:
            raise TableError(f"{p}: cannot read as a mistool .npz table: {exc}") from None
    else:
        _, pq = _pyarrow()
        try:
            t = pq.read_table(p)
        except (OSError, ValueError) as exc:  # pyarrow's errors derive from these
            raise TableError(f"{p}: cannot read as a Parquet table: {exc}") from None
        for c in t.column_names:
            col = t.column(c).to_numpy(zero_copy_only=False)
            columns[c] = col.astype(object) if col.dtype == object else col
    require_columns(columns, _REQUIRED, str(p))
    try:
        return TrackTable(columns)
    except TableError as exc:
        raise TableError(f"{p}: {exc}") from None


def read_any(path: str | Path) -> TrackTable:
    """:func:`read_table` for ``.npz`` and ``.parquet`` files, the CSV reader for any
    other name (a motion table with another suffix is read as CSV, as before)."""
    if Path(path).suffix.lower() in (".npz", ".parquet"):
        return read_table(path)
    return read_csv(path)
