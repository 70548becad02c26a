"""Tracking in the background, chunk by chunk, into a cache entry (no viser here).

``mistool serve`` starts a :class:`TrackingJob` and shows each chunk as soon as it is
stored: a child process tracks the sequence in frame order, stores the raw rows of every
chunk (and the tracker's state after it) in a :class:`~mistool.cache.CacheEntry`, and at
the end applies the sequence-level refinement (paper motion over the whole sequence, trocar,
smoothing) and stores the finished table. The server reads the entry; it never waits for the
child. Stopping kills the child; what was stored stays valid, and the next job on the same
entry resumes after the last stored chunk.

Why a process and not a thread: the tracker's Python parts would otherwise share the GIL
with the viewer's event loop, and its memory (rows, refinement) would add to the server's.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, overload

from mistool.cache import CacheEntry, Progress
from mistool.config import Config
from mistool.errors import MistoolError
from mistool.forksafe import fork_is_safe as fork_is_safe  # (the command line's too)
from mistool.model import TrackTable
from mistool.sequence import MaskSequence

if TYPE_CHECKING:
    from mistool.parallel import FrameResult

#: Frames of the first chunks: small at first so that the first picture comes at once,
#: then growing (fewer files, less overhead), at most the last value. A chunk also ends
#: at the sequence's first frame with an instrument drawn in 3D (often tens of frames in:
#: the tools enter), so that it is on screen without waiting for the end of its chunk.
CHUNK_SCHEDULE = (25, 50, 100, 200, 400, 800)
#: Frame files stat'ed for the cache entry's frames digest per frame tracked, until every
#: file is (a second at 100,000 frames, spread over the first few chunks instead of
#: delaying the first ones).
STATS_PER_FRAME = 50
#: Frames of paper-motion context carried over a chunk boundary (Eq. 5 needs two).
_PAPER_CONTEXT = 2


def chunk_sizes() -> Iterator[int]:
    """Chunk lengths in frames: :data:`CHUNK_SCHEDULE`, then its last value forever."""
    yield from CHUNK_SCHEDULE
    yield from itertools.repeat(CHUNK_SCHEDULE[-1])


@dataclass(frozen=True)
class JobSpec:
    """What to track (picklable: it is sent to the child process)."""

    sequence: Path
    """The folder of label images or the mask video."""
    config: Config
    """The effective config."""
    entry: CacheEntry | None = None
    """Where chunks and the finished table go; None: the job finds it (:func:`locate`:
    it lists the folder and computes the cache key itself, so its caller need not)."""
    metric: bool = True
    """Compute the metric pose when the config has a camera."""
    smoothing: str = "offline"
    """Sequence-level smoothing applied when tracking finishes."""
    workers: int = 1
    """Processes for the per-frame work (1: in the tracking process itself)."""
    files: Sequence[Path] = ()
    """The folder's frame files in order, when the caller has listed them already (saves
    listing a long folder again)."""
    fresh: bool = False
    """Forget what the entry holds and track from the start."""
    root: Path | None = None
    """The cache's folder, where :func:`locate` looks (None: :func:`mistool.cache.cache_root`)."""

    def key_options(self) -> dict[str, Any]:
        """The tracking options that are part of the cache key."""
        return {"metric": self.metric, "smoothing": self.smoothing}


def locate(spec: JobSpec) -> tuple[JobSpec, Sequence[Any]]:
    """``spec`` with its frame files listed (a folder) and its cache entry found, and the
    files to ``stat`` for the entry's :func:`~mistool.cache.frames_digest` (directory
    entries, paths, or the video), in frame order.

    The entry's key (:func:`mistool.cache.cache_key`) covers the frame names, the config and
    the tracking options: a listing (``mistool serve`` does it here, in the tracking
    process, not before its server starts), without a ``stat`` per frame (symlinks are not
    followed either): the files' sizes and times are checked by :func:`_settle` when
    something is stored, else digested while tracking. The entry found is marked used and
    the cache's size policy applied (:func:`mistool.cache.enforce_limit`); ``spec.fresh``
    empties it.

    Raises:
        InputPathError: the folder cannot be listed.
    """
    from mistool.cache import cache_key, enforce_limit, open_entry
    from mistool.sequence import scan_frames

    files: Sequence[Path] = spec.files
    stat_of: Sequence[Any] = files or [spec.sequence]
    if not files and spec.sequence.is_dir():
        stat_of = scan_frames(spec.sequence, check_links=False)
        files = FrameFiles(spec.sequence, [e.name for e in stat_of])
    entry = spec.entry
    if entry is None:
        key = cache_key(spec.sequence, spec.config, stat_of, **spec.key_options())
        entry = open_entry(key, spec.root)
        with contextlib.suppress(OSError):
            entry.touch()
            enforce_limit(keep=entry)
    if spec.fresh:
        entry.remove()
    return replace(spec, entry=entry, files=files, fresh=False), stat_of


