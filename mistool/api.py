"""The Python API: a mask sequence in, one motion table out.

Pipeline (one direction)::

    open_sequence  ->  per frame, in worker processes (decode, Algorithm 1 observations,
                       metric pose when a camera is known): mistool.parallel
                   ->  in frame order, here: instrument identities (IdentityTracker.resolve;
                       the pieces of a split blob are measured again in the workers,
                       while the next frames are identified) -> rows (mistool.rows)
                   ->  raw chunks of rows (iter_track)
                   ->  refine: paper motion (Algorithm 2), sequence-level metric refinement
                       (trocar, smoothing) -> sorted table

Only the identity step and the refinement are sequential; at most a few batches of frames
per worker are in flight, so memory does not grow with the sequence length beyond the
table's own rows. The output is the same whatever the number of workers.

Entry points:

- :func:`track` for a whole sequence (a folder, a mask video or an iterable of arrays);
- :func:`iter_track` + :func:`refine` for the same, chunk by chunk (a viewer that shows
  the first frames while the rest is tracked);
- :class:`Tracker` for a segmentation network's own loop, frame by frame.
"""

from __future__ import annotations

import collections
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mistool import paper, parallel, tracking
from mistool.config import Config, load_config, preset_hint
from mistool.errors import ConfigError, MistoolWarning
from mistool.heap import frozen_heap
from mistool.model import PARTS, TrackTable
from mistool.pose import refine_sequence
from mistool.pose.status import status_column
from mistool.rows import RowBuilder
from mistool.sequence import MaskSequence, finish_video, open_sequence, to_labels
from mistool.tracking.relink import relink

#: Allowed values of ``smoothing``.
SMOOTHING = ("none", "offline", "online")

#: Frames per chunk yielded by :func:`iter_track`.
DEFAULT_CHUNK_FRAMES = 256

#: ``track``/``run`` with the default workers use a process pool only for sequences of at
#: least this many frames (known length): starting the workers (their fork server loads
#: the compiled kernels, ~1-1.5 s) costs more than it saves on a short sequence. A new
#: ``mistool track`` process on 2 cores: 600 frames 1.77 s with 1 process vs 2.26 s with
#: 2 workers (one instrument), 2.27 vs 2.72 s (two crossing); 2,500 crossing frames
#: 5.66 vs 5.12 s. The output is the same either way.
POOL_MIN_FRAMES = 1000

#: Frames over which the most instances per frame (after the identity step) is kept: a
#: frame with fewer, worked on in a pool, has its metric pose deferred
#: (:func:`mistool.parallel.observe_labels`).
DEFER_WINDOW_FRAMES = 256


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


# --- the sequential steps ---------------------------------------------------------------


def _identify(
    tracker: tracking.IdentityTracker,
    index: int,
    result: parallel.FrameResult,
    config: Config,
    metric: bool,
) -> tuple[list[str], parallel.FrameResult]:
    """Instrument names for a frame's instances, in frame order (sequential).

    Uses :meth:`~mistool.tracking.IdentityTracker.resolve`, which splits a blob holding
    several known instruments (crossing or grasping in merged masks) into its instruments;
    the metric pose is then measured (here, in the caller's process) for the split pieces,
    or for every instance of a frame whose pose was deferred (``result.deferred``)."""
    instances, names = tracker.resolve(index, result.instances, result.runs)
    if instances is result.instances and not result.deferred:
        return list(names), result
    kept = list(instances)
    metrics = parallel.measure_all(kept, result.shape, config, metric)
    return list(names), result.replaced(instances=kept, metrics=metrics, deferred=False)


class _RecentInstances:
    """The most instances per frame over the last :data:`DEFER_WINDOW_FRAMES` frames
    identified: the ``defer_below`` of the next batches (a frame with fewer instances
    likely holds a blob of crossing tools that the identity step will split)."""

    def __init__(self) -> None:
        self._counts: collections.deque[int] = collections.deque(maxlen=DEFER_WINDOW_FRAMES)

    def add(self, count: int) -> None:
        self._counts.append(count)

    def most(self) -> int:
        return max(self._counts, default=0)

    def hint(self) -> int:
        """:meth:`most`, at least 1: a batch made before any frame is identified defers
        nothing on the hint alone, but its worker still defers a frame with fewer
        instances than an earlier frame of the batch (:class:`mistool.parallel.Batch`)."""
        return max(1, self.most())


