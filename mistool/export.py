"""Writing and reading motion tables (CSV) and writing any output file atomically.

CSV format: a header row with the column names in :data:`mistool.model.COLUMNS` order
(extras after), one row per (frame, instrument, part); NaN is written as an empty cell;
floats with at most 6 decimals, trailing zeros dropped.
"""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import itertools
import math
import os
import stat
import sys
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from mistool.errors import InputPathError, TableError
from mistool.model import COLUMN_DTYPES, TrackTable, require_columns

#: The output name that means standard output.
STDOUT = "-"
#: ``errno`` values of a write that failed for lack of room or a broken device: reported
#: as one line, the temporary file removed and the old output kept.
_WRITE_ERRNOS = frozenset(
    {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS, errno.ENXIO}
)
_umask_lock = threading.Lock()


def _kind(mode: int) -> str:
    """A file type in words (for messages about outputs that are not regular files)."""
    for test, name in (
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def _same_file(source: Path, target: Path, mine: tuple[int, int] | None) -> bool:
    """Whether the input ``source`` is the output file ``target`` (resolved; ``mine``:
    its ``(device, inode)``, None when it does not exist yet).

    An input that exists is the same file exactly when its ``(device, inode)`` (symlinks
    followed) is the output's: a symlink or a hard link to it included, and nothing
    that exists resolves to an output that does not. Only an input that cannot be
    stat'ed (a dangling symlink, say) is resolved, to see whether it names the output:
    one ``stat`` per input, not a path resolution (~40 us each, 0.06 s for 2,500
    frames before any work)."""
    try:
        st = os.stat(source)
    except (OSError, ValueError):
        return target == _resolved(source)
    return mine == (st.st_dev, st.st_ino)


def check_output(
    path: str | Path,
    inputs: Iterable[str | Path | None] = (),
    existing: Iterable[str | Path | os.DirEntry[str]] = (),
) -> Path:
    """Check, before any work, that ``path`` can receive a command's output.

    The output must be a regular file (or not exist yet) in an existing folder, and must
    not resolve to one of the command's ``inputs`` (frames, ``mistool.toml``, ``source``,
    calibration files, input tables; a folder in ``inputs`` stands for every file in it
    whose name is listed by the caller as an input, so pass files, not folders). Symlinks
    are followed: the returned path is the real file to replace, so that writing keeps
    the link itself. Hard links to an input are caught by comparing inodes.

    Args:
        path: the output path given by the user (not ``"-"``: the caller writes stdout).
        inputs: the command's input files (None entries are skipped).
        existing: more input files, that existed a moment ago (a folder's frames, as
            just listed): when the output does not exist, none of them can be it, and
            they are not looked at (one ``stat`` each otherwise). Given as the
            listing's ``os.DirEntry`` objects, one that is not a symlink is the output
            only if its inode number is the output's (no ``stat``; a file bind-mounted
            over a frame aside).

    Returns:
        The resolved output path (symlinks followed).

    Raises:
        InputPathError: the output would replace an input or a non-regular file, its
            folder does not exist, or its symlinks loop.
    """
    given = Path(path)
    if str(path) == "":
        raise InputPathError("output: empty file name")
    try:
        target = given.resolve()
    except RuntimeError:  # symlink loop (Python < 3.13)
        raise InputPathError(f"{given}: symlink loop; expected an output file name") from None
    except OSError as exc:
        raise InputPathError(f"{given}: cannot resolve: {exc.strerror or exc}") from None
    try:
        st = target.stat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise InputPathError(f"{given}: symlink loop; expected an output file name") from None
        raise InputPathError(f"{given}: cannot use as output: {exc.strerror or exc}") from None
    if st is not None and not stat.S_ISREG(st.st_mode):
        hint = " (use -o - for standard output)" if not stat.S_ISDIR(st.st_mode) else ""
        raise InputPathError(
            f"{given}: is {_kind(st.st_mode)}; mistool writes outputs only to regular files{hint}"
        )
    folder = target.parent
    if not folder.is_dir():
        raise InputPathError(f"{given}: output folder {given.parent} does not exist")
    mine = (st.st_dev, st.st_ino) if st is not None else None
    for item in itertools.chain(inputs, existing if mine is not None else ()):
        if item is None:
            continue
        if isinstance(item, os.DirEntry):
            # a listed file that is not a symlink: its inode number came with the listing
            # (~0.3 us against a stat's ~6: 15 ms for 2,500 frames when the output exists)
            if mine is not None and not item.is_symlink() and item.inode() != mine[1]:
                continue
            item = item.path
        source = Path(item)
        if _same_file(source, target, mine):
            raise InputPathError(
                f"{given}: is an input of this command ({source}); choose another output file name"
            )
    return target


def _resolved(path: Path) -> Path | None:
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return None


def _new_file_mode() -> int:
    """0o666 minus the process umask: the mode ``open()`` would give a new file."""
    with _umask_lock:  # reading the umask means setting it: keep that step atomic
        mask = os.umask(0o022)
        os.umask(mask)
    return 0o666 & ~mask


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", **kwargs: Any) -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; on success rename it over ``path``.

    On any exception the temporary file is removed and ``path`` is left untouched, so a
    failed command never leaves partial output. ``path`` must pass :func:`check_output`
    (a regular file or a new name; symlinks are followed, so a link stays a link). An
    existing output keeps its permission bits (and, for root, its owner); a new one gets
    the mode ``open()`` would give it under the process umask. A full disk or a failing
    device is one :class:`~mistool.errors.InputPathError`.
    """
    given = Path(path)
    target = check_output(given)
    directory = target.parent
    try:
        old = target.stat()
    except OSError:
        old = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        raise InputPathError(
            f"{given}: cannot write in {given.parent}: {exc.strerror or exc}"
        ) from None
    try:
        try:
            with os.fdopen(fd, mode, **kwargs) as f:
                yield f
                f.flush()
                os.fsync(f.fileno())
            _copy_mode(tmp, old)
            os.replace(tmp, target)
        except OSError as exc:
            if exc.errno in _WRITE_ERRNOS or exc.filename in (None, tmp):
                raise InputPathError(f"{given}: cannot write: {exc.strerror or exc}") from None
            raise
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _copy_mode(tmp: str, old: os.stat_result | None) -> None:
    """Give the temporary file the old output's mode (and owner) or a new file's mode."""
    if old is None:
        os.chmod(tmp, _new_file_mode())
        return
    os.chmod(tmp, stat.S_IMODE(old.st_mode))
    if hasattr(os, "chown") and os.geteuid() == 0:
        with contextlib.suppress(OSError):
            os.chown(tmp, old.st_uid, old.st_gid)


def stdout_stream() -> IO[str]:
    """Standard output for ``-o -``; raises when it is closed (checked before the work)."""
    stream = sys.stdout
    closed = InputPathError("-o -: standard output is closed; give an output file name")
    if stream is None or getattr(stream, "closed", False):
        raise closed
    try:
        fd = stream.fileno()
    except (io.UnsupportedOperation, AttributeError):  # an in-memory stream (tests)
        return stream
    try:
        os.fstat(fd)
    except OSError:
        raise closed from None
    return stream


def write_stdout(write: Callable[[IO[str]], None]) -> None:
    """Call ``write(stream)`` on standard output and flush it (EPIPE propagates: the
    command line reports a closed pipe as one line)."""
    stream = stdout_stream()
    write(stream)
    stream.flush()


#: Largest frame number a motion table may hold (the viewer keeps dense per-frame arrays:
#: a million frames is 11 hours at 25 fps, a few hundred MB of arrays).
MAX_TABLE_FRAME = 1_000_000
#: Largest magnitude of a box coordinate or size in a motion table (px).
MAX_TABLE_PX = 1e6
#: Box columns every row of a motion table needs as finite numbers (Algorithm 1's box).
_BOX_COLUMNS = ("cx_px", "cy_px", "length_px", "width_px")


def check_table_limits(table: TrackTable, where: str, limit: int = MAX_TABLE_FRAME) -> None:
    """Raise :class:`TableError` unless ``table`` is safe to lay out densely per frame:
    ``frame`` values in ``0..limit``, and box columns (and corners, when present) finite
    and within :data:`MAX_TABLE_PX`, sizes not negative."""
    if table.num_rows == 0:
        return
    if "frame" in table.columns:
        frames = np.asarray(table["frame"])
        lo, hi = int(frames.min()), int(frames.max())
        if lo < 0:
            raise TableError(f"{where}: frame {lo} is negative; frames count from 0")
        if hi > limit:
            raise TableError(
                f"{where}: frame {hi} is beyond the limit of {limit} frames "
                f"({limit / 25 / 3600:.0f} h at 25 fps); is the frame column right?"
            )
    corners = tuple(f"{a}{k}_px" for k in range(1, 5) for a in ("x", "y"))
    for name in (*_BOX_COLUMNS, *(c for c in corners if c in table.columns)):
        if name not in table.columns:
            continue
        try:
            values = np.asarray(table[name], dtype=np.float64)
        except (TypeError, ValueError):
            raise TableError(f"{where}: column {name!r} must hold numbers") from None
        bad = ~(np.abs(values) <= MAX_TABLE_PX)
        if name in ("length_px", "width_px"):
            bad |= values < 0
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise TableError(
                f"{where}: row {row + 1}, column {name!r}: {values[row]!r} is not a box "
                f"value (finite, |v| <= {MAX_TABLE_PX:g} px, sizes >= 0)"
            )


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


#: Rows formatted at a time by :func:`write_table_csv` (bounds its memory).
CSV_BLOCK_ROWS = 4096


def _format_floats(values: list[float]) -> list[str]:
    """:func:`format_value` of Python floats, for a whole column block at once."""
    out = []
    for v in values:
        if v != v:  # NaN
            out.append("")
        elif v in (math.inf, -math.inf):
            out.append("inf" if v > 0 else "-inf")
        else:
            text = f"{v:.6f}".rstrip("0").rstrip(".")
            out.append("0" if text in ("-0", "") else text)
    return out


def _format_column(col: np.ndarray) -> list[str]:
    """Every cell of a column block, as :func:`format_value` writes it."""
    if col.dtype.kind == "f":
        return _format_floats(col.tolist())
    if col.dtype.kind in "iu":
        return [str(v) for v in col.tolist()]
    return [format_value(v) for v in col]


def write_table_csv(table: TrackTable, out: IO[str]) -> None:
    """Write ``table`` as CSV to an open text stream: the header by ``csv.writer``, the
    rows a block at a time by a compiled formatter (:mod:`mistool.kernels.csvtext`; the
    same text as :func:`format_value` cell by cell with ``csv.writer``'s quoting:
    ``tests/test_export.py``). A block holding a finite float of magnitude 9e9 or more
    is formatted by Python instead."""
    from mistool.kernels.csvtext import FLOAT_LIMIT, format_rows  # numba: at the first use

    names = list(table.columns)
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(names)
    cols = [table[c] for c in names]
    kinds = [_cell_kind(col) for col in cols]
    plan = np.zeros((len(cols), 2), np.int64)
    counts = [0, 0, 0]
    for c, kind in enumerate(kinds):
        plan[c] = kind, counts[kind]
        counts[kind] += 1
    for start in range(0, table.num_rows, CSV_BLOCK_ROWS):
        block = [col[start : start + CSV_BLOCK_ROWS] for col in cols]
        n = len(block[0]) if block else 0
        floats = np.empty((n, counts[0]), np.float64)
        ints = np.empty((n, counts[1]), np.int64)
        texts = np.empty((n, counts[2]), np.int64)
        encoded: dict[str, int] = {}
        for c, col in enumerate(block):
            kind, j = kinds[c], int(plan[c, 1])
            if kind == 0:
                floats[:, j] = col
            elif kind == 1:
                ints[:, j] = col
            else:  # (a str is its own cell text: format_value's last case, not called)
                put = encoded.setdefault
                texts[:, j] = [
                    put(v if type(v) is str else format_value(v), len(encoded)) for v in col
                ]
        big = np.abs(floats) >= FLOAT_LIMIT
        if big.any() and np.isfinite(floats[big]).any():
            writer.writerows(zip(*[_format_column(col) for col in block], strict=True))
            continue
        pieces = [_csv_field(text).encode("utf-8") for text in encoded]
        offsets = np.zeros(len(pieces) + 1, np.int64)
        offsets[1:] = np.cumsum([len(p) for p in pieces])
        text_bytes = np.frombuffer(bytearray(b"".join(pieces) + b"\0"), np.uint8)
        longest = max((len(p) for p in pieces), default=0)
        buf = np.empty(n * (len(cols) * (26 + longest) + 1), np.uint8)
        size = format_rows(n, floats, ints, texts, plan, text_bytes, offsets, buf)
        out.write(buf[:size].tobytes().decode("utf-8"))


def _cell_kind(col: np.ndarray) -> int:
    """0: float cells, 1: integer cells (formatted as int64), 2: any other (text)."""
    if col.dtype.kind == "f":
        return 0
    if (
        col.dtype.kind in "iu"
        and col.dtype.itemsize <= 8
        and not (col.dtype.kind == "u" and col.dtype.itemsize == 8)
    ):
        return 1
    return 2


def _csv_field(text: str) -> str:
    """``text`` as ``csv.writer`` (``lineterminator="\\n"``) writes a field that is not
    alone on its row (its quoting rules vary between Python versions: asked, not copied)."""
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow([text, ""])
    return buf.getvalue()[:-2]  # without the empty last field's "," and the "\n"


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
            wrong = np.isnan(values) | (values != np.round(values)) | ~(np.abs(values) <= _MAX_INT)
            if wrong.any():
                bad = int(np.flatnonzero(wrong)[0])
                raise TableError(
                    f"{p}: line {bad + 2}, column {name!r}: expected an integer, got {cells[bad]!r}"
                )
            values = values.astype(np.int64)
        columns[name] = values
    return TrackTable(columns)


#: Largest integer magnitude read into an integer column (exact in float64).
_MAX_INT = 2.0**53


def _is_number(text: str) -> bool:
    if text.strip() == "":
        return True
    try:
        float(text)
    except ValueError:
        return False
    return True
