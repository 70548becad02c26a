#!/usr/bin/env python
"""Per-stage CPU time of ``mistool track`` on one sequence, in one process.

Runs ``mistool.api.iter_track(seq, workers=1)`` + ``refine`` + the CSV writer with
timers wrapped around each stage's entry point (CPU time, ``time.process_time``; each
stage's own time, nested stages excluded):

- decode: reading a frame's label image (``parallel._load``);
- scan: the label image read once for the per-frame work (``scan_labels``: its
  foreground bounds, then its runs of equal values; before commit d7072b5 these passes
  were OpenCV's masks inside ``observe_frame``, i.e. in "instances", and the bounds
  outside every stage);
- boxes: Algorithm 1 per part (``instances._fit_instance``: all parts of an instance and
  its centroid and bounds in one call since 2026-11-27's ninth session; before it,
  ``instances._fit_runs`` per part, the instance's sums then counted in "instances"; and
  ``geometry.fit_part`` called by ``observe_frame``);
- instances: the rest of ``observe_frame`` (components, grouping);
- identity: ``IdentityTracker.resolve`` (including the blob splits and the boxes of the
  split pieces): the sequential step;
- pose: the per-frame metric pose (``parallel.measure``; also the split pieces');
- refinement: ``api.refine`` (paper motion, trocar, temporal filter);
- csv: ``export.write_csv``.

Beside it, the decode-only baseline (``cv2.imread(path, cv2.IMREAD_UNCHANGED)`` over the
same files) measured in the same run. The sequence is made with ``mistool synth`` when
missing (default: 2,500 frames, two instruments, EndoVis'17 merged labels, crossing).
``--cprofile N`` also prints the N costliest functions under ``resolve`` (cProfile; that
first run's stage times then include cProfile's own overhead: compare runs without it).
OpenCV runs on ``--cv-threads`` threads (default 1, as in the worker processes; with
OpenCV's default pool, its threads spinning after one stage's calls are counted in the
next stage's CPU time: identity 1.39-1.45 against 0.98 ms/frame at commit 097b037).

Usage::

    python scripts/profile_stages.py [--seq /tmp/cross2500] [--frames 2500] [--runs 3]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2

from mistool import api, parallel
from mistool.export import write_csv
from mistool.kernels import warm
from mistool.model import TrackTable
from mistool.sequence import list_frames, open_sequence
from mistool.synth import synthesize
from mistool.tracking import IdentityTracker, instances

STAGES = ("decode", "scan", "boxes", "instances", "identity", "pose", "refinement", "csv")


class StageClock:
    """Exclusive CPU time per stage: a stage's time excludes the stages nested in it."""

    def __init__(self) -> None:
        self.total = dict.fromkeys(STAGES, 0.0)
        self.calls = dict.fromkeys(STAGES, 0)
        self._stack: list[list[Any]] = []  # [stage, start, nested time]

    def wrap(self, stage: str, fn: Callable[..., Any], inside: str | None = None) -> Any:
        """``fn`` timed as ``stage``; with ``inside``, only when not under that stage
        (its time then stays with the enclosing stage)."""

        def timed(*args: Any, **kwargs: Any) -> Any:
            if inside is not None and any(s[0] == inside for s in self._stack):
                return fn(*args, **kwargs)
            self.calls[stage] += 1
            self._stack.append([stage, time.process_time(), 0.0])
            try:
                return fn(*args, **kwargs)
            finally:
                name, t0, nested = self._stack.pop()
                spent = time.process_time() - t0
                self.total[name] += spent - nested
                if self._stack:
                    self._stack[-1][2] += spent

        return timed


