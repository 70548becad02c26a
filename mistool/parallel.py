"""Per-frame work and where it runs: in-process, a local process pool, or a Dask cluster.

The per-frame work (decode, Algorithm 1 boxes, instance grouping, metric pose, unknown
label values) is pure: :func:`observe_labels` depends only on the frame and the config.
It runs in worker processes on batches of consecutive frames (:func:`observe_batch`);
the caller consumes the results strictly in frame order (:func:`ordered_results`) and
does the sequential steps itself (identity across frames, sequence refinement). At most
``IN_FLIGHT_PER_WORKER`` batches per worker are submitted and not yet consumed, so
memory does not grow with the sequence length.

Where the work runs is a :class:`FramePool`:

- :class:`LocalPool`: a process pool on this machine (``forkserver`` processes, so a
  parent with threads, e.g. the viewer, forks nothing but a clean server; workers ignore
  Ctrl+C, the parent terminates them on any error or interrupt);
- :class:`DaskPool`: an existing Dask cluster (``distributed``, optional dependency).
  Workers read folder frames from their paths, so inputs must be on a filesystem the
  workers share with the client; frames of videos and arrays are decoded by the client
  and sent to the workers.

A folder frame is sent as its absolute path, a string (the worker decodes it); other
frames are decoded in the caller and sent as arrays.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import itertools
import os
import signal
import struct
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

import cv2
import numpy as np

from mistool import tracking
from mistool.config import Config
from mistool.errors import InputPathError, MistoolError
from mistool.forkserver import default_workers, worker_context
from mistool.model import PARTS, InstanceObservation, PartObservation, RotatedBox
from mistool.pngdecode import decode_png_runs, grey8
from mistool.pose.measure import ROW_LEN, SLOTS, measure_rows
from mistool.sequence import (
    VIDEO_TOLERANCE,
    FastPathGate,
    MaskSequence,
    VideoReader,
    VideoSource,
    check_pixels,
    read_label_image,
)
from mistool.tracking.instances import LabelRuns, scan_labels
from mistool.tracking.split import border_runs

#: Frames per task sent to a local worker process: enough to amortise a task's cost (the
#: caller's executor threads' wake-ups, pickling, the future; the worker's queue, lock
#: and pipe: together ~1 ms of CPU per task) against a frame's work (~0.4-1.3 ms of every
#: process's CPU). Against 16, 64 frames cut every process's CPU per frame with one
#: instrument from 0.61 to 0.56 ms (32: 0.59, 128: 0.57) and leave the crossing's
#: within 1% (1.38-1.41 either way): reused 2-worker pools, 3 runs each after a warm-up,
#: 3-4 alternating rounds at load 5-7 (the session's notes: docs/throughput.md).
LOCAL_BATCH_FRAMES = 64
#: Frames per task on a Dask cluster (a task's scheduling costs ~1 ms or more).
DASK_BATCH_FRAMES = 64
#: Seconds to wait for a Dask scheduler to answer before giving up.
DASK_CONNECT_TIMEOUT_S = 10.0
#: Seconds :meth:`LocalPool.close` waits for the worker processes being started.
_START_WAIT_S = 30.0
#: Batches in flight per worker: one running, one queued, so no worker waits on the caller.
IN_FLIGHT_PER_WORKER = 2
#: Frames the caller may have identified and not yet turned into rows while the pieces of
#: a split blob are measured in a worker, per worker (``mistool.api.identified``).
PENDING_FRAMES_PER_WORKER = 32
#: ``defer_below`` value that leaves every frame's metric pose to the caller (in-process
#: runs: the pose is measured once the identity step has run, never for a blob it splits).
DEFER_ALWAYS = 1 << 30


# --- the per-frame work -------------------------------------------------------------------


@dataclass
class FrameResult:
    """One frame's per-frame results (everything but the identities)."""

    instances: list[InstanceObservation]
    """``mistool.tracking.observe_frame``'s instances."""
    metrics: np.ndarray | None
    """The metric pose, ``(instances, 3, ROW_LEN)`` float64: instance ``k``'s part
    ``p`` in row ``[k, SLOT_OF[p]]`` (:func:`mistool.pose.measure.measure_rows`); None
    without camera / metric pose, and while ``deferred``."""
    unknown: np.ndarray
    """Label values present that the config does not know (1-D int64)."""
    shape: tuple[int, int]
    """``(H, W)`` of the frame."""
    corrupt: bool = False
    """A mask video frame decoded in a worker that looks like decoded garbage
    (:data:`mistool.sequence.GARBAGE_FRACTION`)."""
    runs: list[list[tuple[np.ndarray, int]]] | None = None
    """Per instance, :func:`mistool.tracking.split.border_runs` (where its shaft enters
    the view), computed here for the caller's identity step (None when that step does
    not need them: every instance labelled)."""
    deferred: bool = False
    """The metric pose was left to the caller (``metrics`` is None): it measures the
    instances the identity step keeps (:func:`measure_frames`), so the pose of a blob
    that the identity step splits is never measured (see :func:`observe_labels`)."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        # sent alone (a batch's are sent together: FrameResults)
        return _frame_result, (pack_frames([self]),)

    def replaced(self, **changes: Any) -> FrameResult:
        """``dataclasses.replace(self, **changes)``: the same fields and values, without
        its walk over the fields at each call (~5 us; the caller's identity step does it
        for each frame it splits or whose pose was deferred)."""
        unknown = changes.keys() - self.__dict__.keys()
        if unknown:
            raise TypeError(f"FrameResult.replaced: no field {sorted(unknown)[0]!r}")
        new = object.__new__(FrameResult)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new


def _frame_result(packed: tuple[Any, ...]) -> FrameResult:
    return unpack_frames(packed)[0]


class FrameResults(list[FrameResult]):
    """A batch's results as :func:`observe_batch` returns them: a list that a worker
    sends as a few flat arrays for the whole batch (:func:`pack_frames`); it unpickles
    to a plain list of :class:`FrameResult` with the same values."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return unpack_frames, (pack_frames(self),)


