#!/usr/bin/env python
"""Strict tracking coverage on sequences with ground truth (mistool synth folders).

For each folder, tracks it (``mistool.track``, no metric pose) and scores it with
``mistool.evaluation`` against its ``truth.csv``: instruments are matched one-to-one
(Hungarian on box centres), so a tool the tracker renamed midway counts its second name's
rows as misses. Prints names handed out vs true, and coverage per part; then the mean
shaft coverage. Stricter than ``scripts/eval_identity.py`` (which maps several names to one
tool).

Usage::

    mistool synth /tmp/a --frames 100 --instruments 2 --seed 1 --jitter 1 --holes 3 --speckle 10
    python scripts/eval_coverage.py /tmp/a sample_masks
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from mistool.api import track
from mistool.evaluation import evaluate
from mistool.export import read_csv


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    args = ap.parse_args()
    shaft = []
    for folder in args.folders:
        table = track(folder, metric=False)
        truth = read_csv(folder / "truth.csv")
        parts = evaluate({"p": table}, truth).methods[0].parts
        names = len(set(table["instrument"].tolist()))
        true = len(set(truth["instrument"].tolist()))
        shaft.append(parts["shaft"]["coverage"] if "shaft" in parts else math.nan)
        cov = "  ".join(f"{p} {100 * s['coverage']:5.1f}%" for p, s in parts.items())
        print(f"{folder.name:16s} names {names}/{true}  {cov}")
    print(f"mean shaft coverage {100 * sum(shaft) / len(shaft):.1f}% over {len(shaft)} sequence(s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
