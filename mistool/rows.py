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

#: Rows allocated at first; capacity doubles when full.
INITIAL_ROWS = 256

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
        # metric columns, created when first seen (NaN / "" in earlier rows)
        self._num: dict[str, np.ndarray] = {}
        self._text: dict[str, np.ndarray] = {}

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
            out[: self._n] = a[: self._n]
            return out

        self._frame = grown(self._frame, 0)
        self._inst = grown(self._inst, 0)
        self._part = grown(self._part, 0)
        self._box = grown(self._box, np.nan)
        self._num = {c: grown(a, np.nan) for c, a in self._num.items()}
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
        metrics: Sequence[Mapping[str, Mapping[str, Any]] | None],
    ) -> None:
        """Add one frame's rows: one per visible part of each named instance.

        Args:
            index: the frame's 0-based index.
            names: instrument name per instance.
            instances: ``InstanceObservation`` per instance (``.parts``: part -> obs with
                ``.box``, ``.corners`` (4, 2) px, ``.area_px``).
            metrics: per instance, part -> {column: value} of the metric pose, or None.
        """
        for name, inst, metric in zip(names, instances, metrics, strict=True):
            code = self._code(str(name))
            for p, part in enumerate(PARTS):
                obs = inst.parts.get(part)
                if obs is None:
                    continue
                self._add(index, code, p, obs, (metric or {}).get(part))

    def _add(self, index: int, code: int, part: int, obs: Any, metric: Any) -> None:
        i = self._n
        if i == self._cap:
            self._grow(i + 1)
        self._frame[i] = index
        self._inst[i] = code
        self._part[i] = part
        b = obs.box
        row = self._box[i]
        row[:6] = (b.cx, b.cy, b.length, b.width, b.angle_deg, obs.area_px)
        row[6:] = np.asarray(obs.corners, dtype=np.float64).reshape(8)
        self._n = i + 1
        if metric:
            for col, v in metric.items():
                if isinstance(v, str):
                    self._column(self._text, col, "", object)[i] = v
                else:
                    self._column(self._num, col, np.nan, np.float64)[i] = np.nan if v is None else v

    def _column(self, cols: dict[str, np.ndarray], name: str, fill: Any, dtype: Any) -> np.ndarray:
        arr = cols.get(name)
        if arr is None:
            arr = cols[name] = np.full(self._cap, fill, dtype=dtype)
        return arr

    def take(self) -> TrackTable:
        """The rows so far as a table (columns: :data:`BASE_COLUMNS`, then the metric
        columns, known ones in :data:`~mistool.model.COLUMNS` order); the builder is
        emptied (its capacity kept)."""
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
        extra = {**self._num, **self._text}
        known = [c for c in COLUMN_NAMES if c in extra]
        for c in known + [c for c in extra if c not in known]:
            cols[c] = extra[c][:n].copy()
        self._n = 0
        for a in self._num.values():
            a[:n] = np.nan
        for a in self._text.values():
            a[:n] = ""
        return TrackTable(cols)