@dataclass
class _Pending:
    """A frame identified, perhaps waiting for the metric pose of its instances (split
    pieces, or a deferred frame's instances)."""

    index: int
    names: list[str]
    result: parallel.FrameResult
    waiting: bool = False
    """Its pose is to be measured in the pool (``result.metrics`` is None meanwhile)."""
    metrics: parallel.ResultFuture | None = None
    """The task measuring it (with other frames': its ``slot``); None: not submitted."""
    slot: int = 0

    def ready(self, force: bool) -> bool:
        """Whether it can be yielded now (``force``: waiting for its task if need be)."""
        if not self.waiting:
            return True
        return self.metrics is not None and (force or self.metrics.done())

    def finish(self) -> tuple[int, list[str], parallel.FrameResult]:
        if self.metrics is None:
            return self.index, self.names, self.result
        metrics = self.metrics.result()[self.slot]
        return self.index, self.names, self.result.replaced(metrics=metrics)


class _MeasureGroup:
    """Frames waiting for their pose, submitted to the pool together as one task
    (:func:`mistool.parallel.measure_frames`): each task costs the caller a round trip."""

    def __init__(self, pool: parallel.FramePool, config: Config, metric: bool, age: int) -> None:
        self._pool, self._config, self._metric = pool, config, metric
        self._size = max(1, pool.batch_frames)
        self._age = age
        self._frames: list[_Pending] = []

    def add(self, item: _Pending) -> None:
        """Queue ``item``; submit the group once full or its first frame is ``age`` old."""
        self._frames.append(item)
        if len(self._frames) >= self._size or item.index - self._frames[0].index >= self._age:
            self.submit()

    def submit(self) -> None:
        """Submit the frames queued (if any)."""
        if not self._frames:
            return
        work = parallel.MeasureWork((p.result.instances, p.result.shape) for p in self._frames)
        future = self._pool.submit(parallel.measure_frames, work, self._config, self._metric)
        for k, p in enumerate(self._frames):
            p.metrics, p.slot = future, k
        self._frames = []


