"""The Python API: a mask sequence in, one motion table out.

Pipeline (one direction)::

    open_sequence  ->  per frame, in worker threads (decode, Algorithm 1 observations,
                       metric pose when a camera is known)
                   ->  in frame order: instrument identities (IdentityTracker.resolve)
                   ->  rows -> TrackTable -> paper motion (Algorithm 2)
                   ->  sequence-level metric refinement (trocar, smoothing) -> sorted table

Decoding (zlib inflate, OpenCV) and most of the per-frame work release the GIL, so worker
threads use every core; at most two frames per worker are in flight (memory stays flat in
sequence length) and results are consumed in frame order.

Two entry points:

- :func:`track` for a whole sequence (a folder, a mask video or an iterable of arrays);
- :class:`Tracker` for a segmentation network's own loop, frame by frame.
"""

from __future__ import annotations

import collections
import importlib
import math
import os
import time
import warnings
from collections.abc import Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np

from mistool import paper, tracking
from mistool.config import Config, load_config
from mistool.errors import ConfigError
from mistool.model import COLUMN_NAMES, PARTS, TrackTable
from mistool.sequence import VIDEO_TOLERANCE, Frame, MaskSequence, open_sequence, to_labels

#: Default worker threads: the CPU count, at most this (the GIL-bound parts of a frame's
#: work keep more threads from helping).
MAX_DEFAULT_WORKERS = 8

#: Allowed values of ``smoothing``.
SMOOTHING = ("none", "offline", "online")

