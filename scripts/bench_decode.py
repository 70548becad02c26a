"""Benchmark: decoding label PNGs, mistool's reader against ``cv2.imread(IMREAD_UNCHANGED)``.

Does mistool's PNG decoder (``mistool.pngdecode.decode_png``, with zlib-ng) pay? For
each set of real mask PNGs it times, per file (CPU time of this process, OpenCV on one
thread as in the worker processes):

- ``imread``: ``cv2.imread(path, cv2.IMREAD_UNCHANGED)``, the baseline;
- ``reader, fast path``: ``read_label_image(path)`` as mistool reads (fast decoder first);
- ``reader, gated``: the same with a ``FastPathGate``, as sequences read a folder (stops
  trying the decoder on a folder whose files it keeps declining);
- ``reader, OpenCV only``: ``read_label_image`` with the fast path closed (what the reader
  costs without the decoder: ``cv2.imdecode`` plus the label checks);
- ``fast decode only``: ``decode_png(bytes)`` on bytes already in memory, with zlib-ng,
  and with the standard library's zlib.

Sets: ``sample_masks/`` (the bundled sequence) and fresh ``mistool synth`` output (PNG
level 3, as ``mistool synth`` writes; 1 and 4 instruments, with every corruption), plus the
same synth frames re-encoded by ``cv2.imwrite`` with its defaults (Sub-filtered rows, which
the fast decoder was written for) and at level 9 (libpng's adaptive filters). Several runs,
median per file, ratios against imread measured in the same run.

    python scripts/bench_decode.py [--runs 7] [--frames 100]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2

from mistool import pngdecode
from mistool.config import MAX_PIXELS
from mistool.pngdecode import decode_png
from mistool.sequence import FastPathGate, read_label_image
from mistool.synth import synthesize
from mistool.synth.corrupt import Corruptions

ROOT = Path(__file__).resolve().parent.parent


def _per_file(fn: Callable[[], object], n_files: int, runs: int) -> list[float]:
    """CPU milliseconds per file of each run."""
    out = []
    for _ in range(runs):
        t0 = time.process_time()
        fn()
        out.append(1e3 * (time.process_time() - t0) / n_files)
    return out


def _tasks(paths: list[Path], blobs: list[bytes]) -> dict[str, Callable[[], object]]:
    """The decoders to time, each over every file of a set."""
    strs = [str(p) for p in paths]
    closed = FastPathGate(patience=0)  # never open: the reader's OpenCV-only path

    def reader_gated() -> None:
        gate = FastPathGate()  # as a sequence reads its folder
        for p in paths:
            read_label_image(p, gate=gate)

    def fast_stdlib() -> None:
        saved, pngdecode._ZLIB = pngdecode._ZLIB, zlib
        try:
            [decode_png(b, MAX_PIXELS) for b in blobs]
        finally:
            pngdecode._ZLIB = saved

    return {
        "imread (baseline)": lambda: [cv2.imread(s, cv2.IMREAD_UNCHANGED) for s in strs],
        "reader, fast path": lambda: [read_label_image(p) for p in paths],
        "reader, gated": reader_gated,
        "reader, OpenCV only": lambda: [read_label_image(p, gate=closed) for p in paths],
        "fast decode only": lambda: [decode_png(b, MAX_PIXELS) for b in blobs],
        "fast, stdlib zlib": fast_stdlib,
    }


def bench_set(name: str, paths: list[Path], runs: int) -> None:
    """Time the decoders on ``paths`` and print medians and ratios."""
    blobs = [p.read_bytes() for p in paths]
    tasks = _tasks(paths, blobs)
    for fn in tasks.values():  # warm-up: page cache, imports
        fn()
    times: dict[str, list[float]] = {k: [] for k in tasks}
    for _ in range(runs):  # interleaved, so a busy moment hits every method alike
        for k, fn in tasks.items():
            times[k] += _per_file(fn, len(paths), 1)
    med = {k: statistics.median(v) for k, v in times.items()}
    took = [i for i, b in enumerate(blobs) if decode_png(b, MAX_PIXELS) is not None]
    size = sum(len(b) for b in blobs) / len(blobs)
    print(
        f"{name}: {len(paths)} files, {size / 1024:.1f} KiB mean, "
        f"fast decoder accepts {len(took)}/{len(paths)}"
    )
    base = med["imread (baseline)"]
    for k, v in med.items():
        spread = f"{min(times[k]):.3f}-{max(times[k]):.3f}"
        print(f"  {k:22s} {v:7.3f} ms/file (runs {spread})  imread / this = {base / v:5.2f}")
    if took:  # where the decoder does apply: its best case
        sub = _tasks([paths[i] for i in took], [blobs[i] for i in took])
        t_cv = statistics.median(_per_file(sub["imread (baseline)"], len(took), runs))
        t_fast = statistics.median(_per_file(sub["fast decode only"], len(took), runs))
        print(
            f"  on the {len(took)} files it accepts: imread {t_cv:.3f} ms, fast decode "
            f"{t_fast:.3f} ms per file (imread / fast = {t_cv / t_fast:.2f})"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--frames", type=int, default=100, help="frames per synth set")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)  # as in the worker processes
    print(f"runs {args.runs} (median), OpenCV {cv2.__version__}, load {os.getloadavg()}")
    bench_set("sample_masks", sorted((ROOT / "sample_masks").glob("*.png")), args.runs)
    every = Corruptions(jitter_px=1.0, holes=2.0, speckle=2.0, occluders=1, bias_px=0.5)
    with tempfile.TemporaryDirectory(prefix="mistool-bench-decode-") as tmp:
        for label, kw in (
            ("synth, 1 instrument", {"instruments": 1, "seed": 1}),
            (
                "synth, 4 instruments, corrupted",
                {"instruments": 4, "seed": 2, "corruptions": every},
            ),
        ):
            folder = Path(tmp) / label.replace(" ", "_").replace(",", "")
            synthesize(folder, frames=args.frames, **kw)  # type: ignore[arg-type]
            paths = sorted(folder.glob("*.png"))
            bench_set(label, paths, args.runs)
            for suffix, params in (
                ("re-encoded by OpenCV's defaults", []),
                ("re-encoded level 9", [cv2.IMWRITE_PNG_COMPRESSION, 9]),
            ):
                again = folder.with_name(folder.name + "_" + str(len(params)))
                again.mkdir()
                for p in paths:
                    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                    cv2.imwrite(str(again / p.name), img, params)
                bench_set(f"{label}, {suffix}", sorted(again.glob("*.png")), args.runs)
    print(f"load after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
