"""Benchmark: Algorithm 2 over a 1270-frame sequence, and Algorithm 1 + instance
separation (``observe_frame``) per 720x576 frame against decoding the same PNG.

Usage::

    python scripts/bench_paper.py [--runs 15]

Prints medians over ``--runs`` runs. Baselines are measured in the same run:
the paper reports about 20 ms for 1270 frames of Algorithm 2 (target here: <= 2 ms), and
``cv2.imread`` of the frame's PNG is the per-frame baseline for ``observe_frame``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from mistool.config import config_from_dict
from mistool.model import RotatedBox, TrackTable
from mistool.paper import paper_motion
from mistool.tracking import observe_frame

FRAMES = 1270
H, W = 576, 720


def _median_time(fn, runs: int, inner: int = 1) -> tuple[float, float]:
    """Median wall-clock and CPU (process, all threads) seconds per call."""
    wall, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(inner):
            fn()
        wall.append((time.perf_counter() - t0) / inner)
        cpu.append((time.process_time() - c0) / inner)
    return statistics.median(wall), statistics.median(cpu)


def motion_table(frames: int = FRAMES) -> TrackTable:
    """One instrument, shaft and clasper, moving smoothly: boxPoints corners per frame."""
    rows: dict[str, list] = {"frame": [], "instrument": [], "part": []}
    for i in range(1, 5):
        rows[f"x{i}_px"] = []
        rows[f"y{i}_px"] = []
    for k in range(frames):
        s = k / frames
        for part, box in (
            (
                "shaft",
                RotatedBox(250 + 100 * s, 300 - 50 * s, 260 + 20 * s, 30, (25 + 40 * s) % 180),
            ),
            ("clasper", RotatedBox(400 + 100 * s, 350 - 50 * s, 45, 20, (35 + 40 * s) % 180)),
        ):
            c = cv2.boxPoints(((box.cx, box.cy), (box.length, box.width), box.angle_deg))
            rows["frame"].append(k)
            rows["instrument"].append("1")
            rows["part"].append(part)
            for i in range(4):
                rows[f"x{i + 1}_px"].append(float(c[i, 0]))
                rows[f"y{i + 1}_px"].append(float(c[i, 1]))
    return TrackTable(rows)


def one_instrument_frame() -> np.ndarray:
    """A 720x576 EndoVis'15-style label image: shaft 160 from the border, clasper 70."""
    img = np.zeros((H, W), np.uint8)
    t = math.radians(30.0)
    d = np.array([math.cos(t), math.sin(t)])
    joint = np.array([430.0, 330.0])
    shaft = RotatedBox(*(joint - 250 * d), 500.0, 40.0, 30.0)
    clasper = RotatedBox(*(joint + 30 * d), 60.0, 30.0, 30.0)
    cv2.fillPoly(img, [np.round(shaft.corners()).astype(np.int32)], 160)
    cv2.fillPoly(img, [np.round(clasper.corners()).astype(np.int32)], 70)
    return img


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=15, help="timed runs (median reported)")
    args = parser.parse_args()

    table = motion_table()
    paper_motion(table)  # warm-up
    t_alg2, c_alg2 = _median_time(lambda: paper_motion(table, 580.0), args.runs)
    print(
        f"Algorithm 2 (paper_motion), {FRAMES} frames x 2 parts = {table.num_rows} rows: "
        f"median {t_alg2 * 1e3:.2f} ms wall, {c_alg2 * 1e3:.2f} ms CPU over {args.runs} "
        f"runs (paper: ~20 ms; target <= 2 ms)"
    )

    img = one_instrument_frame()
    cfg = config_from_dict({"labels": "endovis15"})
    insts = observe_frame(img, cfg)
    assert len(insts) == 1 and set(insts[0].parts) == {"shaft", "clasper"}
    with tempfile.TemporaryDirectory() as tmp:
        png = str(Path(tmp) / "000000.png")
        cv2.imwrite(png, img)
        t_read, c_read = _median_time(lambda: cv2.imread(png, cv2.IMREAD_UNCHANGED), args.runs, 50)
    print(
        f"cv2.imread (IMREAD_UNCHANGED) of the frame's PNG: {t_read * 1e3:.3f} ms wall / "
        f"{c_read * 1e3:.3f} ms CPU"
    )
    default_threads = cv2.getNumThreads()
    for threads in (default_threads, 1):
        cv2.setNumThreads(threads)
        t_obs, c_obs = _median_time(lambda: observe_frame(img, cfg), args.runs, 50)
        print(
            f"observe_frame, 720x576, one instrument (shaft + clasper), OpenCV threads "
            f"{threads}: median {t_obs * 1e3:.3f} ms wall / {c_obs * 1e3:.3f} ms CPU per "
            f"frame; ratio imread/observe = {t_read / t_obs:.2f} wall, "
            f"{c_read / c_obs:.2f} CPU"
        )
    cv2.setNumThreads(default_threads)
    print(f"load average: {', '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
