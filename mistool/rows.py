"""Accumulating motion-table rows in growing numpy columns.

:class:`RowBuilder` turns each frame's named instances (and their metric pose) into rows,
one per (frame, instrument, part), written into preallocated numpy columns that double
in capacity when full. A row costs its columns' bytes (8 per numeric column; names are
small integer codes until :meth:`RowBuilder.take`), never a Python float object per
cell, so a long sequence's rows stay compact.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from mistool.model import COLUMN_NAMES, PARTS, TrackTable
from mistool.pose.measure import ROW_KEYS, ROW_LEN, SLOT_OF, SLOTS

#: Rows allocated at first; capacity doubles when full.
INITIAL_ROWS = 256
#: Rows kept in lists before they are written into the columns together.
FLUSH_ROWS = 1024

#: The numeric columns every table built here has, after frame, time_s, instrument, part.
BOX_COLUMNS: tuple[str, ...] = (
    "cx_px",
    "cy_px",
    "length_px",
    "width_px",
    "angle_deg",
    "area_px",
    "x1_px",
    "y1_px",
    "x2_px",
    "y2_px",
    "x3_px",
    "y3_px",
    "x4_px",
    "y4_px",
)
#: Columns every table built here has, in order (the rest come from the metric pose).
BASE_COLUMNS: tuple[str, ...] = ("frame", "time_s", "instrument", "part", *BOX_COLUMNS)

#: No run of rows' cells yet (:meth:`RowBuilder._add_posed`).
_NO_RUN: tuple[None, list[Any]] = (None, [])
#: Each of :data:`~mistool.model.PARTS`: its index, name, and its row in an instance's
#: metric pose array (:func:`mistool.pose.measure.measure_rows`).
_PART_ROWS: tuple[tuple[int, str, int], ...] = tuple(
    (p, part, SLOT_OF[part]) for p, part in enumerate(PARTS)
)
#: Rows of an instance's metric pose array.
_SLOTS_PER_INSTANCE = len(SLOTS)


class RowBuilder:
    """Rows of consecutive frames, in growing numpy columns.

    Args:
        fps: frames per second (``time_s = frame / fps``).
    """

    def __init__(self, fps: float) -> None:
        self.fps = fps
        self._cap = INITIAL_ROWS
        self._n = 0
        self._frame = np.empty(self._cap, np.int64)
        self._inst = np.empty(self._cap, np.int32)  # code into self._names
        self._part = np.empty(self._cap, np.int8)  # index into PARTS
        self._box = np.empty((self._cap, len(BOX_COLUMNS)), np.float64)
        self._names: list[str] = []
        self._codes: dict[str, int] = {}
        # numeric metric columns, one block, a column each, created when first seen (NaN
        # in earlier rows); text metric columns apart ("" in earlier rows)
        self._num_names: list[str] = []
        self._num_index: dict[str, int] = {}
        self._num = np.empty((self._cap, 0), np.float64)
        self._text: dict[str, np.ndarray] = {}
        # per tuple of a metric's keys (all numeric): where its values go in self._num
        self._plans: dict[tuple[str, ...], slice | list[int]] = {}
        # rows of frames with the pose as one array, not yet in the columns (written
        # together, :meth:`_flush`): rows before self._done are in the columns
        self._done = 0
        self._frames: list[int] = []
        self._insts: list[int] = []
        self._parts: list[int] = []
        # their box cells: runs of rows from one array (a worker's batch: the parts'
        # ``_row``, mistool.parallel.unpack_frames), each the array and the rows' indices
        # in it, or None and the rows' cells (a part without ``_row``: _row_cells)
        self._cells: list[tuple[np.ndarray | None, list[Any]]] = []
        self._poses: list[np.ndarray] = []  # each frame's poses, (instances, 3, ROW_LEN)
        self._picks: list[int] = []  # per row with a pose, its row in those stacked
        self._posed: list[int] = []  # and its row in the table
        self._stacked = 0  # rows of the poses so far

    @property
    def num_rows(self) -> int:
        """Rows so far."""
        return self._n

    def _grow(self, need: int) -> None:
        cap = self._cap
        while cap < need:
            cap *= 2
        if cap == self._cap:
            return

        def grown(a: np.ndarray, fill: Any) -> np.ndarray:
            out = np.full((cap, *a.shape[1:]), fill, dtype=a.dtype)
            out[: self._done] = a[: self._done]
            return out

        self._frame = grown(self._frame, 0)
        self._inst = grown(self._inst, 0)
        self._part = grown(self._part, 0)
        self._box = grown(self._box, np.nan)
        self._num = grown(self._num, np.nan)
        self._text = {c: grown(a, "") for c, a in self._text.items()}
        self._cap = cap

    def _code(self, name: str) -> int:
        code = self._codes.get(name)
        if code is None:
            code = self._codes[name] = len(self._names)
            self._names.append(name)
        return code

    def add_frame(
        self,
        index: int,
        names: Sequence[str],
        instances: Sequence[Any],
        metrics: np.ndarray | Sequence[Mapping[str, Mapping[str, Any]] | None] | None,
    ) -> None:
        """Add one frame's rows: one per visible part of each named instance.

        Args:
            index: the frame's 0-based index.
            names: instrument name per instance.
            instances: ``InstanceObservation`` per instance (``.parts``: part -> obs with
                ``.box``, ``.corners`` (4, 2) px, ``.area_px``).
            metrics: the metric pose: one ``(instances, 3, ROW_LEN)`` float64 array
                (:attr:`mistool.parallel.FrameResult.metrics`: each instance's
                :func:`~mistool.pose.measure.measure_rows`), copied into the columns of
                :data:`~mistool.pose.measure.ROW_KEYS` in one assignment; or per
                instance, part -> {column: value} (any columns, numbers or text), or
                None; None: no metric pose.
        """
        if metrics is None or isinstance(metrics, np.ndarray):
            self._add_posed(index, names, instances, metrics)
            return
        self._flush()
        rows: list[tuple[int, int, Any, Any]] = []
        for name, inst, metric in zip(names, instances, metrics, strict=True):
            code = self._code(str(name))
            parts = inst.parts
            for p, part in enumerate(PARTS):
                obs = parts.get(part)
                if obs is not None:
                    rows.append((code, p, obs, metric.get(part) if metric else None))
        if not rows:
            return
        i0 = self._rows(index, rows)
        for i, (_, _, _, metric) in enumerate(rows, i0):
            if metric:
                self._add_metric(i, metric)

    def _add_posed(
        self,
        index: int,
        names: Sequence[str],
        instances: Sequence[Any],
        poses: np.ndarray | None,
    ) -> None:
        """:meth:`add_frame` with the metric pose as one array, or None: the rows' cells
        kept in lists (written into the columns together, :meth:`_flush`)."""
        if poses is not None and poses.shape != (len(instances), len(SLOTS), ROW_LEN):
            raise ValueError(
                f"metrics: expected shape ({len(instances)}, {len(SLOTS)}, {ROW_LEN}) for "
                f"{len(instances)} instances, got {poses.shape}"
            )
        n0 = self._n
        insts, parts_of, cells = self._insts, self._parts, self._cells
        picks = self._picks
        codes = self._codes
        first = len(insts)
        slot = self._stacked  # the instance's first row in the poses stacked
        src, at = cells[-1] if cells else _NO_RUN
        for name, inst in zip(names, instances, strict=True):
            code = codes.get(name)  # (a name's code: :meth:`_code` of ``str(name)``)
            if code is None or type(name) is not str:
                code = self._code(str(name))
            get = inst.parts.get
            for p, part, k in _PART_ROWS:
                obs = get(part)
                if obs is not None:
                    insts.append(code)
                    parts_of.append(p)
                    row = getattr(obs, "_row", None)
                    if row is not None:
                        if row[0] is not src:
                            src, at = row[0], []
                            cells.append((src, at))
                        at.append(row[1])
                    else:
                        if src is not None or not cells:
                            src, at = None, []
                            cells.append((src, at))
                        at.append(_row_cells(obs))
                    picks.append(slot + k)
            slot += _SLOTS_PER_INSTANCE
        added = len(insts) - first
        if not added:
            return
        self._frames.extend([index] * added)
        self._n = n0 + added
        if poses is None:
            del picks[len(picks) - added :]
        else:
            self._poses.append(poses)  # (stacked and reshaped together: _flush)
            self._stacked += len(poses) * _SLOTS_PER_INSTANCE
            self._posed.extend(range(n0, n0 + added))
        if self._n - self._done >= FLUSH_ROWS:
            self._flush()

    def _flush(self) -> None:
        """Write the rows kept in lists into the columns."""
        i0, i1 = self._done, self._n
        if i1 == i0:
            return
        if i1 > self._cap:
            self._grow(i1)
        self._frame[i0:i1] = self._frames
        self._inst[i0:i1] = self._insts
        self._part[i0:i1] = self._parts
        blocks = [
            np.array(at, np.float64).reshape(-1, len(BOX_COLUMNS)) if src is None else src[at]
            for src, at in self._cells
        ]
        self._box[i0:i1] = blocks[0] if len(blocks) == 1 else np.concatenate(blocks)
        if self._posed:
            plan = self._plans.get(ROW_KEYS)
            if plan is None:  # before self._num is read: it may grow
                plan = self._plans[ROW_KEYS] = self._plan(ROW_KEYS)
            cols = np.arange(self._num.shape[1])[plan]
            stacked = np.concatenate(self._poses).reshape(-1, ROW_LEN)
            at = np.array(self._posed, np.int64)
            self._num[np.ix_(at, cols)] = stacked[self._picks]
        self._done = i1
        self._frames.clear()
        self._insts.clear()
        self._parts.clear()
        self._cells.clear()
        self._poses.clear()
        self._picks.clear()
        self._posed.clear()
        self._stacked = 0

    def _rows(self, index: int, rows: list[tuple[int, int, Any, Any]]) -> int:
        """Write ``rows``' frame, instrument, part and box cells; their first row (no
        rows kept in lists: :meth:`_flush` first)."""
        i0 = self._n
        i1 = i0 + len(rows)
        if i1 > self._cap:
            self._grow(i1)
        self._frame[i0:i1] = index
        self._inst[i0:i1] = [r[0] for r in rows]
        self._part[i0:i1] = [r[1] for r in rows]
        self._box[i0:i1] = [_cells_of(r[2]) for r in rows]
        self._n = self._done = i1
        return i0

    def _add_metric(self, i: int, metric: Mapping[str, Any]) -> None:
        """Row ``i``'s metric values: numbers (None: NaN) and text, by column name."""
        values = list(metric.values())
        if any(isinstance(v, str) for v in values):
            for col, v in metric.items():
                if isinstance(v, str):
                    self._text_column(col)[i] = v
                else:
                    j = self._num_column(col)  # before self._num is read: it may grow
                    self._num[i, j] = np.nan if v is None else v
            return
        keys = tuple(metric)
        plan = self._plans.get(keys)
        if plan is None:  # before self._num is read: it may grow
            plan = self._plans[keys] = self._plan(keys)
        # a float64 cell takes a number as it is and None as NaN, as a cell at a time did
        self._num[i, plan] = values

    def _plan(self, keys: tuple[str, ...]) -> slice | list[int]:
        js = [self._num_column(k) for k in keys]
        if js == list(range(js[0], js[0] + len(js))):
            return slice(js[0], js[0] + len(js))
        return js

    def _num_column(self, name: str) -> int:
        j = self._num_index.get(name)
        if j is None:
            j = self._num_index[name] = len(self._num_names)
            self._num_names.append(name)
            self._num = np.hstack([self._num, np.full((self._cap, 1), np.nan)])
        return j

    def _text_column(self, name: str) -> np.ndarray:
        arr = self._text.get(name)
        if arr is None:
            arr = self._text[name] = np.full(self._cap, "", dtype=object)
        return arr

    def take(self) -> TrackTable:
        """The rows so far as a table (columns: :data:`BASE_COLUMNS`, then the metric
        columns, known ones in :data:`~mistool.model.COLUMNS` order); the builder is
        emptied (its capacity kept)."""
        self._flush()
        n = self._n
        names = np.empty(len(self._names), dtype=object)
        names[:] = self._names
        parts = np.empty(len(PARTS), dtype=object)
        parts[:] = PARTS
        frame = self._frame[:n].copy()
        cols: dict[str, Any] = {
            "frame": frame,
            "time_s": frame / self.fps,
            "instrument": names[self._inst[:n]],
            "part": parts[self._part[:n]],
        }
        for j, c in enumerate(BOX_COLUMNS):
            cols[c] = self._box[:n, j].copy()
        extra: dict[str, np.ndarray] = {c: self._num[:, j] for j, c in enumerate(self._num_names)}
        extra.update(self._text)
        known = [c for c in COLUMN_NAMES if c in extra]
        for c in known + [c for c in extra if c not in known]:
            cols[c] = extra[c][:n].copy()
        self._n = self._done = 0
        self._num[:n] = np.nan
        for a in self._text.values():
            a[:n] = ""
        return TrackTable(cols)


def _cells_of(obs: Any) -> list[float]:
    """A part's :data:`BOX_COLUMNS` cells: its ``_row`` (a worker's part: the batch's
    cells and its row there, :func:`mistool.parallel.unpack_frames`), else
    :func:`_row_cells`."""
    row = getattr(obs, "_row", None)
    if row is None:
        return _row_cells(obs)
    cells: list[float] = row[0][row[1]].tolist()
    return cells


def _row_cells(obs: Any) -> list[float]:
    """A part's :data:`BOX_COLUMNS` cells read from its fields: its box, area and (4, 2)
    corners row by row."""
    b = obs.box
    corners: list[float] = np.asarray(obs.corners, dtype=np.float64).ravel().tolist()
    return [b.cx, b.cy, b.length, b.width, b.angle_deg, obs.area_px, *corners]
