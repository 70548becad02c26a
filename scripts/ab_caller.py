#!/usr/bin/env python
"""Benchmark: the caller's CPU per frame of ``mistool.track`` on a reused 2-worker pool.

For each sequence: ``--runs`` runs of ``api.track(seq, cfg, pool=LocalPool(workers))``
after one warm-up run; prints the medians of the caller's CPU (``time.process_time``:
every thread of this process, the pool's result and feeder threads included), of its
refinement (``api.refine``, which runs after the workers are done) and the CPU of each
thread of this process over all the runs (``/proc/self/task``, 10 ms ticks). Run it once
per tree, alternately, for an A/B (``PYTHONPATH`` selects the tree)::

    PYTHONPATH=/tmp/caller-before python scripts/ab_caller.py /tmp/bt/one_600 /tmp/bt/cross_600
    PYTHONPATH=. python scripts/ab_caller.py /tmp/bt/one_600 /tmp/bt/cross_600
"""

from __future__ import annotations

import argparse
import os
import statistics
import threading
import time
from typing import Any

import mistool
from mistool import api, parallel
from mistool.sequence import open_sequence


def _thread_cpu() -> dict[int, float]:
    """CPU seconds (user + system) per thread id of this process."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{tid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        out[int(tid)] = (int(fields[11]) + int(fields[12])) / tick
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sequences", nargs="+")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    refine = api.refine
    refine_cpu: list[float] = []

    def timed_refine(*a: Any, **k: Any) -> Any:
        c = time.process_time()
        out = refine(*a, **k)
        refine_cpu.append(time.process_time() - c)
        return out

    api.refine = timed_refine  # type: ignore[assignment]
    with parallel.LocalPool(args.workers) as pool:
        for seq in args.sequences:
            cfg = mistool.load_config(seq)
            frames = open_sequence(seq, cfg).num_frames or 1
            api.track(seq, cfg, pool=pool)  # warm-up
            refine_cpu.clear()
            caller = []
            before = _thread_cpu()
            for _ in range(args.runs):
                c = time.process_time()
                api.track(seq, cfg, pool=pool)
                caller.append((time.process_time() - c) * 1000 / frames)
            after = _thread_cpu()
            names = {t.native_id: t.name for t in threading.enumerate()}
            threads = ", ".join(
                f"{names.get(t, t)} {(s - before.get(t, 0.0)) * 1000 / frames / args.runs:.3f}"
                for t, s in after.items()
                if s > before.get(t, 0.0)
            )
            print(
                f"{seq}: caller {statistics.median(caller):.3f} ms/frame "
                f"(runs {', '.join(f'{x:.3f}' for x in caller)}), refinement "
                f"{statistics.median(refine_cpu) * 1000 / frames:.3f} ms/frame; "
                f"per thread: {threads} ms/frame"
            )


if __name__ == "__main__":
    main()
