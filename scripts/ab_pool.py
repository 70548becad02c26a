#!/usr/bin/env python
"""Benchmark: frames/s and the caller's CPU of ``mistool.track`` on a reused local pool.

For each sequence: one warm-up run, then ``--runs`` runs of ``api.track(seq,
pool=LocalPool(workers))`` on the same pool; prints the median frames/s (and the best)
and the median CPU of this process per frame (``time.process_time``: its threads
included). Run it once per tree, alternately, for an A/B (``PYTHONPATH`` selects the
tree)::

    PYTHONPATH=/tmp/before python scripts/ab_pool.py /tmp/bt/one_2500 /tmp/bt/cross_2500
    PYTHONPATH=. python scripts/ab_pool.py /tmp/bt/one_2500 /tmp/bt/cross_2500
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

from mistool import api, parallel
from mistool.sequence import list_frames


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", nargs="+", type=Path)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    with parallel.LocalPool(args.workers) as pool:
        while pool.warming():
            time.sleep(0.01)
        for seq in args.sequences:
            api.track(seq, pool=pool)
        for seq in args.sequences:
            n = len(list_frames(seq))
            walls, cpus = [], []
            for _ in range(args.runs):
                t, c = time.perf_counter(), time.process_time()
                api.track(seq, pool=pool)
                walls.append(time.perf_counter() - t)
                cpus.append(time.process_time() - c)
            print(
                f"{seq.name}: {n / statistics.median(walls):.0f} frames/s "
                f"(best {n / min(walls):.0f}), caller {statistics.median(cpus) / n * 1e3:.3f} "
                "ms/frame",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
