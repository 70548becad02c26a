#!/usr/bin/env python3
"""Regenerate ``sample_masks/``: the bundled sequence ``mistool serve`` shows by default.

Two robotic instruments (8 mm shafts) enter one after the other, pivot about their trocars,
grasp (jaws opening and closing) and cross each other; 250 frames (10 s at 25 fps),
720x576, EndoVis'15 label values (shaft 160, clasper 70) shared by both tools as in the
real dataset, the camera in ``mistool.toml``, and mild corruptions like a good
segmentation network's output (1 px boundary jitter, a specular hole and a couple of
specks per frame). ``truth.csv`` holds the exact ground truth.

Deterministic: the same command writes byte-identical files.

Usage: python scripts/make_sample.py [--out sample_masks] [--check]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mistool.synth import Corruptions, synthesize

ROOT = Path(__file__).resolve().parent.parent
SEED = 0
FRAMES = 250
MAX_BYTES = 5_000_000


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, default=ROOT / "sample_masks")
    args = ap.parse_args()
    res = synthesize(
        args.out,
        frames=FRAMES,
        instruments=2,
        seed=SEED,
        preset="endovis15",
        fps=25.0,
        corruptions=Corruptions(jitter_px=1.0, holes=1.0, speckle=2.0),
        force=True,
        png_compression=9,
    )
    size = sum(p.stat().st_size for p in res.path.iterdir())
    t = res.truth
    print(f"{res.path}: {FRAMES} frames, {size / 1e6:.2f} MB")
    for name in sorted(set(t["instrument"])):
        rows = t["instrument"] == name
        frames = t["frame"][rows]
        jaw = t["jaw_open_deg"][rows]
        print(
            f"  instrument {name}: visible frames {frames.min()}..{frames.max()} "
            f"({len(set(frames.tolist()))}), jaw opening {jaw.min():.0f}..{jaw.max():.0f} "
            "deg"
        )
    # crossing: instrument 1 comes from the right, 2 from the left; they have crossed
    # when 1's tip is left of 2's tip
    tips = t[t["part"] == "clasper"]
    x = {
        n: dict(
            zip(
                tips["frame"][tips["instrument"] == n].tolist(),
                tips["cx_px"][tips["instrument"] == n].tolist(),
                strict=True,
            )
        )
        for n in ("1", "2")
    }
    common = sorted(set(x["1"]) & set(x["2"]))
    crossed = sum(x["1"][f] < x["2"][f] for f in common)
    print(f"  both tips visible in {len(common)} frames; crossed in {crossed}")
    if size > MAX_BYTES:
        print(f"error: {size} bytes > {MAX_BYTES}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
