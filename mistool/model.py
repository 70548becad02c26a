"""The data model: rotated boxes and the track table (the motion table's columns).

Conventions (stated once, used everywhere; see README "Conventions"):

- Pixels: x right, y down, pixel centres at integer coordinates.
- A rotated box is ``(cx, cy, length, width, angle)`` with ``length >= width`` and
  ``angle`` the direction of the long side in degrees, in ``[0, 180)``, measured from +x
  towards +y (clockwise on screen, since y points down).
- Camera frame: OpenCV (x right, y down, z forward), millimetres.
- Quaternions are ``wxyz`` (as viser).
- A part that is not visible in a frame has no row; an estimate that is unknown or not
  trustworthy is NaN (an empty CSV cell), never zero.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mistool.errors import TableError
from mistool.parts import PARTS as PARTS  # (defined there: no numpy)


@dataclass(frozen=True)
class RotatedBox:
    """A part's rotated bounding box in pixels, in mistool's one canonical form."""

    cx: float
    """Centre x (px)."""
    cy: float
    """Centre y (px)."""
    length: float
    """Long side (px); always ``>= width``."""
    width: float
    """Short side (px)."""
    angle_deg: float
    """Direction of the long side, degrees in ``[0, 180)``, from +x towards +y."""

    def __post_init__(self) -> None:
        if self.length < self.width:
            raise ValueError(f"RotatedBox: length {self.length} < width {self.width}")
        if not 0.0 <= self.angle_deg < 180.0:
            raise ValueError(f"RotatedBox: angle_deg {self.angle_deg} outside [0, 180)")

    def corners(self) -> np.ndarray:
        """The four corners, shape (4, 2), float64, (x, y) px.

        Order: start at the corner at ``-length/2`` along the axis and ``-width/2``
        across it, then go round: (-l,-w), (+l,-w), (+l,+w), (-l,+w). Consecutive corners
        share an edge, so the shoelace formula applies.
        """
        t = math.radians(self.angle_deg)
        ux, uy = math.cos(t), math.sin(t)  # along the long side; (-uy, ux) across it
        hl, hw = self.length / 2.0, self.width / 2.0
        ax, ay = hl * ux, hl * uy  # half the long side
        bx, by = hw * -uy, hw * ux  # half the short side
        cx, cy = self.cx, self.cy  # (plain floats: the same values as numpy's, ~5x faster)
        return np.array(
            [
                [cx - ax - bx, cy - ay - by],
                [cx + ax - bx, cy + ay - by],
                [cx + ax + bx, cy + ay + by],
                [cx - ax + bx, cy - ay + by],
            ]
        )


@dataclass(frozen=True)
class PartObservation:
    """One part of one instrument in one frame (Algorithm 1 on its pixels)."""

    part: str
    """Part name, one of :data:`PARTS`."""
    box: RotatedBox
    """The part's rotated box (Algorithm 1), full-image px."""
    corners: np.ndarray
    """(4, 2) float64 box corners in ``cv2.boxPoints`` order, full-image px."""
    area_px: int
    """Number of the part's mask pixels (after speck removal)."""
    mask: np.ndarray
    """(h, w) bool crop of the part's pixels (after speck removal)."""
    offset: tuple[int, int]
    """(x0, y0): full-image px of the crop's top-left pixel."""


@dataclass(frozen=True)
class InstanceObservation:
    """One instrument in one frame: its visible parts."""

    label: str | None
    """The config instrument's name when instruments have their own label values;
    None in merged masks (the identity tracker names it)."""
    parts: dict[str, PartObservation]
    """Visible parts, proximal to distal."""
    centroid_px: tuple[float, float]
    """(x, y) mean of all the instrument's part pixels, px."""
    area_px: int
    """Number of the instrument's part pixels."""
    bbox_xywh: tuple[int, int, int, int]
    """Axis-aligned bounds of those pixels: (x0, y0, width, height), px."""
    image_shape: tuple[int, int] | None = None
    """(H, W) of the label image (None if unknown): where the image border is."""