#: Columns of :func:`pack_frames`' integer tables.
_FRAME_INTS = 8  # instances, H, W, corrupt, deferred, unknown values, border runs, poses
_INST_INTS = 9  # area, bbox x, y, w, h, image shape given, its H, W, parts
_PART_INTS = 6  # part (index in PARTS), area, offset x, y, mask h, w


def pack_frames(results: list[FrameResult]) -> tuple[Any, ...]:
    """Several frames' results as a few flat values for pickling (a batch sent by a
    worker): every number in one integer and one float table per level (frame,
    instance, part), the masks' bits in one buffer (each part's ``np.packbits`` of its
    mask, from a byte boundary: a fitted part's as the kernel set them from its runs),
    the unknown values, border runs and metric poses concatenated; the labels as they
    are. :func:`unpack_frames` gives the same results back."""
    frames: list[tuple[int, ...]] = []
    inst_i: list[int] = []  # (the tables' cells in a row, reshaped at the end)
    inst_f: list[float] = []
    part_i: list[int] = []
    part_f: list[float] = []
    corners: list[np.ndarray] = []
    masks: list[np.ndarray] = []
    labels: list[str | None] = []
    run_counts: list[int] = []
    run_lengths: list[int] = []
    run_ends: list[np.ndarray] = []
    unknown = []
    poses = []
    code = _PART_CODE
    for r in results:
        instances, metrics, border = r.instances, r.metrics, r.runs
        frames.append(
            (
                len(instances),
                *r.shape,
                r.corrupt,
                r.deferred,
                len(r.unknown),
                border is not None,
                -1 if metrics is None else len(metrics),
            )
        )
        unknown.append(r.unknown)
        if metrics is not None:
            poses.append(metrics)
        for inst in instances:
            shape = inst.image_shape
            parts = inst.parts
            inst_i += (inst.area_px, *inst.bbox_xywh, shape is not None, *(shape or (0, 0)))
            inst_i.append(len(parts))
            inst_f += inst.centroid_px
            labels.append(inst.label)
            for name, p in parts.items():
                b, mask = p.box, p.mask
                part_i += (code[name], p.area_px, *p.offset, *mask.shape)
                part_f += (b.cx, b.cy, b.length, b.width, b.angle_deg)
                corners.append(p.corners)
                packed = p.__dict__.get("_bits")  # (the fit's, set from its runs)
                if packed is not None and packed[0] is mask:
                    masks.append(packed[1])
                else:
                    masks.append(np.packbits(mask.reshape(-1)))
        if border:
            for runs in border:
                run_counts.append(len(runs))
                for ends, length in runs:
                    run_lengths.append(length)
                    run_ends.append(ends)
    return (
        np.array(frames, np.int64).reshape(-1, _FRAME_INTS),
        np.array(inst_i, np.int64).reshape(-1, _INST_INTS),
        np.array(inst_f, np.float64).reshape(-1, 2),
        np.array(part_i, np.int64).reshape(-1, _PART_INTS),
        np.array(part_f, np.float64).reshape(-1, 5),
        np.concatenate(corners).reshape(-1, 4, 2) if corners else np.zeros((0, 4, 2)),
        np.concatenate(masks) if masks else np.zeros(0, np.uint8),
        labels,
        np.concatenate(poses) if poses else _NO_POSES,
        np.concatenate(unknown).astype(np.int64) if unknown else np.zeros(0, np.int64),
        np.array(run_counts, np.int64),
        np.array(run_lengths, np.int64),
        np.concatenate(run_ends, dtype=np.float64).reshape(-1, 3, 2) if run_ends else _NO_ENDS,
    )


_NO_ENDS = np.zeros((0, 3, 2))


_PART_CODE = {name: k for k, name in enumerate(PARTS)}
_NO_POSES = np.zeros((0, len(SLOTS), ROW_LEN))


