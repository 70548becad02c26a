"""RowBuilder: rows in growing numpy columns, metric columns appearing late, take()."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mistool.model import COLUMN_NAMES, PARTS, RotatedBox, TrackTable
from mistool.rows import BASE_COLUMNS, BOX_COLUMNS, INITIAL_ROWS, RowBuilder


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


class _FormerRowBuilder:  # mistool.rows.RowBuilder as it was (e67ef6d)
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


_NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.none(), st.integers(-5, 5))
_TEXT = st.sampled_from(["ok", "no camera", ""])
_ITEM = st.one_of(  # known numeric columns take numbers, text ones text, others either
    st.tuples(st.sampled_from(("end_x_mm", "quality", "axis_z", "aux_u_px")), _NUMBERS),
    st.tuples(st.just("pose_status"), _TEXT),
    st.tuples(st.sampled_from(("zz_extra", "zz_more")), st.one_of(_NUMBERS, _TEXT)),
)
_METRIC = st.one_of(
    st.none(),
    st.dictionaries(st.sampled_from(PARTS), st.lists(_ITEM, max_size=7).map(dict)),
)
_FRAME = st.lists(st.tuples(st.sampled_from("abc"), st.sets(st.sampled_from(PARTS)), _METRIC))


@settings(max_examples=80, deadline=None)
@given(st.lists(_FRAME, max_size=40), st.integers(0, 3))
def test_rows_are_those_of_the_former_definition(frames, takes) -> None:
    """Frames of random instances and metric dicts (numbers, None, text, keys in any
    order, columns appearing late), taken at random points: the same tables, bit for bit."""
    new, old = RowBuilder(fps=7.0), _FormerRowBuilder(fps=7.0)
    got: list[TrackTable] = []
    want: list[TrackTable] = []
    for k, frame in enumerate(frames * 8):  # repeated: past the initial capacity
        insts = [
            _inst(k + j, tuple(p for p in PARTS if p in ps)) for j, (_, ps, _) in enumerate(frame)
        ]
        names = [n for n, _, _ in frame]
        metrics = [m for _, _, m in frame]
        new.add_frame(k, names, insts, metrics)
        old.add_frame(k, names, insts, metrics)
        if takes and k % (takes * 17) == 5:
            got.append(new.take())
            want.append(old.take())
    got.append(new.take())
    want.append(old.take())
    for g, w in zip(got, want, strict=True):
        assert g.columns == w.columns
        for c in g.columns:
            if g[c].dtype == np.float64:
                assert np.array_equal(g[c].view(np.int64), w[c].view(np.int64)), c
            else:
                assert g[c].dtype == w[c].dtype and g[c].tolist() == w[c].tolist(), c


def _poses_strategy() -> st.SearchStrategy:
    """A frame of instances (name, parts) and its metric pose: None, or one number per
    cell of ``(instances, 3, ROW_LEN)`` (NaN cells, some with a payload of their own)."""
    from mistool.pose.measure import ROW_LEN

    cell = st.one_of(
        st.floats(allow_nan=False, allow_infinity=True),
        st.just(math.nan),
        st.integers(1, 2**20).map(
            lambda k: np.uint64(0x7FF8000000000000 | k).view(np.float64).item()
        ),
    )
    instances = st.lists(st.tuples(st.sampled_from("abc"), st.sets(st.sampled_from(PARTS))))
    return instances.flatmap(
        lambda insts: st.tuples(
            st.just(insts),
            st.one_of(
                st.none(),
                st.lists(
                    cell, min_size=len(insts) * 3 * ROW_LEN, max_size=len(insts) * 3 * ROW_LEN
                ),
            ),
        )
    )


@settings(max_examples=80, deadline=None)
@given(st.lists(_poses_strategy(), max_size=30), st.integers(0, 3))
def test_a_frames_metric_pose_array_gives_the_rows_of_its_dicts(frames, takes) -> None:
    """The metric pose as one array per frame (what the workers send) is copied into the
    rows as the same values given as a dict per part (``measure_instance``'s view of that
    array, the former form) are: the same tables, bit for bit (NaN payloads included),
    with frames without a pose, instances without parts and takes at random points."""
    from mistool.pose.measure import ROW_KEYS, ROW_LEN, SLOT_OF

    new, old = RowBuilder(fps=7.0), _FormerRowBuilder(fps=7.0)
    got: list[TrackTable] = []
    want: list[TrackTable] = []
    for k, (frame, cells) in enumerate(frames * 8):  # repeated: past the initial capacity
        insts = [
            _inst(k + j, tuple(p for p in PARTS if p in ps)) for j, (_, ps) in enumerate(frame)
        ]
        names = [n for n, _ in frame]
        poses = None if cells is None else np.array(cells).reshape(len(frame), 3, ROW_LEN)
        dicts = [
            None
            if poses is None
            else {
                p: dict(zip(ROW_KEYS, poses[j, SLOT_OF[p]].tolist(), strict=True))
                for p in inst.parts
            }
            for j, inst in enumerate(insts)
        ]
        new.add_frame(k, names, insts, poses)
        old.add_frame(k, names, insts, dicts)
        if takes and k % (takes * 17) == 5:
            got.append(new.take())
            want.append(old.take())
    got.append(new.take())
    want.append(old.take())
    for g, w in zip(got, want, strict=True):
        assert g.columns == w.columns
        for c in g.columns:
            if g[c].dtype == np.float64:
                assert np.array_equal(g[c].view(np.int64), w[c].view(np.int64)), c
            else:
                assert g[c].dtype == w[c].dtype and g[c].tolist() == w[c].tolist(), c


def test_a_metric_pose_array_of_another_shape_is_an_error() -> None:
    rows = RowBuilder(fps=25.0)
    with pytest.raises(ValueError, match="metrics: expected shape"):
        rows.add_frame(0, ["1", "2"], [_inst(0), _inst(1)], np.zeros((1, 3, 28)))


def test_a_parts_row_cells_given_with_it_are_its_row() -> None:
    """A part that carries its row's cells (``_row``: an array of a batch's cells and its
    row in it, a worker's parts as ``mistool.parallel.unpack_frames`` makes them) gives
    them as its box cells, beside parts without (read from their fields), with or
    without a pose, in runs of rows of several arrays written together."""
    from mistool.pose.measure import ROW_LEN
    from mistool.rows import _row_cells

    batches = [np.arange(k * 100.0, k * 100.0 + 3 * 14).reshape(3, 14) for k in (1, 2)]
    frames = [((0, 2), None), ((1, 0), (0, 1)), ((None, 0), (1, 1))]  # (batch, row)
    rows = RowBuilder(fps=1.0)
    want = []
    for index, picks in enumerate(frames):
        insts = []
        for k, pick in enumerate(picks):
            inst = _inst(index * 2 + k, ("shaft",))
            if pick is not None and pick[0] is not None:
                inst.parts["shaft"]._row = (batches[pick[0]], pick[1])  # type: ignore[attr-defined]
                want.append(batches[pick[0]][pick[1]].tolist())
            else:
                want.append(_row_cells(inst.parts["shaft"]))
            insts.append(inst)
        poses = None if index == 1 else np.zeros((len(insts), 3, ROW_LEN))
        rows.add_frame(index, ["a", "b"], insts, poses)
    dict_inst = _inst(9, ("shaft",))
    dict_inst.parts["shaft"]._row = (batches[1], 2)  # type: ignore[attr-defined]
    rows.add_frame(3, ["c"], [dict_inst], [{"shaft": {"quality": 0.5}}])
    want.append(batches[1][2].tolist())
    t = rows.take()
    assert [[float(t[c][i]) for c in BOX_COLUMNS] for i in range(t.num_rows)] == want


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 2), _poses_strategy(), _FRAME), max_size=30),
    st.integers(1, 6),
)
def test_rows_kept_in_lists_are_the_former_across_dict_frames_and_takes(frames, flush) -> None:
    """Frames whose pose is an array (their rows kept in lists, written ``FLUSH_ROWS``
    at a time) among frames of metric dicts and takes: the same tables as the former
    definition's, bit for bit."""
    from unittest import mock

    from mistool import rows as rows_module
    from mistool.pose.measure import ROW_KEYS, ROW_LEN, SLOT_OF

    new, old = RowBuilder(fps=7.0), _FormerRowBuilder(fps=7.0)
    got: list[TrackTable] = []
    want: list[TrackTable] = []
    with mock.patch.object(rows_module, "FLUSH_ROWS", flush):
        for k, (kind, (frame, cells), dict_frame) in enumerate(frames * 4):
            if kind == 2:
                got.append(new.take())
                want.append(old.take())
            elif kind == 1:
                insts = [
                    _inst(k + j, tuple(p for p in PARTS if p in ps))
                    for j, (_, ps, _) in enumerate(dict_frame)
                ]
                names = [n for n, _, _ in dict_frame]
                metrics = [m for _, _, m in dict_frame]
                new.add_frame(k, names, insts, metrics)
                old.add_frame(k, names, insts, metrics)
            else:
                insts = [
                    _inst(k + j, tuple(p for p in PARTS if p in ps))
                    for j, (_, ps) in enumerate(frame)
                ]
                names = [n for n, _ in frame]
                poses = None if cells is None else np.array(cells).reshape(-1, 3, ROW_LEN)
                dicts = [
                    None
                    if poses is None
                    else {
                        p: dict(zip(ROW_KEYS, poses[j, SLOT_OF[p]].tolist(), strict=True))
                        for p in inst.parts
                    }
                    for j, inst in enumerate(insts)
                ]
                new.add_frame(k, names, insts, poses)
                old.add_frame(k, names, insts, dicts)
            assert new.num_rows == old._n
        got.append(new.take())
        want.append(old.take())
    for g, w in zip(got, want, strict=True):
        assert g.columns == w.columns
        for c in g.columns:
            if g[c].dtype == np.float64:
                assert np.array_equal(g[c].view(np.int64), w[c].view(np.int64)), c
            else:
                assert g[c].dtype == w[c].dtype and g[c].tolist() == w[c].tolist(), c


def test_names_of_other_types_are_their_text() -> None:
    """An instrument name given as another type (an int, numpy's str) is coded as its
    ``str``: the same rows as the names given as text, with or without a pose, whichever
    type comes first."""
    from mistool.pose.measure import ROW_LEN

    poses = np.arange(2 * 3 * ROW_LEN, dtype=np.float64).reshape(2, 3, ROW_LEN)
    frames = [[1, "2"], [np.str_("1"), 2], ["1", np.int64(2)], [2, 1]]
    got, want = RowBuilder(fps=5.0), RowBuilder(fps=5.0)
    for k, names in enumerate(frames):
        for rows, as_given in ((got, names), (want, [str(n) for n in names])):
            rows.add_frame(k, as_given, [_inst(k), _inst(k + 1, ("clasper",))], poses)
            rows.add_frame(k, as_given[:1], [_inst(k + 2)], None)
    g, w = got.take(), want.take()
    assert g.columns == w.columns
    assert [type(n) for n in g["instrument"]] == [str] * g.num_rows
    for c in g.columns:
        assert np.array_equal(g[c], w[c], equal_nan=g[c].dtype == np.float64), c
