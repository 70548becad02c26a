#!/usr/bin/env python
"""Ctrl+C at random moments: ``mistool track SEQ --workers 2`` on a 3,000-frame sequence
(a 60-frame synthetic crossing sequence linked over), SIGINT to the whole process group
(as a terminal's Ctrl+C) 1-4 s after the start. Each run must end with exit code 130, the
one line ``mistool: interrupted`` and nothing else; a run still alive 20 s after the
SIGINT counts as a hang (its threads' stacks are printed, via faulthandler).

Usage::

    scripts/stress_ctrl_c.py [--runs 40] [--seed 11] [--workdir /tmp/mistool-ctrl-c]
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

#: Seconds a run may take to stop after the SIGINT before it counts as a hang.
HANG_S = 20.0
#: Frames of the linked sequence (long enough that no run finishes before its SIGINT).
FRAMES = 3000


def _sequence(workdir: Path) -> Path:
    from mistool.synth import synthesize

    base, long_seq = workdir / "cross", workdir / "long"
    if not base.exists():
        synthesize(base, frames=60, instruments=2, seed=3)
    if not long_seq.exists():
        long_seq.mkdir(parents=True)
        shutil.copy(base / "mistool.toml", long_seq / "mistool.toml")
        frames = sorted(base.glob("*.png"))
        for k in range(FRAMES):
            (long_seq / f"{k:06d}.png").symlink_to(frames[k % len(frames)])
    return long_seq


def _one_run(seq: Path, out: Path, delay: float) -> tuple[str, float, str]:
    code = (
        "import faulthandler, signal, sys; faulthandler.register(signal.SIGUSR1, "
        "all_threads=True); from mistool.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    args = ["track", str(seq), "-o", str(out), "--workers", "2"]
    child = subprocess.Popen(
        [sys.executable, "-c", code, *args],
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    time.sleep(delay)
    start = time.monotonic()
    os.killpg(child.pid, signal.SIGINT)
    try:
        _, err = child.communicate(timeout=HANG_S)
    except subprocess.TimeoutExpired:
        os.kill(child.pid, signal.SIGUSR1)
        time.sleep(1.5)
        child.kill()
        _, err = child.communicate()
        return "hang", HANG_S, err
    seconds = time.monotonic() - start
    clean = child.returncode == 130 and err == "mistool: interrupted\n"
    return ("clean" if clean else f"exit {child.returncode}"), seconds, err


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/mistool-ctrl-c"))
    args = ap.parse_args()
    seq = _sequence(args.workdir)
    rng = random.Random(args.seed)
    counts: dict[str, int] = {}
    stops = []
    for k in range(args.runs):
        delay = rng.uniform(1.0, 4.0)
        outcome, seconds, err = _one_run(seq, args.workdir / f"out{k}.csv", delay)
        counts[outcome] = counts.get(outcome, 0) + 1
        if outcome == "clean":
            stops.append(seconds)
        else:
            print(f"run {k} (SIGINT after {delay:.2f} s): {outcome}\n{err[-3000:]}", flush=True)
    stops.sort()
    summary = ", ".join(f"{n} {what}" for what, n in sorted(counts.items()))
    print(f"{args.runs} runs: {summary}")
    if stops:
        print(
            f"clean stops: {stops[0]:.2f}-{stops[-1]:.2f} s after the SIGINT "
            f"(median {stops[len(stops) // 2]:.2f} s)"
        )


if __name__ == "__main__":
    main()
