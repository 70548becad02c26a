#!/usr/bin/env python
"""A/B: how many identified frames the caller may keep waiting for their pose
(``parallel.PENDING_FRAMES_PER_WORKER``) against the run's wall time.

When the identity step splits a blob, or a frame's pose was deferred, the frame waits in
the caller (``mistool.api.identified``) while its pose is measured in a worker; once more
than ``PENDING_FRAMES_PER_WORKER x workers`` frames wait, the caller blocks on the oldest
one's task, which sits in the workers' queue behind the batches submitted before it, and
while it blocks it submits no new batch. This script runs ``api.track(seq, pool=...)`` on
one reused ``LocalPool`` with each value in turn (``--rounds`` rounds, the values
alternating, ``--runs`` runs each), and prints per value the medians of: wall time per
frame, the caller's CPU per frame (``time.process_time``), the workers' CPU per frame
(``/proc``), the time the caller spent blocked on a pose task (``_Pending.finish``), and
the caller's peak of frames waiting. Outputs are compared (every column, bit for bit) with
the first value's. Wall times depend on the machine's load: run it under
``scripts/realtime.sh``::

    scripts/realtime.sh env PYTHONPATH=. python scripts/ab_pending.py /tmp/bt/cross_2500 \\
        --pending 32 128 512
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from mistool import api, parallel
from mistool.model import TrackTable
from mistool.sequence import list_frames


def _proc_cpu(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _same(a: TrackTable, b: TrackTable) -> bool:
    if list(a.columns) != list(b.columns) or a.num_rows != b.num_rows:
        return False
    for name in a.columns:
        x, y = np.asarray(a[name]), np.asarray(b[name])
        if x.dtype.kind == "f":
            if not np.array_equal(x, y, equal_nan=True):
                return False
        elif not np.array_equal(x, y):
            return False
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--pending", type=int, nargs="+", default=[32, 128, 512])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    n = len(list_frames(args.sequence))
    blocked = [0.0]
    finish = api._Pending.finish

    def timed_finish(self: api._Pending) -> object:
        t = time.perf_counter()
        try:
            return finish(self)
        finally:
            blocked[0] += time.perf_counter() - t

    api._Pending.finish = timed_finish  # type: ignore[method-assign]
    figures: dict[int, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    reference: TrackTable | None = None
    with parallel.LocalPool(args.workers) as pool:
        while pool.warming():
            time.sleep(0.01)
        pids = list(pool._executor._processes) if pool._executor else []
        api.track(args.sequence, pool=pool)
        for _ in range(args.rounds):
            for value in args.pending:
                parallel.PENDING_FRAMES_PER_WORKER = value
                for _ in range(args.runs):
                    blocked[0] = 0.0
                    w0 = sum(_proc_cpu(p) for p in pids)
                    c0, t0 = time.process_time(), time.perf_counter()
                    table = api.track(args.sequence, pool=pool)
                    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                    work = sum(_proc_cpu(p) for p in pids) - w0
                    f = figures[value]
                    f["wall"].append(wall / n * 1e3)
                    f["caller"].append(cpu / n * 1e3)
                    f["workers"].append(work / n * 1e3)
                    f["blocked"].append(blocked[0])
                    if reference is None:
                        reference = table
                    elif not _same(reference, table):
                        print(f"pending {value}: a different table")
                        return 1
    print(f"{args.sequence} ({n} frames), {args.workers} workers, load {os.getloadavg()}")
    print("pending/worker  wall ms/frame  caller CPU  workers CPU  caller blocked (s)")
    for value, f in figures.items():
        med = {k: statistics.median(v) for k, v in f.items()}
        print(
            f"{value:14d}  {med['wall']:13.3f}  {med['caller']:10.3f}  "
            f"{med['workers']:11.3f}  {med['blocked']:8.3f}"
            f"   (walls {' '.join(f'{w:.3f}' for w in f['wall'])})"
        )
    print("outputs: identical")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
