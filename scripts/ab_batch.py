#!/usr/bin/env python
"""A/B: every process's CPU per frame of ``mistool.track`` with local tasks of different
sizes (frames per task, ``LocalPool(workers, batch_frames=N)``).

For each size, in turn and for ``--rounds`` rounds (the sizes alternating), a reused
2-worker ``LocalPool``: one warm-up run once its workers have started, then ``--runs``
runs of ``api.track(SEQ, pool=pool)``; each run's CPU is the workers' (``/proc``) plus
the caller's (``time.process_time``: every thread of this process), per frame. Prints the
median per size over every run of every round (and the wall-clock frames/s, which
depends on the machine's load). The output does not depend on the size (the tests
compare it across worker counts and task sizes).

Usage::

    python scripts/ab_batch.py /tmp/bt/one_2500 --sizes 16,64 --rounds 3
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
import warnings
from pathlib import Path


def _proc_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure(seq: Path, size: int, runs: int, workers: int) -> list[tuple[float, ...]]:
    """``runs`` runs' (total, workers', caller's CPU ms per frame, frames/s)."""
    from mistool import api, parallel
    from mistool.sequence import open_sequence

    frames = open_sequence(seq).num_frames
    out = []
    with parallel.LocalPool(workers, batch_frames=size) as pool:
        while pool.warming():
            time.sleep(0.05)
        api.track(seq, pool=pool)
        pids = list(pool._executor._processes)  # type: ignore[union-attr]
        for _ in range(runs):
            w0 = sum(_proc_cpu(p) for p in pids)
            c0, t0 = time.process_time(), time.perf_counter()
            api.track(seq, pool=pool)
            wall = time.perf_counter() - t0
            caller = time.process_time() - c0
            work = sum(_proc_cpu(p) for p in pids) - w0
            out.append(
                (1e3 * (work + caller) / frames, 1e3 * work / frames, 1e3 * caller / frames)
                + (frames / wall,)
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seq", type=Path, help="a sequence folder")
    ap.add_argument("--sizes", default="16,64", help="frames per task, comma-separated")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--runs", type=int, default=3, help="runs per size and round")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    sizes = [int(s) for s in args.sizes.split(",")]
    got: dict[int, list[tuple[float, ...]]] = {s: [] for s in sizes}
    for _ in range(args.rounds):
        for s in sizes:
            got[s] += measure(args.seq, s, args.runs, args.workers)
    print(f"{args.seq}: load average {os.getloadavg()[0]:.1f}")
    for s in sizes:
        total, work, caller, fps = (statistics.median(v) for v in zip(*got[s], strict=True))
        print(
            f"  {s:4d} frames per task: CPU ms/frame total {total:.3f} (workers {work:.3f}, "
            f"caller {caller:.3f}); {fps:.0f} frames/s"
        )


if __name__ == "__main__":
    main()
