#!/usr/bin/env python
"""Benchmark: end-to-end ``mistool track`` versus merely decoding the same PNGs.

Generates ``--frames`` 720x576 8-bit label PNGs (EndoVis'15 values: shaft 160, clasper 70)
of one instrument (a rotated shaft with a clasper at its end, moving and turning) in a
temporary folder, then, alternating, ``--runs`` times each:

- baseline ``imread``: ``cv2.imread(path)`` over every file in one process (OpenCV's
  default flags: decoded to 3-channel BGR);
- baseline ``imread-unchanged``: ``cv2.imread(path, cv2.IMREAD_UNCHANGED)`` (the plain
  8-bit decode, the stricter baseline);
- ``api``: ``mistool.api.run(folder)`` in-process (read, Algorithm 1, identities,
  Algorithm 2; the folder has no [camera], so no metric pose);
- ``cli``: ``mistool.cli.main(["track", folder, "-o", out.csv, "--quiet"])`` in-process
  (the above plus writing the CSV).

It prints the median wall-clock seconds of each (and the median CPU time per frame, all
threads, which is less sensitive to other load on the machine) and the ratios
``baseline / mistool`` (> 1: mistool is faster than only decoding). The machine's load
average is printed too: the wall-clock ratio needs the cores to be free.

With ``--memory`` it also runs ``api.run`` in fresh
subprocesses on N and 4N frames and prints their peak RSS and tracemalloc peak, to show
that memory does not grow with the number of frames (only the output table does, about
a kilobyte per frame).

Usage::

    python scripts/bench_track.py                 # 300 frames, 5 runs
    python scripts/bench_track.py --frames 300 --runs 7 --memory
    python scripts/bench_track.py --png-level 6   # PNGs as libpng's adaptive filters write
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

W, H = 720, 576


def make_frames(folder: Path, n: int, png_level: int | None = None) -> list[Path]:
    """Write ``n`` label PNGs of one moving instrument into ``folder`` (``png_level``:
    an explicit zlib level, which makes libpng choose row filters adaptively)."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        t = i / max(n - 1, 1)
        img = np.zeros((H, W), np.uint8)
        angle = 20.0 + 50.0 * math.sin(2 * math.pi * t)  # deg, long side from +x to +y
        u = np.array([math.cos(math.radians(angle)), math.sin(math.radians(angle))])
        tip = np.array([250.0 + 200.0 * t, 200.0 + 80.0 * math.sin(4 * math.pi * t)])
        shaft_len, clasper_len = 420.0, 70.0
        shaft_c = tip - u * (clasper_len + shaft_len / 2)
        clasper_c = tip - u * (clasper_len / 2)
        for centre, size, value in (
            (shaft_c, (shaft_len, 38.0), 160),
            (clasper_c, (clasper_len, 26.0), 70),
        ):
            box = cv2.boxPoints(((float(centre[0]), float(centre[1])), size, angle))
            cv2.fillPoly(img, [np.round(box).astype(np.int32)], value)
        path = folder / f"{i:06d}.png"
        params = [] if png_level is None else [cv2.IMWRITE_PNG_COMPRESSION, png_level]
        cv2.imwrite(str(path), img, params)
        paths.append(path)
    return paths


def timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(wall seconds, CPU seconds of this process, all threads) of one call."""
    start, cpu = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - start, time.process_time() - cpu


def child_memory(folder: str, workers: int | None) -> None:
    """Run api.run once in this (fresh) process and print its memory as JSON."""
    import resource
    import tracemalloc

    from mistool import api

    tracemalloc.start()
    result = api.run(folder, workers=workers)
    _, peak = tracemalloc.get_traced_memory()
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(
        json.dumps(
            {
                "frames": result.num_frames,
                "rows": result.table.num_rows,
                "peak_rss_mb": rss_kb / 1024,
                "tracemalloc_peak_mb": peak / 2**20,
            }
        )
    )


def _print_results(
    args: argparse.Namespace,
    times: dict[str, list[float]],
    cpu: dict[str, list[float]],
    load0: tuple[float, float, float],
    inflate: str,
) -> None:
    """Medians, spreads and ratios against the imread baselines."""
    med = {k: statistics.median(v) for k, v in times.items()}
    med_cpu = {k: statistics.median(v) for k, v in cpu.items()}
    print(
        f"mistool track benchmark: {args.frames} frames {W}x{H} 8-bit PNG, one "
        f"instrument, {args.runs} runs (median), {os.cpu_count()} CPUs, "
        f"workers={args.workers or 'auto'}, OpenCV {cv2.__version__}, PNG inflate: "
        f"{inflate}, PNG level "
        f"{'default' if args.png_level is None else args.png_level}"
    )
    for name, t in med.items():
        spread = f"{min(times[name]):.3f}-{max(times[name]):.3f}"
        print(
            f"  {name:18s} {t:7.3f} s  ({args.frames / t:7.1f} frames/s, "
            f"runs {spread}; CPU {1e3 * med_cpu[name] / args.frames:.2f} ms/frame)"
        )
    for base in ("imread", "imread-unchanged"):
        for ours in ("api", "cli"):
            print(
                f"  ratio {base} / {ours}: {med[base] / med[ours]:.2f} wall-clock "
                f"(CPU time ratio {med_cpu[base] / med_cpu[ours]:.2f})"
            )
    print(f"  load average before/after: {load0} / {os.getloadavg()}")


def _print_memory(seq: Path, workers: int | None) -> None:
    """Peak memory of tracking ``seq`` in a fresh process."""
    cmd = [sys.executable, __file__, "--child-memory", str(seq)]
    if workers:
        cmd += ["--workers", str(workers)]
    res = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)
    print(
        f"  memory {res['frames']:5d} frames ({res['rows']} rows): peak RSS "
        f"{res['peak_rss_mb']:.1f} MB, tracemalloc peak "
        f"{res['tracemalloc_peak_mb']:.1f} MB"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument(
        "--workers", type=int, default=None, help="mistool worker threads (default: CPU count)"
    )
    parser.add_argument(
        "--png-level",
        type=int,
        default=None,
        metavar="L",
        help="write the PNGs with this zlib level (libpng's adaptive row "
        "filters, as many tools write them) instead of OpenCV's default",
    )
    parser.add_argument(
        "--stdlib-zlib",
        action="store_true",
        help="inflate PNGs with the standard library's zlib, not zlib-ng",
    )
    parser.add_argument(
        "--memory", action="store_true", help="also measure peak memory for N and 4N frames"
    )
    parser.add_argument("--child-memory", metavar="DIR", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child_memory:
        child_memory(args.child_memory, args.workers)
        return 0

    from mistool import api, pngdecode
    from mistool.cli import main as cli_main

    if args.stdlib_zlib:
        import zlib

        pngdecode._ZLIB = zlib

    with tempfile.TemporaryDirectory(prefix="mistool-bench-") as tmp:
        folder = Path(tmp) / "seq"
        paths = make_frames(folder, args.frames, args.png_level)
        out = Path(tmp) / "out.csv"
        names = [str(p) for p in paths]

        def imread() -> None:
            for p in names:
                cv2.imread(p)

        def imread_unchanged() -> None:
            for p in names:
                cv2.imread(p, cv2.IMREAD_UNCHANGED)

        def run_api() -> None:
            result = api.run(folder, workers=args.workers)
            assert result.num_frames == args.frames and result.table.num_rows > 0

        def run_cli() -> None:
            code = cli_main(
                [
                    "track",
                    str(folder),
                    "-o",
                    str(out),
                    "--quiet",
                    *(["--workers", str(args.workers)] if args.workers else []),
                ]
            )
            assert code == 0

        tasks = {
            "imread": imread,
            "imread-unchanged": imread_unchanged,
            "api": run_api,
            "cli": run_cli,
        }
        for fn in tasks.values():  # warm-up: page cache, imports, thread pools
            fn()
        load0 = os.getloadavg()
        times: dict[str, list[float]] = {k: [] for k in tasks}
        cpu: dict[str, list[float]] = {k: [] for k in tasks}
        for _ in range(args.runs):
            for name, fn in tasks.items():
                wall, used = timed(fn)
                times[name].append(wall)
                cpu[name].append(used)
        _print_results(args, times, cpu, load0, pngdecode._ZLIB.__name__)
        if args.memory:
            big = Path(tmp) / "seq4"
            make_frames(big, 4 * args.frames, args.png_level)
            for seq in (folder, big):
                _print_memory(seq, args.workers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