# The motion table's columns, in their one fixed order, with their dtypes.
# "contract" columns are required by DESIGN.md; the rest are mistool's extras.
_F = np.float64
COLUMNS: tuple[tuple[str, Any], ...] = (
    ("frame", np.int64),  # 0-based index in the sequence
    ("time_s", _F),  # frame / fps
    ("instrument", object),  # instrument name (str)
    ("part", object),  # "shaft" | "wrist" | "clasper"
    # Algorithm 1: the part's rotated box
    ("cx_px", _F),
    ("cy_px", _F),
    ("length_px", _F),
    ("width_px", _F),
    ("angle_deg", _F),
    ("area_px", _F),  # number of the part's mask pixels
    ("x1_px", _F),
    ("y1_px", _F),
    ("x2_px", _F),
    ("y2_px", _F),  # boxPoints corners, in
    ("x3_px", _F),
    ("y3_px", _F),
    ("x4_px", _F),
    ("y4_px", _F),  # OpenCV's order
    # Algorithm 2: the paper's frame-to-frame motion (NaN on a part's first frame)
    ("dx_px", _F),
    ("dy_px", _F),
    ("dz", _F),
    ("droll_deg", _F),
    ("dpitch_deg", _F),
    ("dyaw_deg", _F),
    # Algorithm 2: the paper's per-frame quantities (centroid, z of Eq. 5, e_r, e_p, e_y)
    ("paper_x_px", _F),
    ("paper_y_px", _F),
    ("paper_z", _F),
    ("paper_roll_deg", _F),
    ("paper_pitch_deg", _F),
    ("paper_yaw_deg", _F),
    # Metric pose (camera frame, mm): distal end (shaft: joint J; clasper: tip), unit axis
    ("end_x_mm", _F),
    ("end_y_mm", _F),
    ("end_z_mm", _F),
    ("axis_x", _F),
    ("axis_y", _F),
    ("axis_z", _F),
    # Metric pose for the viewer: proximal end and orientation T_camera_part (wxyz),
    # the part frame's +z along the axis.
    ("start_x_mm", _F),
    ("start_y_mm", _F),
    ("start_z_mm", _F),
    ("qw", _F),
    ("qx", _F),
    ("qy", _F),
    ("qz", _F),
    ("quality", _F),  # IoU of the re-rendered pose with the mask, [0, 1]
    ("trocar_x_mm", _F),
    ("trocar_y_mm", _F),
    ("trocar_z_mm", _F),  # per instrument
    ("pose_status", object),  # "ok" or why the metric pose is empty (mistool.pose.status)
)
COLUMN_NAMES: tuple[str, ...] = tuple(name for name, _ in COLUMNS)
COLUMN_DTYPES: dict[str, Any] = dict(COLUMNS)

#: The columns DESIGN.md requires in every motion table.
CONTRACT_COLUMNS: tuple[str, ...] = (
    "frame",
    "instrument",
    "part",
    "cx_px",
    "cy_px",
    "length_px",
    "width_px",
    "angle_deg",
    "dx_px",
    "dy_px",
    "dz",
    "droll_deg",
    "dpitch_deg",
    "dyaw_deg",
    "end_x_mm",
    "end_y_mm",
    "end_z_mm",
    "axis_x",
    "axis_y",
    "axis_z",
)


def _as_column(name: str, values: Any, n: int | None = None) -> np.ndarray:
    dtype = COLUMN_DTYPES.get(name)
    if dtype is object:
        arr = np.empty(len(values), dtype=object)
        arr[:] = [str(v) for v in values]
        return arr
    arr = np.asarray(values)
    if dtype is not None:
        arr = arr.astype(dtype, copy=False)
    elif arr.dtype.kind not in "biuf":
        out = np.empty(len(arr), dtype=object)
        out[:] = [str(v) for v in arr]
        arr = out
    if arr.ndim != 1:
        raise TableError(f"column {name!r}: expected a 1-D array, got shape {arr.shape}")
    return arr


