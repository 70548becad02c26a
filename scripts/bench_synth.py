#!/usr/bin/env python3
"""Benchmark of the synthetic renderer (issue 3: >= 25 frames/s, one instrument, 720x576).

Measures, each as the median of several runs over the same seeded motion:

- ``render``: ray casting + label lookup of one frame (what ``synthesize`` does per frame
  before corrupting and writing);
- ``synth``: the whole ``synthesize`` call per frame (render, truth boxes, PNG writing,
  truth.csv), no corruptions;
- baseline, in the same run: ``cv2.imwrite`` of the same label frames alone (the cost of
  merely writing the PNGs), to put the numbers in proportion.

Usage: python scripts/bench_synth.py [--frames 100] [--runs 5] [--instruments 1]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from mistool.synth import ImageCamera, InstrumentGeometry, RayCaster, synthesize
from mistool.synth.motion import MotionOptions, generate_motion
from mistool.synth.scene import instrument_parts


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--instruments", type=int, default=1)
    args = ap.parse_args()

    cam = ImageCamera.default()
    geom = InstrumentGeometry()
    poses = generate_motion(
        cam,
        [geom] * args.instruments,
        args.frames,
        25.0,
        seed=0,
        options=MotionOptions(enter=False),
    )
    caster = RayCaster(cam)
    lut = np.array([0, 160, 70, 70], dtype=np.uint8)
    frames = []
    render_fps = []
    for _ in range(args.runs):
        frames = []
        t0 = time.perf_counter()
        for f in range(args.frames):
            buf = caster.render([instrument_parts(p[f], geom) for p in poses])
            frames.append(lut[buf.part])
        render_fps.append(args.frames / (time.perf_counter() - t0))
    write_fps = []
    synth_fps = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.runs):
            t0 = time.perf_counter()
            for f, img in enumerate(frames):
                cv2.imwrite(str(Path(tmp) / f"w{f:06d}.png"), img, [cv2.IMWRITE_PNG_COMPRESSION, 3])
            write_fps.append(args.frames / (time.perf_counter() - t0))
            t0 = time.perf_counter()
            synthesize(
                Path(tmp) / f"s{r}", frames=args.frames, instruments=args.instruments, seed=0
            )
            synth_fps.append(args.frames / (time.perf_counter() - t0))
    visible = np.mean([np.count_nonzero(f) for f in frames]) / frames[0].size
    med = statistics.median
    print(
        f"720x576, {args.instruments} instrument(s), {args.frames} frames x {args.runs} "
        f"runs (median); tool pixels {100 * visible:.1f}% of the image"
    )
    print(
        f"  render only        {med(render_fps):8.1f} frames/s   "
        f"(target >= 25: ratio {med(render_fps) / 25.0:.1f})"
    )
    print(f"  synthesize (all)   {med(synth_fps):8.1f} frames/s")
    print(
        f"  baseline: imwrite  {med(write_fps):8.1f} frames/s   "
        f"(render / imwrite = {med(render_fps) / med(write_fps):.2f})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
