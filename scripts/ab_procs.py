#!/usr/bin/env python
"""A/B of two checkouts: every process's CPU per frame of ``mistool.track`` on a reused
local pool, the trees alternating in separate processes.

For each round and each tree in turn (``PYTHONPATH`` set to the tree: two copies of one
compiled kernel module cannot share a process), a child process starts a
``LocalPool(--workers)``, tracks each sequence once to warm up, then ``--runs`` times;
each run's CPU is the workers' (``/proc/PID/stat``, 10 ms ticks) and the caller's
(``time.process_time``: every thread of the child), per frame. Prints each round's
medians and, at the end, per tree and sequence the median over every run of every round
(ms per frame: workers, caller, total) and the machine's load average at the start and
end.

Usage::

    python scripts/ab_procs.py /tmp/after13 . /tmp/bt/cross_2500 /tmp/bt/one_2500 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path


def _proc_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def child(seqs: list[str], runs: int, workers: int) -> None:
    """One tree's runs: prints ``{seq: [(workers, caller), ...]}`` (ms per frame) as JSON."""
    from mistool import api, parallel
    from mistool.sequence import open_sequence

    out: dict[str, list[tuple[float, float]]] = {}
    with parallel.LocalPool(workers) as pool:
        while pool.warming():
            time.sleep(0.05)
        for seq in seqs:
            api.track(seq, pool=pool)
        pids = list(pool._executor._processes)  # type: ignore[union-attr]
        for seq in seqs:
            frames = open_sequence(Path(seq)).num_frames
            got = out[seq] = []
            for _ in range(runs):
                w0 = sum(_proc_cpu(p) for p in pids)
                c0 = time.process_time()
                api.track(seq, pool=pool)
                caller = time.process_time() - c0
                work = sum(_proc_cpu(p) for p in pids) - w0
                got.append((1e3 * work / frames, 1e3 * caller / frames))
    print(json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", type=Path, help="tree A (the before-tree; holds mistool/)")
    ap.add_argument("b", type=Path, help="tree B")
    ap.add_argument("seqs", nargs="+", help="sequence folders")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--runs", type=int, default=3, help="runs per sequence, tree and round")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.seqs, args.runs, args.workers)
        return
    trees = {"A": args.a.resolve(), "B": args.b.resolve()}
    every: dict[tuple[str, str], list[tuple[float, float]]] = {}
    print(f"load at start: {os.getloadavg()}", flush=True)
    for r in range(args.rounds):
        for tag, tree in trees.items():
            env = dict(os.environ, PYTHONPATH=str(tree))
            cmd = [sys.executable, __file__, str(tree), str(tree), *args.seqs, "--child"]
            cmd += ["--runs", str(args.runs), "--workers", str(args.workers)]
            res = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            got = json.loads(res.stdout.strip().splitlines()[-1])
            for seq, vals in got.items():
                every.setdefault((tag, seq), []).extend(vals)
                w = statistics.median(v[0] for v in vals)
                c = statistics.median(v[1] for v in vals)
                print(
                    f"round {r} {tag} {Path(seq).name}: workers {w:.3f} caller {c:.3f} "
                    f"total {w + c:.3f} ms/frame (load {os.getloadavg()[0]:.1f})",
                    flush=True,
                )
    print(f"load at end: {os.getloadavg()}")
    for seq in args.seqs:
        for tag in trees:
            vals = every[(tag, seq)]
            w = statistics.median(v[0] for v in vals)
            c = statistics.median(v[1] for v in vals)
            t = statistics.median(v[0] + v[1] for v in vals)
            print(
                f"{tag} {Path(seq).name}: workers {w:.3f} caller {c:.3f} total {t:.3f} "
                f"ms/frame (median of {len(vals)} runs)"
            )


if __name__ == "__main__":
    main()
