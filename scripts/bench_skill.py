"""Time of mistool.skill and of the report on a long recording (default: one hour at
25 fps, two instruments, shaft + clasper rows: 360,000 rows), median of several runs,
against a baseline measured in the same run: the plain path length of every tip with
numpy (the least any metric code has to do).

    python scripts/bench_skill.py --frames 90000 --runs 5
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from mistool.model import TrackTable
from mistool.report import ReportRecording, build_report
from mistool.skill import skill


def long_table(frames: int, fps: float = 25.0) -> TrackTable:
    """Two tools moving smoothly with 0.5 mm noise; shaft and clasper rows each frame."""
    t = np.arange(frames) / fps
    rng = np.random.default_rng(0)
    parts = []
    for k, name in enumerate(("1", "2")):
        x = 20 * np.sin(0.3 * t + k) + rng.normal(0, 0.5, frames)
        y, z = 10 * np.cos(0.2 * t), 80 + 10 * np.sin(0.1 * t)
        for part, off in (("shaft", -15.0), ("clasper", 0.0)):
            parts.append(
                {
                    "frame": np.arange(frames),
                    "time_s": t,
                    "instrument": np.full(frames, name, object),
                    "part": np.full(frames, part, object),
                    "end_x_mm": x + off,
                    "end_y_mm": y,
                    "end_z_mm": z,
                    "axis_x": np.ones(frames),
                    "axis_y": np.zeros(frames),
                    "axis_z": np.zeros(frames),
                }
            )
    return TrackTable({c: np.concatenate([p[c] for p in parts]) for c in parts[0]})


def baseline(table: TrackTable) -> float:
    total = 0.0
    for inst in ("1", "2"):
        sel = (table["instrument"] == inst) & (table["part"] == "clasper")
        p = np.stack([table[c][sel] for c in ("end_x_mm", "end_y_mm", "end_z_mm")], 1)
        total += float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=90000)
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    table = long_table(args.frames)
    times: dict[str, list[float]] = {"baseline": [], "skill": [], "report": []}
    for _ in range(args.runs):
        for name, fn in (
            ("baseline", lambda: baseline(table)),
            ("skill", lambda: skill(table)),
            ("report", lambda: build_report([ReportRecording("long", table)])),
        ):
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    base = statistics.median(times["baseline"])
    print(f"{table.num_rows} rows, {args.frames} frames x 2 instruments, {args.runs} runs")
    for name, ts in times.items():
        med = statistics.median(ts)
        print(f"{name:9s} median {med * 1000:8.1f} ms   {med / base:6.1f}x baseline")


if __name__ == "__main__":
    main()
