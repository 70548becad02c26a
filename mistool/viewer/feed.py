"""Where a growing replay's frames come from while it is shown (no viser here).

A *feed* turns new results into :class:`~mistool.viewer.replay.ReplayPatch` es that the
viewer applies one by one (:meth:`ReplayViewer.apply`); it also says how far it has got,
for the GUI's progress line. :class:`CacheFeed` follows a background tracking job
(:mod:`mistool.background`) through its cache entry: each stored chunk becomes a patch as
soon as it is on disk; when the job stores the refined table, the whole timeline is
rewritten with it, window by window (:data:`~mistool.viewer.replay.WRITE_WINDOW` frames),
so the picture changes in place without going blank.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from mistool.background import JobSpec, TrackingJob
from mistool.cache import CacheEntry, Progress
from mistool.errors import MistoolError
from mistool.viewer.replay import WRITE_WINDOW, Replay, ReplayPatch

#: Seconds of history the frames-per-second estimate averages over.
RATE_WINDOW_S = 5.0


@dataclass
class FeedStatus:
    """How far a feed has got (for the progress line)."""

    done: int
    """Frames with results."""
    total: int | None
    """Frames expected (None: unknown, e.g. live use)."""
    rate: float
    """Frames per second recently (0 when unknown)."""
    phase: str
    """``"opening"`` (the job lists the frames and looks in the cache), ``"tracking"``,
    ``"refining"``, ``"done"``, ``"stopped"`` or ``"failed"``."""
    error: str | None = None
    """The one-line error that stopped tracking."""

    @property
    def seconds_left(self) -> float | None:
        """Estimated seconds until every frame is tracked (None when unknown)."""
        if self.total is None or self.rate <= 0:
            return None
        return max(0.0, (self.total - self.done) / self.rate)

    def text(self) -> str:
        """One line for the GUI."""
        total = f"{self.total:,}" if self.total is not None else "?"
        if self.phase == "opening":
            return "**Listing** the frames and looking in the cache..."
        if self.phase == "done":
            return f"**Tracked** all {self.done:,} frames (refined)"
        if self.phase == "failed":
            return f"**Tracking stopped** at frame {self.done:,} of {total}: {self.error}"
        if self.phase == "refining":
            return f"**Refining** {self.done:,} frames (trocar, smoothing)..."
        if self.phase == "stopped":
            return f"**Tracked** {self.done:,} of {total} frames (stopped)"
        left = self.seconds_left
        eta = f" · {_duration(left)} left" if left is not None else ""
        rate = f" · {self.rate:,.0f} frames/s" if self.rate > 0 else ""
        return f"**Tracking** {self.done:,} / {total} frames{rate}{eta}"


def _duration(seconds: float) -> str:
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class RateMeter:
    """Frames per second over the last :data:`RATE_WINDOW_S` seconds."""

    def __init__(self) -> None:
        self._history: collections.deque[tuple[float, int]] = collections.deque()

    def add(self, done: int, now: float | None = None) -> float:
        """Record ``done`` frames at ``now``; returns the recent rate."""
        now = time.monotonic() if now is None else now
        h = self._history
        if not h or h[-1][1] != done:
            h.append((now, done))
        while len(h) > 2 and now - h[1][0] > RATE_WINDOW_S:
            h.popleft()
        if len(h) < 2 or h[-1][0] <= h[0][0]:
            return 0.0
        return (h[-1][1] - h[0][1]) / (h[-1][0] - h[0][0])


class CacheFeed:
    """Grows a replay from a cache entry that a background job fills (or has filled).

    The entry may be unknown at first (``entry=None``): the job then finds it itself
    (:func:`mistool.background.locate`: listing the frames and computing the cache key cost
    a second at 100,000 frames, which would otherwise delay the server's start) and says
    which it is; only then is anything shown from it, so a changed sequence never shows
    another's stored frames.
    """

    def __init__(
        self,
        entry: CacheEntry | None,
        spec: JobSpec | None,
        total: int | None,
        *,
        on_names: Callable[[list[str]], None] | None = None,
    ) -> None:
        """
        Args:
            entry: the cache entry (complete, partial or new); None: the job finds it.
            spec: the job that fills it (None: show only what is stored; required when
                ``entry`` is None).
            total: frames in the sequence, when known (else learnt from the job).
            on_names: given the sequence's frame file names in frame order (as the job
                listed them) once the entry is known and before any frame is shown; e.g.
                :meth:`mistool.viewer.overlay.FrameStore.set_mask_names`.
        """
        if entry is None and spec is None:
            raise ValueError("CacheFeed: give the entry, or the job that finds it")
        self.entry = entry
        self.spec = spec
        self.total = total
        self.stored: Progress | None = entry.progress() if entry is not None else None
        """What the entry held before this run tracked anything (None until known)."""
        self.job: TrackingJob | None = None
        self._on_names = on_names
        self._shown = 0  # frames [0, _shown) applied from raw chunks
        self._final_shown = False
        self._meter = RateMeter()
        self._phase = "tracking" if entry is not None else "opening"
        self._error: str | None = None

    def start(self) -> None:
        """Start the background job, unless the entry is complete or it has started."""
        if self.job is not None or self.spec is None:
            return
        if self.entry is None or not self.entry.progress().complete:
            self.job = TrackingJob(self.spec)
            self.job.start()

    def _find_entry(self) -> bool:
        """Whether the entry is known (asks the job once more when it is not)."""
        if self.entry is not None:
            return True
        if self._phase == "failed":
            return False
        said = self.job.opened() if self.job is not None else None
        if said is None:
            return False
        entry, stored = said
        if entry is None or not isinstance(stored, Progress):
            self._phase, self._error = "failed", str(stored)
            return False
        names = entry.frame_names()
        if names is not None and self._on_names is not None:
            self._on_names(names)
        self.stored, self.total = stored, stored.total if stored.total else self.total
        self._phase = "tracking"
        self.entry = entry  # last: readers of ``entry`` see a complete state
        return True

    def stop(self) -> None:
        """Stop the job (what is stored stays, for the next launch to resume)."""
        if self.job is not None:
            self.job.stop()
        if self._phase in ("opening", "tracking", "refining"):
            self._phase = "stopped"

    @property
    def finished(self) -> bool:
        """Nothing more will come."""
        return self._phase in ("done", "failed", "stopped")

    def status(self) -> FeedStatus:
        """Where the feed stands now."""
        return FeedStatus(
            self._shown, self.total, self._meter.add(self._shown), self._phase, self._error
        )

    def poll(self, replay: Replay) -> Iterator[ReplayPatch]:
        """New patches since the last call (computed, not applied), in frame order;
        computed one at a time as the caller iterates."""
        if self.entry is None and not self._find_entry():
            if self._phase == "opening" and self.job is not None and not self.job.running:
                if not self._find_entry() and self._phase == "opening":  # its last word
                    self._phase = "stopped"
            return
        assert self.entry is not None
        if replay.expected_frames is None and self.total is not None:
            replay.expected_frames = self.total  # allocated once, not doubled as it grows
        progress = self.entry.progress()
        if progress.complete:
            if not self._final_shown:
                yield from self._final(replay)
            return
        for a, b in progress.chunks:
            if b <= self._shown:
                continue
            try:
                table = self.entry.read_chunk(a, b)
            except (OSError, ValueError, MistoolError):
                break  # being replaced (a restarted job): read again next time
            yield replay.compute(table, a, b)
            self._shown = b
        if progress.error:
            self._phase, self._error = "failed", progress.error
        elif self.total is not None and self._shown >= self.total:
            self._phase = "refining"
        job_ended = self.job is not None and not self.job.running
        if job_ended and not progress.error and not self.entry.progress().complete:
            self._phase = "stopped"

    def _final(self, replay: Replay) -> Iterator[ReplayPatch]:
        """The refined table, as patches over the whole timeline."""
        assert self.entry is not None
        table = self.entry.read_final()
        n = max(replay.num_frames, self._shown)
        if table.num_rows:
            n = max(n, int(table["frame"][-1]) + 1)
        for a in range(0, n, WRITE_WINDOW):
            yield replay.compute(table, a, min(n, a + WRITE_WINDOW))
        self._shown = n
        self._final_shown = True
        self._phase = "done"