class MeasureWork(list[tuple[list[InstanceObservation], tuple[int, int]]]):
    """The ``(instances, shape)`` of frames whose pose a worker is to measure
    (:func:`measure_frames`), sent as a batch's results are (:func:`pack_frames`: the
    masks as bits, an eighth of their bytes); unpickles to a plain list of equal
    values."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        frames = [FrameResult(inst, None, _NO_VALUES, shape) for inst, shape in self]
        return _unpack_work, (pack_frames(frames),)


_NO_VALUES = np.zeros(0, np.int64)


def _unpack_work(
    packed: tuple[Any, ...],
) -> list[tuple[list[InstanceObservation], tuple[int, int]]]:
    return [(r.instances, r.shape) for r in unpack_frames(packed)]


def unpack_frames(packed: tuple[Any, ...]) -> list[FrameResult]:
    """The results :func:`pack_frames` packed (every value, dtype and shape; a mask is a
    C-contiguous bool array, unpacked here for the frames and parts whose masks the
    caller's identity step reads: every part of a deferred frame, the head parts of a
    frame with two instruments or more (the heads' hand-over reads them), in one
    ``unpackbits`` for the batch; the others when first read, :class:`_SentPart`)."""
    frames, inst_i, inst_f, part_i, part_f, corners, bits, labels, poses, *rest = packed
    unknown, run_counts, run_lengths, run_ends = rest
    if not len(frames):
        return []
    at, lo, hi = _mask_bits(frames, inst_i, part_i)
    masks = _eager_masks(bits, at, lo, hi, part_i)
    inst_rows, inst_xy = inst_i.tolist(), inst_f.tolist()
    part_rows, at_list = part_i.tolist(), at.tolist()
    # each part's row cells (box, area, corners: rows.BOX_COLUMNS) for the caller's rows,
    # which copy them from this array (a part's ``_row``: the array and its row in it)
    cells = np.concatenate(
        [part_f, part_i[:, 1:2].astype(np.float64), corners.reshape(-1, 8)], axis=1
    )
    boxes = part_f.tolist()
    corner_rows = list(corners)  # (views, as corners[p])
    run_n, run_len, ends = run_counts.tolist(), run_lengths.tolist(), list(run_ends)
    new = object.__new__
    out = []
    i = p = u = r = e = m = 0  # next instance, part, unknown value, runs list, run, pose
    for count, h, w, corrupt, deferred, n_unknown, has_runs, n_poses in frames.tolist():
        instances = []
        for area, x, y, bw, bh, given, sh, sw, n_parts in inst_rows[i : i + count]:
            own: dict[str, PartObservation] = {}
            for _ in range(n_parts):
                code, parea, ox, oy, mh, mw = part_rows[p]
                box = new(RotatedBox)
                d = box.__dict__
                d["cx"], d["cy"], d["length"], d["width"], d["angle_deg"] = boxes[p]
                obj = new(_SentPart)
                name = PARTS[code]
                obj.__dict__.update(
                    {"part": name, "box": box, "corners": corner_rows[p], "area_px": parea,
                     "offset": (ox, oy), "_row": (cells, p)}
                )  # fmt: skip
                mask = masks.get(p)
                if mask is not None:
                    obj.__dict__["mask"] = mask
                else:
                    obj.__dict__["_packed"] = (bits, at_list[p], (mh, mw))
                own[name] = obj
                p += 1
            inst = new(InstanceObservation)
            inst.__dict__.update(
                {"label": labels[i], "parts": own, "centroid_px": tuple(inst_xy[i]),
                 "area_px": area, "bbox_xywh": (x, y, bw, bh),
                 "image_shape": (sh, sw) if given else None}
            )  # fmt: skip
            instances.append(inst)
            i += 1
        border = None
        if has_runs:
            border = []
            for _ in range(count):
                k = run_n[r]
                border.append(list(zip(ends[e : e + k], run_len[e : e + k], strict=True)))
                e += k
                r += 1
        metrics = None
        if n_poses >= 0:
            metrics = poses[m : m + n_poses]
            m += n_poses
        result = new(FrameResult)
        result.__dict__.update(
            {"instances": instances, "metrics": metrics,
             "unknown": unknown[u : u + n_unknown] if n_unknown else _NO_VALUES,
             "shape": (h, w), "corrupt": bool(corrupt), "runs": border,
             "deferred": bool(deferred)}
        )  # fmt: skip
        out.append(result)
        u += n_unknown
    return out


def _mask_bits(
    frames: np.ndarray, inst_i: np.ndarray, part_i: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per part of a packed batch: the first bit of its mask in the bits' buffer (each
    part's from a byte boundary, as :func:`pack_frames` packs them), and the bytes
    unpacked at once to read it (:func:`unpack_frames`; empty when it is not): its own
    bytes for a head part of a deferred frame or of a frame with two instances or more
    (the split's and the heads' hand-over read them). A shaft is left packed: the caller
    reads a blob's shaft as runs from its bits (:meth:`mistool.tracking.split.BlobPixels.
    shaft_runs`), an instrument's seen apart never."""
    counts = frames[:, 0]
    inst_end = np.cumsum(counts)
    part_end = np.zeros(len(inst_i) + 1, np.int64)
    np.cumsum(inst_i[:, 8], out=part_end[1:])
    first = part_end[inst_end - counts]  # each frame's first part
    parts = part_end[inst_end] - first  # and its number of parts
    byte_end = np.zeros(len(part_i) + 1, np.int64)  # each part's bytes end (from 1)
    np.cumsum(-(-(part_i[:, 4] * part_i[:, 5]) // 8), out=byte_end[1:])
    of = np.repeat(np.arange(len(frames)), parts)  # each part's frame
    at = 8 * byte_end[:-1]
    eager = ((frames[of, 4] != 0) | (counts[of] > 1)) & (part_i[:, 0] != _SHAFT)
    lo = byte_end[:-1]
    hi = np.where(eager, byte_end[1:], lo)
    return at, lo, hi


def _eager_masks(
    bits: np.ndarray, at: np.ndarray, lo: np.ndarray, hi: np.ndarray, part_i: np.ndarray
) -> dict[int, np.ndarray]:
    """The masks of the parts with bytes ``lo .. hi - 1`` to unpack (:func:`_mask_bits`),
    by part: those bytes (each run of parts whose bytes follow each other as one
    range) unpacked in one ``unpackbits``, each mask a (h, w) view of it."""
    which = np.flatnonzero(hi > lo)
    if not len(which):
        return {}
    lo, hi = lo[which], hi[which]
    new = np.ones(len(which), np.bool_)  # parts whose bytes start a range
    new[1:] = lo[1:] != hi[:-1]
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], len(which)) - 1  # each range's last part
    span = hi[ends] - lo[starts]
    base = np.cumsum(span) - span  # each range's first byte in those concatenated
    pieces = [bits[a:b] for a, b in zip(lo[starts].tolist(), hi[ends].tolist(), strict=True)]
    flat = np.unpackbits(np.concatenate(pieces)).view(np.bool_)
    run = np.cumsum(new) - 1  # each part's range
    first = (8 * (base[run] - lo[starts][run]) + at[which]).tolist()
    h, w = part_i[which, 4].tolist(), part_i[which, 5].tolist()
    return {
        k: flat[f : f + mh * mw].reshape(mh, mw)
        for k, f, mh, mw in zip(which.tolist(), first, h, w, strict=True)
    }


class _SentPart(PartObservation):
    """A part as a worker sent it: a :class:`~mistool.model.PartObservation` with the
    same values, made without its ``__init__`` (the worker made and checked them), with
    its row's cells (``_row``: the batch's cells and its row there, :mod:`mistool.rows`);
    its mask, when not unpacked with the batch's (:func:`unpack_frames`), is unpacked at
    its first use (the caller's identity step reads the masks of a blob it splits, mostly
    in deferred frames, and of the heads it may hand over; the shaft of an instrument
    seen apart, most of a frame's bits, never). Pickled as a plain ``PartObservation``."""

    @functools.cached_property
    def mask(self) -> np.ndarray:
        """(h, w) bool crop of the part's pixels, unpacked now (then kept)."""
        return _part_mask(*self.__dict__.pop("_packed"))

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return PartObservation, (
            self.part, self.box, self.corners, self.area_px, self.mask, self.offset,
        )  # fmt: skip


_SHAFT = PARTS.index("shaft")


def _part_mask(bits: np.ndarray, at: int, shape: tuple[int, int]) -> np.ndarray:
    """The (h, w) bool mask of the ``h * w`` bits of ``bits`` from bit ``at`` on."""
    n = shape[0] * shape[1]
    flat = np.unpackbits(bits[at // 8 : -(-(at + n) // 8)]).view(np.bool_)
    return flat[at % 8 : at % 8 + n].reshape(shape)


_T = TypeVar("_T")


def _made(cls: type[_T], **values: Any) -> _T:
    """A ``cls`` (a frozen dataclass) holding ``values``, made without its ``__init__``
    and checks (values made and checked as such objects already)."""
    obj = object.__new__(cls)
    obj.__dict__.update(values)
    return obj


def metric_pose(metric: bool, config: Config) -> bool:
    """Whether the per-frame metric pose runs: asked for (``metric``) and the config has a
    camera."""
    return metric and config.camera is not None


def measure(
    inst: InstanceObservation,
    shape: tuple[int, int],
    config: Config,
    metric: bool,
    out: np.ndarray | None = None,
) -> np.ndarray | None:
    """The per-frame metric pose of one instance (:func:`mistool.pose.measure.measure_rows`:
    ``(3, ROW_LEN)``, into ``out`` when given), or None when the metric pose does not
    run (see :func:`metric_pose`)."""
    if not metric or config.camera is None:
        return None
    name = inst.label
    return measure_rows(
        inst,
        shape,
        config.camera,
        config.shaft_diameter_for(name) if name else config.shaft_diameter_mm,
        config.clasper_length_for(name) if name else config.clasper_length_mm,
        out,
    )


def measure_all(
    instances: list[InstanceObservation], shape: tuple[int, int], config: Config, metric: bool
) -> np.ndarray | None:
    """:func:`measure` of each instance, in one ``(instances, 3, ROW_LEN)`` array
    (:attr:`FrameResult.metrics`), or None when the metric pose does not run."""
    if not metric or config.camera is None:
        return None
    out = np.empty((len(instances), len(SLOTS), ROW_LEN))
    for k, inst in enumerate(instances):
        measure(inst, shape, config, metric, out[k])
    return out


def measure_frames(
    frames: list[tuple[list[InstanceObservation], tuple[int, int]]], config: Config, metric: bool
) -> list[np.ndarray | None]:
    """:func:`measure_all` of several frames' ``(instances, shape)`` (a task: the pieces
    of the blobs the identity step split and the instances of deferred frames, measured
    in a worker while the caller goes on with the next frames; several frames per task,
    since each task costs the caller an inter-process round trip)."""
    return [measure_all(instances, shape, config, metric) for instances, shape in frames]


def unknown_values(
    labels: np.ndarray | None,
    config: Config,
    lossy: bool = False,
    bounds: tuple[int, int, int, int] | None = None,
    runs: LabelRuns | None = None,
) -> np.ndarray:
    """``tracking.unknown_values``, on the values present, within ``bounds`` (the non-zero
    pixels' ``(x, y, w, h)``, :func:`mistool.tracking.instances.foreground_bounds`) when
    given: 0 is never unknown, so the pixels outside do not matter. An 8-bit image's
    values are counted from its runs (:func:`mistool.tracking.instances.scan_labels`)
    when given, else with an 8-bit histogram (~7x faster than scanning the image in
    numpy). ``labels`` may be None when ``runs`` are those of an 8-bit image (a PNG
    decoded straight to runs: :func:`_load`).

    In a mask video (``lossy``) the codec smears values around every edge, so a value
    counts only where it covers at least ``min_area_px`` pixels of the frame, and values
    up to :data:`~mistool.sequence.VIDEO_TOLERANCE` are background."""
    if runs is not None:
        bounds = runs.bounds
    if bounds is not None:
        x, y, w, h = bounds
        if w == 0 or h == 0:
            return np.zeros(0, np.int64)
        if labels is not None:
            labels = labels[y : y + h, x : x + w]
    if labels is None or (labels.dtype == np.uint8 and labels.ndim == 2):
        if runs is not None:  # (the values counted and picked in one compiled pass)
            least = max(config.min_area_px, 1) if lossy else 1
            lut = _unknown_u8(config, lossy)
            return _values_present()(runs.rv, runs.rx0, runs.rx1, runs.n, lut, least)
        if labels is not None:
            hist = cv2.calcHist([labels], [0], None, [256], [0, 256]).ravel()
        else:
            raise ValueError("unknown_values: give the labels or their runs")
        if lossy:
            enough = (hist >= max(config.min_area_px, 1)) & _unknown_u8(config, lossy)
        else:  # (pixel counts: present where not zero)
            enough = hist * _unknown_u8(config, lossy)
        return np.flatnonzero(enough).astype(np.int64, copy=False)
    return np.asarray(tracking.unknown_values(labels, config))


def _values_present() -> Any:
    """``kernels.instances.values_present``, imported at the first 8-bit frame's runs
    (an import statement in the function: ~0.7 us a frame)."""
    if not _VALUES_PRESENT:
        from mistool.kernels.instances import values_present

        _VALUES_PRESENT.append(values_present)
    return _VALUES_PRESENT[0]


_VALUES_PRESENT: list[Any] = []


def _unknown_u8(config: Config, lossy: bool) -> np.ndarray:
    """(256,) bool: the 8-bit values ``tracking.unknown_values`` calls unknown (in a
    mask video, none up to :data:`~mistool.sequence.VIDEO_TOLERANCE`); kept for the last
    config asked (a batch's frames share theirs)."""
    global _UNKNOWN_U8
    have = _UNKNOWN_U8  # (one read: another thread may replace it)
    if have[0] is config and have[1] == lossy:
        return have[2]
    every = np.arange(256, dtype=np.uint8)[None, :]
    lut = np.zeros(256, np.bool_)
    lut[np.asarray(tracking.unknown_values(every, config))] = True
    if lossy:
        lut[: VIDEO_TOLERANCE + 1] = False
    _UNKNOWN_U8 = (config, lossy, lut)
    return lut


_UNKNOWN_U8: tuple[Any, bool, Any] = (None, False, None)


def observe_labels(
    labels: np.ndarray | LabelRuns,
    config: Config,
    metric: bool,
    lossy: bool = False,
    defer_below: int = 0,
) -> FrameResult:
    """The per-frame work on a decoded label image, or on the runs of an 8-bit one
    (:func:`_load`: a PNG decoded straight to its runs); pure, thread- and process-safe.

    ``defer_below``: with the metric pose on, a frame with instances but fewer than this
    many is returned ``deferred`` (no pose measured): fewer instances than instruments
    recently seen is the sign of a blob of crossing tools, which the identity step will
    likely split, its pose then thrown away. Only where the work is done changes: the
    caller measures the deferred frames' instances after the identity step, with the
    same function, so the output is the same whatever ``defer_below``."""
    if isinstance(labels, LabelRuns):
        runs, pixels = labels, None
    else:  # one pass: shared by the instances and the unknown values
        runs, pixels = scan_labels(labels), labels
    instances = tracking.observe_frame(pixels, config, runs=runs)
    shape = runs.shape
    unknown = unknown_values(pixels, config, lossy, runs=runs)
    # the identity step's border runs, here rather than in the (sequential) caller
    runs_in = (
        [border_runs(i) for i in instances] if any(i.label is None for i in instances) else None
    )
    if metric and config.camera is not None and 0 < len(instances) < defer_below:
        return FrameResult(instances, None, unknown, shape, runs=runs_in, deferred=True)
    metrics = measure_all(instances, shape, config, metric)
    return FrameResult(instances, metrics, unknown, shape, runs=runs_in)


@dataclass(frozen=True)
class VideoSpan:
    """Frames ``start .. stop - 1`` of a mask video, decoded by the worker."""

    source: VideoSource
    start: int
    stop: int


@dataclass(frozen=True)
class Batch:
    """Consecutive frames of one sequence, as sent to a worker (picklable)."""

    names: tuple[str, ...]
    """Frame names, for error messages (a file name, ``video#i``, ``frame i``)."""
    items: tuple[str | Path | np.ndarray | VideoSpan, ...]
    """Per frame: the label image file's path (decoded by the worker; :func:`batches`
    gives absolute paths as strings) or the label array; or one :class:`VideoSpan` for
    all the names (fewer frames at the end of the video)."""
    config: Config
    metric: bool
    lossy: bool
    defer_below: int = 0
    """See :func:`observe_labels` (0: every frame's pose measured in the worker); when
    above 0, raised within the batch to the most instances of its earlier frames
    (:func:`_raised`)."""


# One fast-path gate per worker process and folder (the caller's gate is not shared),
# keyed by the folder's path as a string (a ``Path``'s parent and hash cost ~2 us a frame).
_GATES: dict[str, FastPathGate] = {}


def _load(item: str | Path | np.ndarray, config: Config) -> np.ndarray | LabelRuns:
    """A frame's label image; an 8-bit grey PNG (grey labels) straight to its runs
    (:func:`mistool.pngdecode.decode_png_runs`: the image itself is never written)."""
    if isinstance(item, np.ndarray):
        return item
    path = os.fspath(item)  # (a Path keeps its string)
    folder = path.rpartition(os.sep)[0]
    gate = _GATES.get(folder)
    if gate is None:
        gate = _GATES[folder] = FastPathGate()
    if not config.colour_masks and gate.open and folder not in _NOT_GREY8:
        data = _read(path)
        if not grey8(data):  # (its folder's other files are read as they are)
            _NOT_GREY8.add(folder)
        else:
            if data[12:16] == b"IHDR":  # check_pixels(header_size(data), ...), inline
                w, h = _IHDR_SIZE.unpack_from(data, 16)
                if not (w and h and w * h <= config.max_pixels):
                    check_pixels((w, h), path, config.max_pixels)
            got = decode_png_runs(data, config.max_pixels)
            gate.record(got is not None)
            if got is None:  # OpenCV decides (and reports)
                return read_label_image(Path(path), gate=_OPENCV, max_pixels=config.max_pixels)
            bounds, ry, rx0, rx1, rv, n, shape = got
            return _made(  # (a frozen dataclass's __init__: ~1.5 us more a frame)
                LabelRuns, bounds=bounds, ry=ry, rx0=rx0, rx1=rx1, rv=rv, n=n, shape=shape,
                dtype=_UINT8,
            )  # fmt: skip
    return read_label_image(
        Path(path), colour=config.colour_masks, gate=gate, max_pixels=config.max_pixels
    )


def _read(path: str) -> bytes:
    """The file's bytes, as ``Path.read_bytes`` reads them without its file objects
    (~4 us against ~10 a mask); an error as ``read_label_image`` gives it."""
    try:
        fd = os.open(path, _READ_FLAGS)
        try:
            data = os.read(fd, _READ_PIECE)
            if data:  # to the end (a mask's file: one more read, empty)
                more = os.read(fd, _READ_PIECE)
                if more:
                    pieces = [data, more]
                    while more := os.read(fd, _READ_PIECE):
                        pieces.append(more)
                    data = b"".join(pieces)
        finally:
            os.close(fd)
    except OSError as exc:  # (read_label_image's error)
        raise InputPathError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return data


#: Bytes asked for by each read of a frame's file (masks are a few KB).
_READ_PIECE = 16384
_READ_FLAGS = os.O_RDONLY | getattr(os, "O_BINARY", 0) | getattr(os, "O_CLOEXEC", 0)
_IHDR_SIZE = struct.Struct(">II")
#: Folders whose files are not 8-bit grey PNGs (read by ``read_label_image`` alone).
_NOT_GREY8: set[str] = set()
#: A closed fast-path gate: straight to OpenCV.
_OPENCV = FastPathGate(patience=0)
_UINT8 = np.dtype(np.uint8)


# The video a worker process decodes spans of (one at a time: a new video closes the last).
_READER: list[VideoReader] = []


def _video_span(span: VideoSpan) -> list[tuple[np.ndarray, bool]]:
    if not _READER or _READER[0].source != span.source:
        for r in _READER:
            r.close()
        _READER[:] = [VideoReader(span.source)]
    return _READER[0].read(span.start, span.stop)


def _raised(below: int, result: FrameResult) -> int:
    """The next frame's ``defer_below`` in a batch: at least the instances of this frame
    when the batch defers at all (``below`` > 0: the caller's hint is one or more batches
    old, so a frame with fewer instances than an earlier frame of its own batch is the
    sign of a blob too)."""
    return max(below, len(result.instances)) if below > 0 else below


def _observe_span(batch: Batch, span: VideoSpan, metric: bool) -> list[FrameResult]:
    out = FrameResults()
    below = batch.defer_below
    for labels, corrupt in _video_span(span):
        result = observe_labels(labels, batch.config, metric, batch.lossy, below)
        below = _raised(below, result)
        result.corrupt = corrupt
        out.append(result)
    return out


def observe_batch(batch: Batch) -> list[FrameResult]:
    """The per-frame work of a batch (runs in a worker).

    Raises:
        MistoolError: a frame that cannot be read or is not a label image; the message
            names the frame.
    """
    metric = metric_pose(batch.metric, batch.config)
    if batch.items and isinstance(batch.items[0], VideoSpan):
        return _observe_span(batch, batch.items[0], metric)
    out = FrameResults()
    below = batch.defer_below
    for name, item in zip(batch.names, batch.items, strict=True):
        try:
            assert not isinstance(item, VideoSpan)
            labels = _load(item, batch.config)
            out.append(observe_labels(labels, batch.config, metric, batch.lossy, below))
            below = _raised(below, out[-1])
        except MistoolError as exc:
            where = os.fspath(item) if isinstance(item, (str, Path)) else name
            if where in str(exc):
                raise
            raise type(exc)(f"{where}: {exc}") from None
    return out


def batches(
    seq: MaskSequence,
    metric: bool,
    batch_frames: int,
    *,
    video_spans: bool = False,
    defer_below: Callable[[], int] | None = None,
) -> Iterator[tuple[list[str], Batch]]:
    """The sequence's frames in batches of ``batch_frames``: ``(frame names, batch)``.

    Folder frames go as absolute paths; other frames are decoded here (in order), except
    with ``video_spans`` the frames of a mask video (``seq.video``): each batch is then a
    :class:`VideoSpan` the worker decodes itself, without end (the batch holding the
    video's last frame comes back short: :func:`ordered_results` stops there; then
    :func:`mistool.sequence.finish_video`).

    ``defer_below``: called as each batch is made (just before it is submitted), gives
    the batch's ``defer_below`` (:func:`observe_labels`); None: 0, never deferred."""
    hint = defer_below or _never

    def batch(names: list[str], items: list[str | np.ndarray | VideoSpan]) -> Batch:
        return Batch(tuple(names), tuple(items), seq.config, metric, seq.lossy, hint())

    if video_spans and seq.video is not None:  # without end: see above
        name = seq.video.path.name
        for start in itertools.count(0, batch_frames):
            stop = start + batch_frames
            span_names = [f"{name}#{i}" for i in range(start, stop)]
            yield span_names, batch(span_names, [VideoSpan(seq.video, start, stop)])
    names: list[str] = []
    items: list[str | np.ndarray | VideoSpan] = []
    folder = seq.path.resolve() if seq.kind == "folder" and seq.path is not None else None
    # a folder frame's absolute path as a string: no Path made here per frame, none
    # pickled, none parsed again in the worker (~10 us a frame in all)
    prefix = os.path.join(folder, "") if folder is not None else None
    for frame in seq.frames():
        names.append(frame.name)
        items.append(prefix + frame.name if prefix is not None else frame.load())
        if len(names) == batch_frames:
            yield names, batch(names, items)
            names, items = [], []
    if names:
        yield names, batch(names, items)


def _never() -> int:
    return 0


def _pairs(
    names: list[str], batch: Batch, results: list[FrameResult]
) -> list[tuple[str, FrameResult]]:
    """``(name, result)`` of a batch; a video span may come back short (its end)."""
    if batch.items and isinstance(batch.items[0], VideoSpan):
        return list(zip(names, results, strict=False))
    return list(zip(names, results, strict=True))


# --- where the work runs ------------------------------------------------------------------


class ResultFuture(Protocol):
    """What :meth:`FramePool.submit` returns (a concurrent or a Dask future)."""

    def result(self) -> Any: ...

    def cancel(self) -> Any: ...

    def done(self) -> bool: ...


class FramePool(Protocol):
    """Somewhere to run :func:`observe_batch` (see the module docstring)."""

    workers: int
    """Worker processes (sets how many batches are kept in flight)."""
    batch_frames: int
    """Frames per task."""

    def submit(self, fn: Callable[..., Any], *args: Any) -> ResultFuture: ...

    def close(self) -> None: ...


def _init_worker() -> None:
    # The parent handles Ctrl+C and terminates the workers; a worker's own traceback on
    # SIGINT would only clutter the terminal. OpenCV's threads inside each worker would
    # compete with the other workers for the same cores.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    cv2.setNumThreads(1)
    threading.Thread(target=_exit_with_parent, name="mistool-watchdog", daemon=True).start()


def _exit_with_parent() -> None:
    """Exit this worker as soon as the process that started it is gone.

    A worker waits for tasks on a queue whose write end it also holds, so it would wait
    forever if the parent were killed (SIGKILL, a crash, a viewer stopping its tracking
    process) before it could terminate its workers."""
    from multiprocessing import connection, parent_process

    parent = parent_process()
    if parent is None or parent.sentinel is None:
        return
    connection.wait([parent.sentinel])
    os._exit(1)


def _unblock_results(results: Any) -> None:
    """Give the executor's result pipe an end of file once its workers are terminated.

    A worker terminated while writing a result leaves half a message in the pipe; the
    executor's manager thread then waits in ``recv`` for the rest forever (this process
    holds the pipe's write end too, so no end of file comes), and the interpreter joins
    that thread at exit: a Ctrl+C'd ``mistool track --workers 2`` hung after printing
    "interrupted" (about 1 run in 15). With the write end closed, ``recv`` fails, the
    manager sees a broken pool and exits."""
    writer = getattr(results, "_writer", None)
    if writer is not None:
        with contextlib.suppress(OSError):
            writer.close()


def _is_cancelled_future_race(args: Any) -> bool:
    """Whether an uncaught thread exception is Python's process pool marking an already
    cancelled future failed: its manager thread (``_ExecutorManagerThread``), finding the
    pool broken by the workers we terminated, calls ``set_exception`` on every pending
    future, and one cancelled meanwhile (the consumer stopping at a Ctrl+C) raises
    ``InvalidStateError`` (Python 3.11). Nothing is lost: the run is being stopped."""
    from concurrent.futures import InvalidStateError

    if args.exc_type is not InvalidStateError or type(args.thread).__name__ != (
        "_ExecutorManagerThread"
    ):
        return False
    tb = args.exc_traceback
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    return tb is not None and tb.tb_frame.f_code.co_name in ("set_exception", "set_result")


_previous_excepthook: Any = None


def _quiet_cancelled_future_race() -> None:
    """Install (once) a ``threading.excepthook`` that drops :func:`_is_cancelled_future_race`
    (its traceback was printed under "mistool: interrupted", or after stderr was closed:
    "lost sys.stderr") and passes everything else to the hook it replaces."""
    global _previous_excepthook
    if _previous_excepthook is not None:
        return
    _previous_excepthook = threading.excepthook

    def hook(args: Any) -> None:
        if not _is_cancelled_future_race(args):
            _previous_excepthook(args)

    threading.excepthook = hook


class LocalPool:
    """A pool of ``workers`` local processes (use as a context manager, or call close).

    The worker processes start at once, in a thread (the first waits for the fork server
    to start and import the per-frame code: ~0.5 s, longer on a loaded machine); until
    they are up (:meth:`warming`), :func:`ordered_results` does the first frames' work in
    the caller instead of waiting."""

    def __init__(self, workers: int, batch_frames: int = LOCAL_BATCH_FRAMES) -> None:
        if workers < 1:
            raise ValueError(f"LocalPool: workers = {workers}, must be >= 1")
        self.workers = workers
        self.batch_frames = batch_frames
        ctx = worker_context()
        self._executor: ProcessPoolExecutor | None = ProcessPoolExecutor(
            max_workers=workers, mp_context=ctx, initializer=_init_worker
        )
        self._closing = False
        self._started = threading.Event()  # every worker process started (or given up)
        self._up = threading.Event()  # ... and each has answered
        threading.Thread(target=self._start_workers, name="mistool-pool-start", daemon=True).start()

    def _start_workers(self) -> None:
        """One trivial task per worker: the executor starts a process for each.

        Ctrl+C is blocked in this thread first: the fork server, the executor's thread
        and the workers started from here inherit the signal mask, so a Ctrl+C while the
        fork server starts (before it ignores SIGINT, once its imports are done) no longer
        prints a ``KeyboardInterrupt`` traceback from it (2 of 20 runs of
        ``scripts/stress_ctrl_c.py``); the caller's main thread still gets the Ctrl+C."""
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        futures = []
        try:
            for _ in range(self.workers):
                ex = self._executor
                if ex is None or self._closing:
                    return
                futures.append(ex.submit(os.getpid))
            self._started.set()
            for f in futures:
                f.result()
        except Exception:  # noqa: BLE001 - closed or broken meanwhile: the caller sees it
            return
        finally:
            self._started.set()
            self._up.set()

    def warming(self) -> bool:
        """Whether the worker processes are still starting."""
        return not self._up.is_set()

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future[Any]:
        if self._executor is None:
            raise RuntimeError("LocalPool: used after close()")
        return self._executor.submit(fn, *args)

    def close(self, *, terminate: bool = False) -> None:
        """Stop the workers (``terminate``: at once, abandoning running tasks)."""
        self._closing = True
        self._started.wait(timeout=_START_WAIT_S)  # no process started after the count
        ex, self._executor = self._executor, None
        if ex is None:
            return
        procs = list((getattr(ex, "_processes", None) or {}).values())
        results = getattr(ex, "_result_queue", None)  # shutdown() forgets it
        ex.shutdown(wait=not terminate, cancel_futures=True)
        if terminate:
            _quiet_cancelled_future_race()
            for p in procs:
                if p.is_alive():
                    p.terminate()
            for p in procs:
                p.join(timeout=5)
            _unblock_results(results)

    def __enter__(self) -> LocalPool:
        return self

    def __exit__(self, exc_type: Any, *_: Any) -> None:
        self.close(terminate=exc_type is not None)


class DaskPool:
    """The workers of an existing Dask cluster (``pip install "mistool[dask]"``).

    Args:
        address: the scheduler, e.g. ``"tcp://scheduler:8786"``; or pass ``client``.
        client: an existing ``distributed.Client`` (not closed by :meth:`close`).
        batch_frames: frames per task.
    """

    def __init__(
        self,
        address: str | None = None,
        *,
        client: Any = None,
        batch_frames: int = DASK_BATCH_FRAMES,
    ) -> None:
        from mistool.errors import ConfigError

        self._own = client is None
        if client is None:
            try:
                from distributed import Client
            except ModuleNotFoundError:
                raise ConfigError(
                    '--dask needs the distributed package: pip install "mistool[dask]"'
                ) from None
            try:
                client = Client(address, timeout=f"{DASK_CONNECT_TIMEOUT_S}s")
            except (OSError, TimeoutError) as exc:
                raise ConfigError(
                    f"--dask {address}: cannot reach the Dask scheduler: {exc}"
                ) from None
        self.client = client
        """The ``distributed.Client``."""
        self.workers = max(1, len(client.scheduler_info().get("workers", {})))
        self.batch_frames = batch_frames

    def submit(self, fn: Callable[..., Any], *args: Any) -> Any:
        return self.client.submit(fn, *args, pure=False)

    def close(self, *, terminate: bool = False) -> None:
        """Close the client this pool opened (the cluster keeps running)."""
        if self._own and self.client is not None:
            self.client.close()
        self.client = None

    def __enter__(self) -> DaskPool:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()


def ordered_results(
    work: Iterable[tuple[list[str], Batch]], pool: FramePool | None
) -> Iterator[tuple[str, FrameResult]]:
    """``(frame name, result)`` in frame order; the work runs in ``pool`` (in this
    process when None) with at most ``IN_FLIGHT_PER_WORKER * pool.workers`` batches
    submitted and not yet consumed. Pending tasks are cancelled when the consumer stops
    early or an error is raised.

    While the pool's processes are starting (a pool with a ``warming()`` method saying
    so, e.g. :class:`LocalPool`), the batches are worked on here, as without a pool (the
    work is pure: the same results); a video span goes to the pool (its frames are
    decoded where the span is read)."""
    if pool is None:
        for names, batch in work:
            pairs = _pairs(names, batch, observe_batch(batch))
            yield from pairs
            if len(pairs) < len(names):  # the end of a video
                return
        return
    work = iter(work)
    warming = getattr(pool, "warming", None)
    while warming is not None and warming():
        item = next(work, None)
        if item is None:
            return
        if item[1].items and isinstance(item[1].items[0], VideoSpan):
            work = itertools.chain([item], work)
            break
        yield from _pairs(item[0], item[1], observe_batch(item[1]))
    item = None  # (its frames are not held while the pool works: memory stays bounded)
    limit = max(1, IN_FLIGHT_PER_WORKER * pool.workers)
    pending: collections.deque[tuple[list[str], Batch, ResultFuture]] = collections.deque()
    try:
        for names, batch in work:
            pending.append((names, batch, pool.submit(observe_batch, batch)))
            if len(pending) >= limit:
                done, sent, fut = pending.popleft()
                pairs = _pairs(done, sent, fut.result())
                yield from pairs
                if len(pairs) < len(done):  # the end of a video: the rest is past it
                    return
        while pending:
            done, sent, fut = pending.popleft()
            pairs = _pairs(done, sent, fut.result())
            yield from pairs
            if len(pairs) < len(done):
                return
    finally:
        for _, _, fut in pending:
            fut.cancel()


def in_flight_frames(pool: FramePool | None) -> int:
    """The most frames decoded and not yet consumed at any time (memory bound)."""
    if pool is None:
        return 1
    return IN_FLIGHT_PER_WORKER * pool.workers * pool.batch_frames


__all__ = [
    "DASK_BATCH_FRAMES",
    "LOCAL_BATCH_FRAMES",
    "Batch",
    "DaskPool",
    "FramePool",
    "FrameResult",
    "LocalPool",
    "batches",
    "default_workers",
    "in_flight_frames",
    "measure",
    "measure_all",
    "measure_frames",
    "observe_batch",
    "observe_labels",
    "ordered_results",
    "metric_pose",
    "unknown_values",
    "VideoSpan",
]