# Columns every table built here has, in order (the rest come from the metric pose).
_BASE = (
    "frame",
    "time_s",
    "instrument",
    "part",
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


class MistoolWarning(UserWarning):
    """Something in the input is unusual but not an error (e.g. unknown label values)."""


@dataclass
class TrackResult:
    """A finished run: the table plus what the command line summarises."""

    table: TrackTable
    """The motion table, rows sorted by (frame, instrument, part)."""
    num_frames: int
    """Frames read."""
    shape: tuple[int, int] | None
    """``(H, W)`` of the frames (None when there were none)."""
    unknown_values: tuple[int, ...]
    """Label values present in the masks that the config does not know (sorted)."""
    seconds: float
    """Wall-clock time of the run (s)."""
    name: str = ""
    """The sequence's short name."""
    metric: bool = False
    """Whether the metric pose ran."""
    config: Config = field(default_factory=Config)
    """The effective config."""

    @property
    def instruments(self) -> tuple[str, ...]:
        """Instrument names seen, sorted."""
        return tuple(sorted(set(self.table["instrument"].tolist())))

    @property
    def parts(self) -> tuple[str, ...]:
        """Part names seen, proximal to distal."""
        seen = set(self.table["part"].tolist())
        return tuple(p for p in PARTS if p in seen)


def _pose_module() -> ModuleType | None:
    """``mistool.pose`` when it is installed with its interface, else None."""
    try:
        pose = importlib.import_module("mistool.pose")
    except ModuleNotFoundError as exc:
        if exc.name in ("mistool.pose",):
            return None
        raise
    return pose if hasattr(pose, "measure_instance") else None


def _resolve_config(config: Config | str | Path | None) -> Config | None:
    if config is None or isinstance(config, Config):
        return config
    if isinstance(config, (str, os.PathLike)):
        return load_config(config)
    raise ConfigError(
        f"config: expected a Config, a path to mistool.toml or None, got {type(config).__name__}"
    )


def _check_smoothing(smoothing: str) -> None:
    if smoothing not in SMOOTHING:
        raise ConfigError(f"smoothing = {smoothing!r}: choose one of {', '.join(SMOOTHING)}")


# --- per frame ------------------------------------------------------------------------


@dataclass
class _FrameResult:
    instances: list[Any]
    metrics: list[dict[str, dict[str, float]] | None]
    unknown: np.ndarray
    shape: tuple[int, int]


def _process(
    labels: np.ndarray, config: Config, pose: ModuleType | None, lossy: bool = False
) -> _FrameResult:
    """The per-frame work (thread-safe): observations, metric pose, unknown values
    (``lossy``: a mask video, see :func:`_unknown_values`)."""
    instances = tracking.observe_frame(labels, config)
    shape = (int(labels.shape[0]), int(labels.shape[1]))
    metrics = [_measure(inst, shape, config, pose) for inst in instances]
    unknown = _unknown_values(labels, config, lossy)
    return _FrameResult(instances, metrics, unknown, shape)


def _measure(
    inst: Any, shape: tuple[int, int], config: Config, pose: ModuleType | None
) -> dict[str, dict[str, float]] | None:
    """The per-frame metric pose of one instance, or None without a camera/pose step."""
    if pose is None or config.camera is None:
        return None
    name = inst.label
    return pose.measure_instance(
        inst,
        shape,
        config.camera,
        config.shaft_diameter_for(name) if name else config.shaft_diameter_mm,
        config.clasper_length_for(name) if name else config.clasper_length_mm,
    )


def _unknown_values(labels: np.ndarray, config: Config, lossy: bool = False) -> np.ndarray:
    """``tracking.unknown_values``, on the values present (an 8-bit histogram is ~7x faster
    than scanning the image in numpy).

    In a mask video (``lossy``) the codec smears values around every edge, so a value
    counts only where it covers at least ``min_area_px`` pixels of the frame, and values
    up to :data:`~mistool.sequence.VIDEO_TOLERANCE` are background."""
    if labels.dtype == np.uint8 and labels.ndim == 2:
        hist = cv2.calcHist([labels], [0], None, [256], [0, 256]).ravel()
        values = np.flatnonzero(hist >= (max(config.min_area_px, 1) if lossy else 1))
        if lossy:
            values = values[values > VIDEO_TOLERANCE]
        return np.asarray(tracking.unknown_values(values.astype(np.uint8)[None, :], config))
    return np.asarray(tracking.unknown_values(labels, config))


def _identify(
    tracker: tracking.IdentityTracker,
    index: int,
    result: _FrameResult,
    config: Config,
    pose: ModuleType | None,
) -> tuple[list[str], _FrameResult]:
    """Instrument names for a frame's instances, in frame order (sequential).

    Uses :meth:`~mistool.tracking.IdentityTracker.resolve`, which splits a blob holding
    several known instruments (crossing or grasping in merged masks) into its instruments;
    the metric pose is then measured again for the split pieces only."""
    instances, names = tracker.resolve(index, result.instances)
    if instances is result.instances:
        return list(names), result
    metrics = [_measure(inst, result.shape, config, pose) for inst in instances]
    return list(names), _FrameResult(list(instances), metrics, result.unknown, result.shape)


def _load_and_process(
    frame: Frame, config: Config, pose: ModuleType | None, lossy: bool
) -> _FrameResult:
    return _process(frame.load(), config, pose, lossy)


class _Rows:
    """Row accumulator: one row per (frame, instrument, part)."""

    def __init__(self, fps: float) -> None:
        self.fps = fps
        self.base: dict[str, list[Any]] = {c: [] for c in _BASE}
        self.extra: dict[str, list[float]] = {}
        self.n = 0

    def add_frame(self, index: int, names: list[str], result: _FrameResult) -> None:
        for name, inst, metric in zip(names, result.instances, result.metrics, strict=True):
            for part in PARTS:
                obs = inst.parts.get(part)
                if obs is None:
                    continue
                self._add(index, name, part, obs, (metric or {}).get(part, {}))

    def _add(self, index: int, name: str, part: str, obs: Any, metric: dict[str, float]) -> None:
        b, base = obs.box, self.base
        corners = np.asarray(obs.corners, dtype=np.float64).reshape(4, 2)
        values = (
            index,
            index / self.fps,
            name,
            part,
            b.cx,
            b.cy,
            b.length,
            b.width,
            b.angle_deg,
            float(obs.area_px),
            *corners.ravel().tolist(),
        )
        for col, v in zip(_BASE, values, strict=True):
            base[col].append(v)
        for col, v in metric.items():
            if col not in self.extra:
                self.extra[col] = [math.nan] * self.n
            self.extra[col].append(float(v) if v is not None else math.nan)
        self.n += 1
        for col in self.extra:
            if len(self.extra[col]) < self.n:
                self.extra[col].append(math.nan)

    def table(self) -> TrackTable:
        cols: dict[str, Any] = dict(self.base)
        cols["frame"] = np.asarray(cols["frame"], dtype=np.int64)
        for col in _BASE[4:]:
            cols[col] = np.asarray(cols[col], dtype=np.float64)
        cols["time_s"] = np.asarray(cols["time_s"], dtype=np.float64)
        known = [c for c in COLUMN_NAMES if c in self.extra]
        for col in known + [c for c in self.extra if c not in known]:
            cols[col] = np.asarray(self.extra[col], dtype=np.float64)
        return TrackTable(cols)


def _finish(
    table: TrackTable, config: Config, pose: ModuleType | None, smoothing: str
) -> TrackTable:
    """Sequence-level steps: paper motion (Algorithm 2), metric refinement, sort."""
    table = table.sorted()
    focal = config.camera.fx if config.camera is not None else 1.0
    table = paper.paper_motion(table, focal_px=focal)
    if pose is not None and config.camera is not None and hasattr(pose, "refine_sequence"):
        table = pose.refine_sequence(table, config, smoothing=smoothing)
    return table.sorted()


def _ordered_results(
    frames: Iterator[Frame],
    config: Config,
    pose: ModuleType | None,
    workers: int,
    lossy: bool = False,
) -> Iterator[tuple[Frame, _FrameResult]]:
    """``(frame, result)`` in frame order; at most ``2 * workers`` frames in flight."""
    if workers <= 1:
        for frame in frames:
            yield frame, _load_and_process(frame, config, pose, lossy)
        return
    pending: collections.deque[tuple[Frame, Future[_FrameResult]]] = collections.deque()
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="mistool")
    # Our pool already uses every core; OpenCV's own threads on top of it only add
    # contention (observe_frame: 1.55 ms CPU with OpenCV's threads vs 0.75 ms without,
    # scripts/bench_paper.py). The setting is process-wide, so it is restored afterwards.
    cv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for frame in frames:
            pending.append((frame, pool.submit(_load_and_process, frame, config, pose, lossy)))
            if len(pending) >= 2 * workers:
                done, fut = pending.popleft()
                yield done, fut.result()
        while pending:
            done, fut = pending.popleft()
            yield done, fut.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        cv2.setNumThreads(cv_threads)