def identified(
    results: Iterable[tuple[int, tuple[str, parallel.FrameResult]]],
    seq: MaskSequence,
    tracker: tracking.IdentityTracker,
    metric: bool,
    pool: parallel.FramePool | None,
    recent: _RecentInstances | None = None,
) -> Iterator[tuple[int, list[str], parallel.FrameResult]]:
    """``(index, instrument names, result)`` of every frame, in frame order: the identity
    step (sequential, here) on :func:`mistool.parallel.ordered_results`' frames.

    When the identity step splits a blob (:func:`_identify`), or a frame's pose was
    deferred, the metric pose of its instances is measured in ``pool`` (several frames
    per task) while the following frames are identified; a frame is yielded once they
    are measured (at most ``PENDING_FRAMES_PER_WORKER`` frames per worker wait). Without
    a pool they are measured here. Same output either way: the identity step sees the
    frames in the same order and the pose is pure. ``recent``: told each frame's number
    of instances."""
    cfg = seq.config
    if pool is None:
        for index, (name, result) in results:
            seq.check_shape(name, result.shape)
            names, result = _identify(tracker, index, result, cfg, metric)
            if recent is not None:
                recent.add(len(names))
            yield index, names, result
        return
    limit = max(1, parallel.PENDING_FRAMES_PER_WORKER * pool.workers)
    pending: collections.deque[_Pending] = collections.deque()
    group = _MeasureGroup(pool, cfg, metric, age=limit // 2)
    try:
        for index, (name, result) in results:
            seq.check_shape(name, result.shape)
            instances, names = tracker.resolve(index, result.instances, result.runs)
            if recent is not None:
                recent.add(len(names))
            if not pending and instances is result.instances and not result.deferred:
                yield index, list(names), result  # (what a _Pending of it would yield now)
                continue
            item = _Pending(index, list(names), result)
            if instances is not result.instances or result.deferred:
                item.result = result.replaced(
                    instances=list(instances), metrics=None, deferred=False
                )
                item.waiting = True
                group.add(item)
            pending.append(item)
            if len(pending) > limit and pending[0].metrics is None:
                group.submit()  # the oldest frame must go: its group with it
            while pending and pending[0].ready(len(pending) > limit):
                yield pending.popleft().finish()
        group.submit()
        while pending:
            yield pending.popleft().finish()
    finally:
        for p in pending:
            if p.metrics is not None:
                p.metrics.cancel()


@dataclass
class Chunk:
    """Raw (unrefined) rows of consecutive frames, with what a run summary needs."""

    table: TrackTable
    """Rows of frames ``start .. start + num_frames - 1`` in frame order (no paper
    motion, no refinement: see :func:`refine`)."""
    start: int
    """Index of the chunk's first frame."""
    num_frames: int
    """Frames in the chunk."""
    unknown: frozenset[int]
    """Label values in these frames that the config does not know."""
    shape: tuple[int, int] | None
    """``(H, W)`` of the frames (None when the sequence has none)."""


def _check_workers(workers: int | None) -> None:
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise ConfigError(f"workers = {workers!r}: must be an integer >= 1")


def _check_chunk(chunk_frames: int) -> None:
    if isinstance(chunk_frames, bool) or not isinstance(chunk_frames, int) or chunk_frames < 1:
        raise ConfigError(f"chunk_frames = {chunk_frames!r}: must be an integer >= 1")


def _with_status(table: TrackTable, config: Config) -> TrackTable:
    """The table with its ``pose_status`` column (:mod:`mistool.pose.status`): as the
    metric refinement wrote it, else ``"no camera"`` or ``"off"`` (metric pose not run)
    on every row."""
    if "pose_status" in table:
        return table
    reason = "no camera" if config.camera is None else "off"
    return table.with_columns(pose_status=np.full(table.num_rows, reason, dtype=object))


def _open(
    source: str | Path | Iterable[np.ndarray] | MaskSequence,
    config: Config | str | Path | None,
) -> MaskSequence:
    if isinstance(source, MaskSequence):
        return source
    return open_sequence(source, _resolve_config(config))


def iter_chunks(
    seq: MaskSequence,
    *,
    metric: bool = True,
    pool: parallel.FramePool | None = None,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    on_frames: Callable[[int], None] | None = None,
) -> Iterator[Chunk]:
    """The sequence's raw rows chunk by chunk, in frame order (see :func:`iter_track`).

    Args:
        seq: an opened sequence (:func:`mistool.sequence.open_sequence`).
        metric: measure the metric pose when the config has a camera.
        pool: where the per-frame work runs (:mod:`mistool.parallel`); None: here.
        chunk_frames: frames per chunk.
        on_frames: called with the number of frames just consumed (progress).

    Yields:
        :class:`Chunk` objects; at least one (an empty one for an empty sequence).
    """
    _check_chunk(chunk_frames)
    cfg = seq.config
    measured = parallel.metric_pose(metric, cfg)
    tracker = tracking.IdentityTracker(cfg)
    rows = RowBuilder(cfg.fps)
    batch = pool.batch_frames if pool is not None else 1
    # a local worker decodes the video frames it works on (a Dask worker may not see the
    # file: the caller decodes them)
    spans = isinstance(pool, parallel.LocalPool) and seq.video is not None
    # in this process, the pose waits for the identity step (never measured for a blob it
    # splits); in a pool, only frames with fewer instances than recently seen wait
    recent = _RecentInstances()
    defer = _defer_always if pool is None else recent.hint
    work = parallel.batches(seq, measured, batch, video_spans=spans, defer_below=defer)
    start, count, yielded = 0, 0, False
    unknown: set[int] = set()
    corrupt: list[int] = []
    index, total = 0, 0
    results = enumerate(parallel.ordered_results(work, pool))
    with frozen_heap():  # no full collection walks the imports (mistool.heap)
        for index, names, result in identified(results, seq, tracker, measured, pool, recent):
            total = index + 1
            if result.corrupt:
                corrupt.append(index)
            rows.add_frame(index, names, result.instances, result.metrics)
            unknown.update(int(v) for v in result.unknown.ravel())
            count += 1
            if on_frames is not None:
                on_frames(1)
            if count == chunk_frames:
                yield Chunk(rows.take(), start, count, frozenset(unknown), seq.shape)
                start, count, unknown, yielded = index + 1, 0, set(), True
    if spans and seq.video is not None:  # the end of the video, as its sequential read ends
        finish_video(seq.video, total, corrupt)
    if count or not yielded:
        yield Chunk(rows.take(), start, count, frozenset(unknown), seq.shape)


def _defer_always() -> int:
    return parallel.DEFER_ALWAYS


def _local_pool(workers: int | None, seq: MaskSequence) -> parallel.LocalPool | None:
    """A process pool for ``workers`` (None: the default, which skips short sequences)."""
    if workers is None:
        short = seq.num_frames is not None and seq.num_frames < POOL_MIN_FRAMES
        workers = 1 if short else parallel.default_workers()
    return parallel.LocalPool(workers) if workers > 1 else None


def iter_track(
    source: str | Path | Iterable[np.ndarray] | MaskSequence,
    config: Config | str | Path | None = None,
    *,
    metric: bool = True,
    workers: int = 1,
    chunk_frames: int = DEFAULT_CHUNK_FRAMES,
    pool: parallel.FramePool | None = None,
) -> Iterator[TrackTable]:
    """Track a sequence chunk by chunk: raw rows, in frame order, as they are ready.

    ``refine(TrackTable.concat(iter_track(src, cfg)), cfg)`` is ``track(src, cfg)``.

    Args:
        source: a folder of label images, a mask video, an iterable of ``(H, W)``
            integer label arrays, or an opened :class:`~mistool.sequence.MaskSequence`.
        config: a :class:`Config`, a path to a ``mistool.toml``, or None to read
            ``mistool.toml`` beside the frames.
        metric: measure the per-frame metric pose when the config has a ``[camera]``.
        workers: processes for the per-frame work (1: in this process). The output is
            the same whatever the number.
        chunk_frames: frames per yielded chunk.
        pool: a :mod:`mistool.parallel` pool to use instead of starting ``workers``
            processes (e.g. a :class:`~mistool.parallel.DaskPool`); it is not closed.

    Yields:
        One :class:`TrackTable` per ``chunk_frames`` frames (the last may be shorter; an
        empty sequence yields one zero-row table): one row per (frame, instrument, part)
        seen, with the boxes, the identities and the per-frame metric pose, without the
        paper motion and the sequence-level refinement (:func:`refine` adds both).
        Rows within a frame are in no particular order.

    Raises:
        MistoolError: bad input path, mask format or config (one-line message).

    Close the generator (or consume it) to stop the worker processes early.
    """
    _check_workers(workers)
    seq = _open(source, config)
    own = None if pool is not None else _local_pool(workers, seq)
    try:
        for chunk in iter_chunks(seq, metric=metric, pool=pool or own, chunk_frames=chunk_frames):
            yield chunk.table
    except BaseException:
        if own is not None:
            own.close(terminate=True)
            own = None
        raise
    finally:
        if own is not None:
            own.close()


def refine(
    table: TrackTable, config: Config | str | Path | None = None, smoothing: str = "offline"
) -> TrackTable:
    """The sequence-level steps on raw rows (:func:`iter_track`'s chunks, concatenated).

    In merged masks (no ``[[instrument]]`` tables), first revisits the identity step's
    names over the whole sequence (:func:`mistool.tracking.relink.relink`: fragments
    absorbed, a tool back after leaving the view linked to its old name). Then sorts the
    rows, adds the paper's frame-to-frame motion (Algorithm 2) and, when the config has a
    camera and the rows have a metric pose, refines it over the sequence (trocar, trocar
    constraint, temporal filtering).

    Args:
        table: raw rows of a whole sequence (``TrackTable.concat`` of the chunks).
        config: the sequence's config (camera, fps, diameters); None: defaults.
        smoothing: ``"none"``, ``"offline"`` (zero-phase) or ``"online"`` (causal).

    Returns:
        The motion table, sorted by (frame, instrument, part).
    """
    _check_smoothing(smoothing)
    cfg = _resolve_config(config) or Config()
    if not cfg.instruments:  # names by connectivity, not by label values
        table = relink(table, cfg.fps)
    table = table.sorted()
    focal = cfg.camera.fx if cfg.camera is not None else 1.0
    table = paper.paper_motion(table, focal_px=focal)
    if parallel.metric_pose(True, cfg):
        table = refine_sequence(table, cfg, smoothing=smoothing)
    return _with_status(table, cfg).sorted()


def run(
    source: str | Path | Iterable[np.ndarray] | MaskSequence,
    config: Config | str | Path | None = None,
    *,
    progress: bool = False,
    workers: int | None = None,
    metric: bool = True,
    smoothing: str = "offline",
    pool: parallel.FramePool | None = None,
    on_frames: Callable[[int], None] | None = None,
) -> TrackResult:
    """Like :func:`track`, but returns a :class:`TrackResult` (table + run summary) and
    does not warn: unknown label values are in ``result.unknown_values``.

    ``pool``: a :mod:`mistool.parallel` pool to run the per-frame work in (not closed);
    ``on_frames``: called with the number of frames just consumed (progress)."""
    _check_smoothing(smoothing)
    _check_workers(workers)
    start = time.perf_counter()
    seq = _open(source, config)
    cfg = seq.config
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

    def advance(n: int) -> None:
        if bar is not None:
            bar.update(n)
        if on_frames is not None:
            on_frames(n)

    own = None if pool is not None else _local_pool(workers, seq)
    chunks: list[TrackTable] = []
    unknown: set[int] = set()
    num_frames = 0
    try:
        for chunk in iter_chunks(seq, metric=metric, pool=pool or own, on_frames=advance):
            chunks.append(chunk.table)
            unknown |= chunk.unknown
            num_frames += chunk.num_frames
    except BaseException:
        if own is not None:
            own.close(terminate=True)
        raise
    finally:
        if bar is not None:
            bar.close()
    # the workers exit (~10 ms) while the table is refined
    closing = None if own is None else threading.Thread(target=own.close, name="mistool-close")
    if closing is not None:
        closing.start()
    try:
        table = refine(TrackTable.concat(chunks), cfg, smoothing)
    finally:
        if closing is not None:
            closing.join()
    return TrackResult(
        table=table,
        num_frames=num_frames,
        shape=seq.shape,
        unknown_values=tuple(sorted(unknown)),
        seconds=time.perf_counter() - start,
        name=seq.name,
        metric=parallel.metric_pose(metric, cfg),
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
        + preset_hint(vals, colour)
    )


def track(
    source: str | Path | Iterable[np.ndarray],
    config: Config | str | Path | None = None,
    *,
    progress: bool = False,
    workers: int | None = None,
    metric: bool = True,
    smoothing: str = "offline",
    pool: parallel.FramePool | None = None,
) -> TrackTable:
    """Track every instrument part through a mask sequence.

    Args:
        source: a folder of label images, a mask video, or an iterable of ``(H, W)``
            integer label arrays (``(H, W, 3)`` RGB for colour masks).
        config: a :class:`Config`, a path to a ``mistool.toml``, or None to read
            ``mistool.toml`` beside the frames (EndoVis'15 defaults without one).
        progress: show a tqdm progress bar on stderr.
        workers: processes for decoding and the per-frame work (default: the CPU
            cores, or 1 for a sequence shorter than :data:`POOL_MIN_FRAMES` frames). The
            output is the same whatever the number.
        metric: compute the metric 3D pose when the config has a ``[camera]``.
        smoothing: temporal filtering of the metric pose: ``"none"``, ``"offline"``
            (uses past and future frames) or ``"online"`` (causal).
        pool: run the per-frame work there instead (a :mod:`mistool.parallel` pool, e.g.
            a :class:`~mistool.parallel.DaskPool`; not closed); ``workers`` is then unused.

    Returns:
        The motion table, one row per (frame, instrument, part) seen, sorted; columns in
        :data:`mistool.model.COLUMNS` order. Empty (zero rows) when nothing was found.

    Raises:
        MistoolError: bad input path, mask format or config (one-line message).

    Warns:
        MistoolWarning: once, listing label values the config does not know.
    """
    result = run(
        source,
        config,
        progress=progress,
        workers=workers,
        metric=metric,
        smoothing=smoothing,
        pool=pool,
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
        self._metric = parallel.metric_pose(metric, self.config)
        self._tracker = tracking.IdentityTracker(self.config)
        self._frames: list[TrackTable] = []
        self._last: dict[tuple[str, str], tuple[TrackTable, ...]] = {}
        self._shape: tuple[int, int] | None = None
        self._unknown: set[int] = set()

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
        # the pose after the identity step (never measured for a blob it splits)
        result = parallel.observe_labels(
            arr, self.config, self._metric, defer_below=parallel.DEFER_ALWAYS
        )
        names, result = _identify(self._tracker, index, result, self.config, self._metric)
        rows = RowBuilder(self.config.fps)
        rows.add_frame(index, names, result.instances, result.metrics)
        raw = rows.take()
        self._frames.append(raw)
        new = {int(v) for v in result.unknown.ravel()} - self._unknown
        if new:
            self._unknown |= new
            warnings.warn(
                unknown_values_message(new, self.config.colour_masks), MistoolWarning, stacklevel=2
            )
        if self._metric:
            raw = raw.with_columns(pose_status=status_column(raw, raw.num_rows))
        raw = _with_status(raw, self.config)
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
            return refine(RowBuilder(self.config.fps).take(), self.config, "none")
        return refine(TrackTable.concat(self._frames), self.config, self.smoothing)