def group_rows(*columns: np.ndarray) -> Iterator[tuple[tuple[Any, ...], np.ndarray]]:
    """``(key values, row indices)`` for each distinct combination of the columns'
    values, in order of first row, the rows in their order within each group (int64).

    The key values are the columns' elements as indexing gives them. Text, integer and
    boolean columns are grouped with ``np.unique``; others (floats: each NaN its own
    key, as in a dict) row by row."""
    n = len(columns[0]) if columns else 0
    if n == 0:
        return
    codes = np.zeros(n, dtype=np.int64)
    span = 1
    for col in columns:
        if col.dtype.kind not in "OUSiub":
            yield from _group_rows_one_by_one(columns)
            return
        try:
            _, inverse = np.unique(col, return_inverse=True)
        except TypeError:  # objects that do not sort (mixed types)
            yield from _group_rows_one_by_one(columns)
            return
        size = int(inverse.max()) + 1
        span *= size
        if span >= 1 << 62:  # (never with a table's few names and parts)
            yield from _group_rows_one_by_one(columns)
            return
        codes = codes * size + inverse.reshape(-1)
    _, first, group = np.unique(codes, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    by_group = np.argsort(group, kind="stable")  # rows of each group in table order
    members = np.split(by_group, np.cumsum(np.bincount(group))[:-1])
    for g in np.argsort(first, kind="stable"):
        idx = members[g].astype(np.int64, copy=False)
        yield tuple(col[idx[0]] for col in columns), idx


def _group_rows_one_by_one(
    columns: tuple[np.ndarray, ...],
) -> Iterator[tuple[tuple[Any, ...], np.ndarray]]:
    seen: dict[tuple[Any, ...], list[int]] = {}
    for i, key in enumerate(zip(*columns, strict=True)):
        seen.setdefault(tuple(key), []).append(i)
    for key, idx in seen.items():
        yield key, np.asarray(idx, dtype=np.int64)


class TrackTable(Mapping[str, np.ndarray]):
    """A sequence's results: equal-length columns, one row per observed
    (frame, instrument, part). An absent part has no row.

    Struct of arrays (like ``supervision.Detections``): ``table["cx_px"]`` is a column,
    ``table[mask]`` / ``table[2:5]`` select rows, ``pandas.DataFrame(dict(table))`` works.
    Known columns keep :data:`COLUMNS` order and dtypes; extra columns follow, in the order
    they were added. Missing known columns read as NaN-filled float columns.
    """

    def __init__(self, columns: Mapping[str, Any] | None = None) -> None:
        cols: dict[str, np.ndarray] = {}
        n: int | None = None
        for name, values in (columns or {}).items():
            arr = _as_column(name, values)
            if n is None:
                n = len(arr)
            elif len(arr) != n:
                raise TableError(f"column {name!r} has {len(arr)} rows, expected {n}")
            cols[name] = arr
        self._n = n or 0
        for name in ("frame", "instrument", "part"):
            if name not in cols:
                cols[name] = _as_column(name, [])
                if self._n:
                    raise TableError(f"track table needs a {name!r} column")
        known = [c for c in COLUMN_NAMES if c in cols]
        extra = [c for c in cols if c not in COLUMN_DTYPES]
        self._cols = {c: cols[c] for c in known + extra}

    # Mapping interface -------------------------------------------------------------
    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, str):
            if key in self._cols:
                return self._cols[key]
            if key in COLUMN_DTYPES and COLUMN_DTYPES[key] is _F:
                return np.full(self._n, np.nan)
            raise KeyError(key)
        cols = {c: v[key] for c, v in self._cols.items()}
        n = len(cols["frame"]) if np.ndim(cols["frame"]) == 1 else None
        if n is None:  # not a row selection: the constructor says what is wrong
            return TrackTable(cols)
        return TrackTable._valid(cols, n)

    def __iter__(self) -> Iterator[str]:
        return iter(self._cols)

    def __len__(self) -> int:  # number of columns, as a Mapping
        return len(self._cols)

    def __contains__(self, key: object) -> bool:
        return key in self._cols

    @property
    def num_rows(self) -> int:
        """Number of rows (observations)."""
        return self._n

    @property
    def columns(self) -> tuple[str, ...]:
        """Column names in table order."""
        return tuple(self._cols)

    def with_columns(self, **updates: Any) -> TrackTable:
        """A new table with columns added or replaced (same number of rows)."""
        cols = dict(self._cols)  # already validated: only the updates are checked
        for name, values in updates.items():
            arr = _as_column(name, values)
            if len(arr) != self._n:
                raise TableError(f"column {name!r} has {len(arr)} rows, expected {self._n}")
            cols[name] = arr
        out = TrackTable.__new__(TrackTable)
        out._n = self._n
        known = [c for c in COLUMN_NAMES if c in cols]
        out._cols = {c: cols[c] for c in known + [c for c in cols if c not in COLUMN_DTYPES]}
        return out

    def without(self, *names: str) -> TrackTable:
        """A new table without the columns ``names`` (absent ones ignored; the others
        are the same arrays)."""
        cols = {c: v for c, v in self._cols.items() if c not in names}
        for name in ("frame", "instrument", "part"):
            if name not in cols:
                raise TableError(f"track table needs a {name!r} column")
        return TrackTable._valid(cols, self._n)

    def full(self) -> TrackTable:
        """A new table holding every known column (NaN, or '' for text, where unknown),
        then the extras."""
        cols = {
            c: self._cols[c]
            if c in self._cols
            else np.full(self._n, "", dtype=object)
            if COLUMN_DTYPES[c] is object
            else self[c]
            for c in COLUMN_NAMES
        }
        cols.update({c: v for c, v in self._cols.items() if c not in cols})
        return TrackTable._valid(cols, self._n)

    def sorted(self) -> TrackTable:
        """Rows ordered by (frame, instrument, part order)."""
        if self._n == 0:
            return self
        part = self._cols["part"]
        part_rank = np.full(self._n, len(PARTS))
        for k in range(len(PARTS) - 1, -1, -1):  # (PARTS.index: the first)
            part_rank[part == PARTS[k]] = k
        order = np.lexsort((part_rank, self._cols["instrument"].astype(str), self._cols["frame"]))
        return self[order]

    @staticmethod
    def concat(tables: Iterable[TrackTable]) -> TrackTable:
        """Stack tables row-wise; a column missing from some table is NaN/'' there."""
        tables = [t for t in tables]
        if not tables:
            return TrackTable()
        names: list[str] = []
        for t in tables:
            names += [c for c in t.columns if c not in names]
        out: dict[str, list[np.ndarray]] = {c: [] for c in names}
        for t in tables:
            for c in names:
                if c in t:
                    out[c].append(t._cols[c])
                elif COLUMN_DTYPES.get(c) is object:
                    out[c].append(np.array([""] * t.num_rows, dtype=object))
                else:
                    out[c].append(np.full(t.num_rows, np.nan))
        # text columns are tables' already (or ''): only the others are converted
        joined = {
            c: np.concatenate(v)
            if COLUMN_DTYPES.get(c) is object
            else _as_column(c, np.concatenate(v))
            for c, v in out.items()
        }
        known = [c for c in COLUMN_NAMES if c in joined]
        extra = [c for c in joined if c not in COLUMN_DTYPES]
        ordered = {c: joined[c] for c in known + extra}
        return TrackTable._valid(ordered, sum(t.num_rows for t in tables))

    def groups(self, *keys: str) -> Iterator[tuple[tuple[Any, ...], np.ndarray]]:
        """Yield ``(key values, row indices)`` for each distinct combination of ``keys``,
        rows in their table order within each group (:func:`group_rows`)."""
        return group_rows(*(self._cols[k] for k in keys))

    @staticmethod
    def _valid(cols: dict[str, np.ndarray], n: int) -> TrackTable:
        """A table of columns taken from valid tables (rows selected, joined): each
        already a 1-D array of its column's dtype with ``n`` rows, in table order."""
        out = TrackTable.__new__(TrackTable)
        out._n = n
        out._cols = cols
        return out

    def to_pandas(self) -> Any:
        """A ``pandas.DataFrame`` of the table (pandas is imported only here)."""
        import pandas as pd  # optional dependency

        return pd.DataFrame({c: v for c, v in self._cols.items()})

    def __repr__(self) -> str:
        return f"TrackTable({self._n} rows x {len(self._cols)} columns)"


def empty_table() -> TrackTable:
    """A zero-row table with every known column, typed."""
    return TrackTable({name: np.empty(0, dtype=dtype) for name, dtype in COLUMNS})


def require_columns(table: Mapping[str, Any], names: Sequence[str], where: str) -> None:
    """Raise :class:`TableError` naming ``where`` if any of ``names`` is missing."""
    missing = [n for n in names if n not in table]
    if missing:
        raise TableError(f"{where}: missing column(s) {', '.join(missing)}")