def profiled_run(seq: Path, out_csv: Path, prof: cProfile.Profile | None) -> StageClock:
    """One tracking run with the stage clock (and cProfile under ``resolve``) installed."""
    clock = StageClock()
    saved = (
        parallel._load,
        instances.fit_part,
        instances._fit_instance,
        parallel.scan_labels,
        parallel.tracking.observe_frame,
        IdentityTracker.resolve,
        parallel.measure,
        api.refine,
    )
    original = IdentityTracker.resolve
    resolve = original
    if prof is not None:

        def resolve_prof(self: IdentityTracker, *a: Any) -> Any:
            return prof.runcall(original, self, *a)

        resolve = resolve_prof  # type: ignore[assignment]
    try:
        parallel._load = clock.wrap("decode", parallel._load)
        instances.fit_part = clock.wrap("boxes", instances.fit_part, inside="identity")
        instances._fit_instance = clock.wrap("boxes", instances._fit_instance)
        parallel.scan_labels = clock.wrap("scan", parallel.scan_labels)
        parallel.tracking.observe_frame = clock.wrap("instances", instances.observe_frame)
        IdentityTracker.resolve = clock.wrap("identity", resolve)  # type: ignore[method-assign]
        parallel.measure = clock.wrap("pose", parallel.measure)
        refine = clock.wrap("refinement", api.refine)
        raw = TrackTable.concat(list(api.iter_track(seq, workers=1)))
        table = refine(raw, open_sequence(seq).config)
        clock.wrap("csv", write_csv)(table, out_csv)
    finally:
        (
            parallel._load,
            instances.fit_part,
            instances._fit_instance,
            parallel.scan_labels,
            parallel.tracking.observe_frame,
            IdentityTracker.resolve,
            parallel.measure,
            api.refine,
        ) = saved  # type: ignore[method-assign]
    return clock


def decode_only(seq: Path) -> float:
    """CPU seconds to decode every frame with ``cv2.imread(path, IMREAD_UNCHANGED)``."""
    t0 = time.process_time()
    for path in list_frames(seq):
        cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return time.process_time() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seq", type=Path, default=Path(tempfile.gettempdir()) / "mistool_cross")
    ap.add_argument("--frames", type=int, default=2500)
    ap.add_argument("--instruments", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--cprofile", type=int, default=0, metavar="N")
    ap.add_argument(
        "--cv-threads",
        type=int,
        default=1,
        help="OpenCV threads (default 1, as in the worker processes: with more, a stage's "
        "CPU time includes the OpenCV pool's threads still spinning after the stages "
        "before it)",
    )
    args = ap.parse_args()
    cv2.setNumThreads(args.cv_threads)
    if not (args.seq / "synth.json").exists():
        print(f"making {args.seq} with mistool synth ({args.frames} frames) ...", flush=True)
        synthesize(
            args.seq,
            frames=args.frames,
            instruments=args.instruments,
            seed=args.seed,
            preset="endovis17",
        )
    n = len(list_frames(args.seq))
    # the compiled kernels loaded before any timing, as the worker processes' fork server
    # does (their first import, numba's included, costs ~0.5 s)
    warm()
    runs: list[dict[str, float]] = []
    calls: dict[str, int] = {}
    base: list[float] = []
    prof = cProfile.Profile() if args.cprofile else None
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.runs):
            base.append(decode_only(args.seq))
            clock = profiled_run(args.seq, Path(tmp) / "m.csv", prof if k == 0 else None)
            runs.append(clock.total)
            calls = clock.calls
    med = {s: statistics.median(r[s] for r in runs) for s in STAGES}
    dec = statistics.median(base)
    print(f"\n{args.seq}: {n} frames; median of {args.runs} run(s); CPU ms per frame")
    print(f"{'stage':<12} {'ms/frame':>9} {'x decode-only':>14} {'calls':>7}")
    for s in STAGES:
        print(f"{s:<12} {1000 * med[s] / n:>9.3f} {med[s] / dec:>14.2f} {calls[s]:>7}")
    total = sum(med.values())
    print(f"{'total':<12} {1000 * total / n:>9.3f} {total / dec:>14.2f}")
    print(f"{'cv2.imread':<12} {1000 * dec / n:>9.3f} {'1.00':>14}  (decode-only baseline)")
    if prof is not None:
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(args.cprofile)
        print("\ncProfile under IdentityTracker.resolve (first run), by own time:")
        print(s.getvalue())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