def run(
    source: str | Path | Iterable[np.ndarray] | MaskSequence,
    config: Config | str | Path | None = None,
    *,
    progress: bool = False,
    workers: int | None = None,
    metric: bool = True,
    smoothing: str = "offline",
) -> TrackResult:
    """Like :func:`track`, but returns a :class:`TrackResult` (table + run summary) and
    does not warn: unknown label values are in ``result.unknown_values``."""
    _check_smoothing(smoothing)
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise ConfigError(f"workers = {workers!r}: must be an integer >= 1")
    n_workers = workers or min(MAX_DEFAULT_WORKERS, max(1, os.cpu_count() or 1))
    start = time.perf_counter()
    seq = (
        source
        if isinstance(source, MaskSequence)
        else open_sequence(source, _resolve_config(config))
    )
    cfg = seq.config
    pose = _pose_module() if metric and cfg.camera is not None else None
    tracker = tracking.IdentityTracker(cfg)
    rows = _Rows(cfg.fps)
    unknown: set[int] = set()
    bar = None
    if progress:
        from tqdm import tqdm  # only when a progress bar is wanted

        bar = tqdm(
            total=seq.num_frames,
            unit="frame",
            desc=seq.name,
            delay=0.5,
            dynamic_ncols=True,
            leave=False,
        )
    num_frames = 0
    try:
        for frame, result in _ordered_results(seq.frames(), cfg, pose, n_workers, lossy=seq.lossy):
            seq.check_shape(frame, result.shape)
            names, result = _identify(tracker, frame.index, result, cfg, pose)
            rows.add_frame(frame.index, names, result)
            unknown.update(int(v) for v in result.unknown.ravel())
            num_frames += 1
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    table = _finish(rows.table(), cfg, pose, smoothing)
    return TrackResult(
        table=table,
        num_frames=num_frames,
        shape=seq.shape,
        unknown_values=tuple(sorted(unknown)),
        seconds=time.perf_counter() - start,
        name=seq.name,
        metric=pose is not None,
        config=cfg,
    )


def unknown_values_message(values: Iterable[int], colour: bool = False) -> str:
    """One line listing label values the config does not know (at most 20 shown)."""
    vals = sorted(values)
    fmt = (lambda v: f"#{v:06x}") if colour else str
    shown = ", ".join(fmt(v) for v in vals[:20]) + (", ..." if len(vals) > 20 else "")
    return (
        f"{len(vals)} label value(s) not in mistool.toml were ignored: {shown} "
        "(set them in [parts] or [[instrument]] if they are instrument parts)"
    )