class FrameFiles(Sequence[Path]):
    """A folder's frame files in order, each path made when asked for (making 100,000
    ``Path`` objects at once costs about half a second)."""

    def __init__(self, folder: Path, names: list[str]) -> None:
        self.folder = folder
        self.names = names
        """The file names, in frame order."""

    def __len__(self) -> int:
        return len(self.names)

    @overload
    def __getitem__(self, index: int) -> Path: ...
    @overload
    def __getitem__(self, index: slice) -> list[Path]: ...
    def __getitem__(self, index: int | slice) -> Path | list[Path]:
        if isinstance(index, slice):
            return [self.folder / n for n in self.names[index]]
        return self.folder / self.names[index]


def _open(spec: JobSpec) -> MaskSequence:
    """The sequence to track (from ``spec.files`` when the folder is listed already)."""
    from mistool.sequence import open_sequence

    return open_sequence(spec.sequence, spec.config, files=spec.files or None)


# -- the child ----------------------------------------------------------------------------
def _paper(table: TrackTable, context: TrackTable | None, config: Config) -> TrackTable:
    """Paper motion of a chunk, continued from the previous chunk's last rows."""
    from mistool import paper

    focal = config.camera.fx if config.camera is not None else 1.0
    if context is None or context.num_rows == 0:
        return paper.paper_motion(table, focal_px=focal)
    both = paper.paper_motion(TrackTable.concat([context, table]), focal_px=focal)
    first = int(table["frame"].min()) if table.num_rows else 0
    return both[both["frame"] >= first]


def _tail(table: TrackTable, frames: int) -> TrackTable:
    if table.num_rows == 0:
        return table
    last = int(table["frame"].max())
    return table[table["frame"] > last - frames]


def _from(seq: MaskSequence, start: int) -> MaskSequence:
    """The same sequence without its first ``start`` frames (frame names kept)."""
    if start == 0:
        return seq
    return MaskSequence(
        seq.kind,
        seq.name,
        seq.config,
        lambda: itertools.islice(seq.frames(), start, None),
        None if seq.num_frames is None else seq.num_frames - start,
        seq.path,
        lossy=seq.lossy,
    )


def _displayed(table: TrackTable, config: Config, measured: bool) -> TrackTable:
    """A raw chunk with what the viewer shows during tracking: the per-frame
    ``pose_status`` (as :meth:`mistool.Tracker.update` gives it)."""
    from mistool import api

    if measured:
        from mistool.pose.status import status_column

        table = table.with_columns(pose_status=status_column(table, table.num_rows))
    return api._with_status(table, config)


def _drawn(result: FrameResult, measured: bool) -> bool:
    """Whether the viewer draws something of this frame in 3D: an instrument with a
    metric pose of some part (without the metric pose: any instrument, in the paper's
    geometry)."""
    if not measured:
        return bool(result.instances)
    if result.metrics is None:
        return False
    from mistool.pose.measure import ROW_KEYS, SLOT_OF

    end_x = result.metrics[:, :, ROW_KEYS.index("end_x_mm")]
    return any(
        math.isfinite(end_x[k, SLOT_OF[part]])
        for k, inst in enumerate(result.instances)
        for part in inst.parts
    )


def _raw(table: TrackTable) -> TrackTable:
    """A stored chunk as the refinement wants it (without the displayed status)."""
    return TrackTable({c: table[c] for c in table.columns if c != "pose_status"})


def _settle(spec: JobSpec, seq: MaskSequence, stat_of: Sequence[Any]) -> tuple[int, Any]:
    """Open ``spec.entry`` for tracking ``seq``: (first frame to track, the identity
    tracker to go on with). What it stores is kept only if it comes from the same files
    (their :func:`~mistool.cache.frames_digest` now is the one stored with it) and can be
    resumed (the tracker's state is stored); else the entry starts again. The frame names
    are stored with it (:meth:`~mistool.cache.CacheEntry.write_frame_names`).
    """
    from mistool import tracking
    from mistool.cache import frames_digest

    entry = spec.entry
    assert entry is not None
    info = {"sequence": str(spec.sequence)}
    entry.begin(seq.num_frames, info)
    progress = entry.progress()
    stored = progress.complete or progress.done > 0
    if stored and entry.frames_digest() != frames_digest(stat_of):  # touched: start again
        entry.remove()
        entry.begin(seq.num_frames, info)
        progress = entry.progress()
    start = 0 if progress.complete else progress.done
    tracker = entry.state(start) if start else None
    if tracker is None and not progress.complete:  # nothing to resume from: start again
        if start:
            entry.remove()
            entry.begin(seq.num_frames, info)
        start, tracker = 0, tracking.IdentityTracker(seq.config)
    files = spec.files
    if files:
        names = files.names if isinstance(files, FrameFiles) else [f.name for f in files]
        entry.write_frame_names(names)
    return start, tracker


def track_into(
    spec: JobSpec,
    stop: Any = None,
    on_open: Callable[[CacheEntry, Progress], None] | None = None,
    on_shown: Callable[[], None] | None = None,
) -> Progress:
    """Track ``spec.sequence`` into ``spec.entry`` (found by :func:`locate` when None),
    resuming after its last stored chunk (when the tracker's state is stored with it;
    else from the start), then refine.

    Args:
        spec: what to track and where.
        stop: an event; when set, return after the current chunk.
        on_open: called once the entry is ready, before any tracking, with the entry and
            what it holds (the frame tracking resumes at: ``done``; ``complete``: nothing
            to do).
        on_shown: called once the first chunk with a frame the viewer draws is stored
            (the child lowers its priority then: :data:`CHILD_NICE`).

    Returns:
        The entry's progress at the end.

    Raises:
        MistoolError: bad input (also recorded in the entry, once there is one).
    """
    entry = spec.entry
    try:
        spec, stat_of = locate(spec)
        entry = spec.entry
        assert entry is not None
        seq = _open(spec)
        start, tracker = _settle(spec, seq, stat_of)
        progress = entry.progress()
        if on_open is not None:
            on_open(entry, progress)
        if not progress.complete:
            stats = stat_of if start == 0 else None
            _track_chunks(spec, seq, start, tracker, stop, stats, on_shown)
    except MistoolError as exc:
        if entry is not None:
            entry.fail(str(exc))
        raise
    return entry.progress()


def _track_chunks(
    spec: JobSpec,
    seq: MaskSequence,
    start: int,
    tracker: Any,
    stop: Any,
    stat_of: Sequence[Any] | None,
    on_shown: Callable[[], None] | None = None,
) -> None:
    """Track ``seq`` from frame ``start`` chunk by chunk into ``spec.entry``; refine and
    store the finished table after the last frame (unless ``stop`` is set before).

    ``stat_of`` (a run from the first frame): the files whose digest is stored with the
    entry once every one is in it. They are stat'ed in frame order, each before it is read,
    :data:`STATS_PER_FRAME` per frame tracked, so that the first frames are shown without
    waiting for a ``stat`` of every frame (a run stopped before the digest is stored is
    not resumed: it starts again).
    """
    from mistool import api, parallel
    from mistool.cache import FramesDigest
    from mistool.rows import RowBuilder

    digest = FramesDigest() if stat_of is not None else None
    stated = 0  # files of stat_of in the digest
    done_digest: str | None = None

    entry, cfg = spec.entry, seq.config
    assert entry is not None
    measured = parallel.metric_pose(spec.metric, cfg)
    progress = entry.progress()
    context = _tail(entry.read_chunk(*progress.chunks[-1]), _PAPER_CONTEXT) if start else None
    pool = parallel.LocalPool(spec.workers) if spec.workers > 1 else None
    batch = pool.batch_frames if pool is not None else 1
    work = parallel.batches(_from(seq, start), measured, batch)
    results = enumerate(parallel.ordered_results(work, pool), start)
    stored_one = start > 0  # a frame the viewer draws is stored: chunks of any length
    try:
        for size in chunk_sizes():
            if digest is not None and stat_of is not None and stated < len(stat_of):
                upto = min(len(stat_of), max(start + size, stated + STATS_PER_FRAME * size))
                digest.add(stat_of[stated:upto])
                stated = upto
                if stated == len(stat_of):
                    done_digest = digest.hexdigest()
            rows = RowBuilder(cfg.fps)
            end = start
            for index, (name, result) in itertools.islice(results, size):
                seq.check_shape(name, result.shape)
                names, result = api._identify(tracker, index, result, cfg, measured)
                rows.add_frame(index, names, result.instances, result.metrics)
                end = index + 1
                if not stored_one and _drawn(result, measured):  # shown at once
                    stored_one = True
                    break
            if end == start:
                break
            table = _paper(_displayed(rows.take(), cfg, measured), context, cfg)
            if done_digest is not None:  # before the rows it covers: a stop between the
                # two (Ctrl+C) keeps the chunks stored so far resumable, not orphaned
                entry.set_frames_digest(done_digest)
                done_digest = digest = None
            entry.add_chunk(start, end, table, tracker)
            if stored_one and on_shown is not None:
                on_shown()
                on_shown = None
            context, start = _tail(table, _PAPER_CONTEXT), end
            if stop is not None and stop.is_set():
                return
    finally:
        if pool is not None:
            pool.close()
    if done_digest is not None:
        entry.set_frames_digest(done_digest)
    raw = _raw(entry.read_raw())
    entry.finish(api.refine(raw, cfg, spec.smoothing))