def track(
    source: str | Path | Iterable[np.ndarray],
    config: Config | str | Path | None = None,
    *,
    progress: bool = False,
    workers: int | None = None,
    metric: bool = True,
    smoothing: str = "offline",
) -> TrackTable:
    """Track every instrument part through a mask sequence.

    Args:
        source: a folder of label images, a mask video, or an iterable of ``(H, W)``
            integer label arrays (``(H, W, 3)`` RGB for colour masks).
        config: a :class:`Config`, a path to a ``mistool.toml``, or None to read
            ``mistool.toml`` beside the frames (EndoVis'15 defaults without one).
        progress: show a tqdm progress bar on stderr.
        workers: worker threads for decoding and per-frame work (default: the CPU count,
            at most :data:`MAX_DEFAULT_WORKERS`).
        metric: compute the metric 3D pose when the config has a ``[camera]``.
        smoothing: temporal filtering of the metric pose: ``"none"``, ``"offline"``
            (uses past and future frames) or ``"online"`` (causal).

    Returns:
        The motion table, one row per (frame, instrument, part) seen, sorted; columns in
        :data:`mistool.model.COLUMNS` order. Empty (zero rows) when nothing was found.

    Raises:
        MistoolError: bad input path, mask format or config (one-line message).

    Warns:
        MistoolWarning: once, listing label values the config does not know.
    """
    result = run(
        source, config, progress=progress, workers=workers, metric=metric, smoothing=smoothing
    )
    if result.unknown_values:
        warnings.warn(
            unknown_values_message(result.unknown_values, result.config.colour_masks),
            MistoolWarning,
            stacklevel=2,
        )
    return result.table


class Tracker:
    """Frame-by-frame tracking inside a segmentation network's own loop.

    Example::

        tracker = mistool.Tracker(mistool.load_config("mistool.toml"))
        for image in video:
            labels = net(image).argmax(0)            # (H, W) integer labels
            rows = tracker.update(labels)            # this frame's rows
        table = tracker.table()                      # the whole sequence

    :meth:`update` returns the frame's rows with the paper motion relative to each part's
    previous row; the metric pose is per frame (no smoothing). :meth:`table` returns the
    whole sequence as :func:`track` would (with ``smoothing``).
    """

    def __init__(
        self,
        config: Config | str | Path | None = None,
        *,
        metric: bool = True,
        smoothing: str = "online",
    ) -> None:
        _check_smoothing(smoothing)
        self.config: Config = _resolve_config(config) or Config()
        """The config the pixels are read with."""
        self.smoothing = smoothing
        self._pose = _pose_module() if metric and self.config.camera is not None else None
        self._tracker = tracking.IdentityTracker(self.config)
        self._frames: list[TrackTable] = []
        self._last: dict[tuple[str, str], tuple[TrackTable, ...]] = {}
        self._shape: tuple[int, int] | None = None
        self._unknown: set[int] = set()
        self._warned = False

    @property
    def num_frames(self) -> int:
        """Frames given to :meth:`update` so far."""
        return len(self._frames)

    def update(self, labels: np.ndarray) -> TrackTable:
        """Track one frame.

        Args:
            labels: ``(H, W)`` integer label image (``(H, W, 3)`` RGB for colour masks).

        Returns:
            This frame's rows (possibly zero rows).
        """
        index = len(self._frames)
        where = f"frame {index}"
        arr = to_labels(np.asarray(labels), where, colour=self.config.colour_masks, order="rgb")
        shape = (int(arr.shape[0]), int(arr.shape[1]))
        if self._shape is None:
            self._shape = shape
        elif shape != self._shape:
            from mistool.errors import MaskFormatError

            raise MaskFormatError(
                f"{where}: frame size changed: {shape[1]}x{shape[0]} px, "
                f"earlier frames are {self._shape[1]}x{self._shape[0]} px"
            )
        result = _process(arr, self.config, self._pose)
        names, result = _identify(self._tracker, index, result, self.config, self._pose)
        rows = _Rows(self.config.fps)
        rows.add_frame(index, names, result)
        raw = rows.table()
        self._frames.append(raw)
        new = {int(v) for v in result.unknown.ravel()} - self._unknown
        if new:
            self._unknown |= new
            warnings.warn(
                unknown_values_message(new, self.config.colour_masks), MistoolWarning, stacklevel=2
            )
        focal = self.config.camera.fx if self.config.camera is not None else 1.0
        if raw.num_rows == 0:
            return paper.paper_motion(raw, focal_px=focal)
        keys = list(zip(raw["instrument"].tolist(), raw["part"].tolist(), strict=True))
        # z of Eq. (5) uses the scale change A^n / A^(n-1), so dz needs two earlier rows
        previous = [t for k in keys for t in self._last.get(k, ())]
        moved = paper.paper_motion(TrackTable.concat([*previous, raw]), focal_px=focal)
        current = moved[moved["frame"] == index]
        for i, k in enumerate(keys):
            self._last[k] = (*self._last.get(k, ())[-1:], raw[i : i + 1])
        return current.sorted()

    def table(self) -> TrackTable:
        """Every frame so far as one table (paper motion and metric refinement applied)."""
        if not self._frames:
            return _finish(_Rows(self.config.fps).table(), self.config, None, "none")
        return _finish(TrackTable.concat(self._frames), self.config, self._pose, self.smoothing)