#: Messages the tracking process sends its parent (the first one only): the entry found
#: and what it held, or the one-line error that stopped it before.
OPENED, FAILED = "opened", "failed"


#: Niceness the tracking process adds to its own once its first picture is stored: the
#: server and the browser (on 2 cores, chromium loading the page with software WebGL
#: wants more than one) go first, the tracking takes what they leave.
CHILD_NICE = 10


def _yield_to_the_viewer() -> None:
    """Lower this process's priority by :data:`CHILD_NICE` (where the OS allows)."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(CHILD_NICE)


def _child(spec: JobSpec, conn: Any) -> None:
    """Entry point of the child process: quiet, no traceback for bad input; tells the
    parent (``conn``) which entry it tracks into, or why it could not start.

    The parent starts the child daemonic (so that it never outlives the parent, which
    does not wait for it at exit), but multiprocessing forbids a daemonic process its
    own children; the flag is cleared here, in the child only, so that ``spec.workers > 1``
    can start its worker pool. The workers exit by themselves when this child is gone
    (:func:`mistool.parallel.LocalPool`)."""
    from mistool.forkserver import forget_inherited_fork_server

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us
    multiprocessing.current_process().daemon = False
    forget_inherited_fork_server()  # forked from a process that had workers of its own
    said = False

    def opened(entry: CacheEntry, progress: Progress) -> None:
        nonlocal said
        conn.send((OPENED, entry, progress))
        said = True

    try:
        track_into(spec, on_open=opened, on_shown=_yield_to_the_viewer)
    except MistoolError as exc:
        if not said:
            with contextlib.suppress(OSError, ValueError):
                conn.send((FAILED, str(exc), None))
    finally:
        conn.close()


# -- the parent ---------------------------------------------------------------------------
class TrackingJob:
    """A child process tracking into a cache entry; :meth:`stop` kills it at any time."""

    def __init__(self, spec: JobSpec) -> None:
        self.spec = spec
        self._process: multiprocessing.process.BaseProcess | None = None
        self._conn: Any = None  # the receiving end of the child's messages
        self.started = 0.0
        self.method = ""  # how the child was started: "fork" or "spawn"

    def start(self) -> None:
        """Start the child (returns at once)."""
        # Forking a process with threads is unsafe (a lock held by another thread stays
        # held in the child): fork only while no other thread could hold one (mistool
        # serve starts tracking before its server), which spares the child a new
        # interpreter and its imports (about half a second before its first frame).
        forkable = "fork" in multiprocessing.get_all_start_methods()
        method = "fork" if forkable and fork_is_safe() else "spawn"
        ctx: Any = multiprocessing.get_context(method)
        self._conn, send = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_child, args=(self.spec, send), name="mistool-track")
        self._process.daemon = True
        self.method = method
        self.started = time.monotonic()
        self._process.start()
        send.close()  # the child has its own: the pipe ends when the child does

    def opened(self) -> tuple[CacheEntry | None, Progress | str] | None:
        """The child's word on its cache entry, without waiting: None while it is still
        looking (listing the frames, computing the key); ``(entry, what it held)`` once
        found; ``(None, error)`` when the child stopped before (a one-line error)."""
        conn = self._conn
        if conn is None:
            return None
        try:
            if not conn.poll():
                return None
            kind, value, progress = conn.recv()
        except (EOFError, OSError):
            kind, value = FAILED, "the tracking process ended before it started"
        conn.close()
        self._conn = None
        return (value, progress) if kind == OPENED else (None, str(value))

    @property
    def running(self) -> bool:
        """Whether the child is still working."""
        return self._process is not None and self._process.is_alive()

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the child now (stored chunks stay; the next job resumes after them)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        p = self._process
        if p is None:
            return
        if p.is_alive():
            p.terminate()
            p.join(timeout)
            if p.is_alive():
                p.kill()
                p.join(timeout)
        p.close()
        self._process = None

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the child ends; True if it did."""
        p = self._process
        if p is None:
            return True
        p.join(timeout)
        return not p.is_alive()
