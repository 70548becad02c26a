#!/usr/bin/env python
"""Strict identity coverage against truth per sequence (mistool synth folders).

For each folder, tracks it (``mistool.track``, no metric pose) and scores it with
:func:`mistool.evaluation.identity_coverage` against its ``truth.csv``: instruments are
matched one-to-one (Hungarian on box centres), and a truth row counts only when the name
matched to its tool has a row there nearer to this tool than to any other; so a tool the
tracker renamed midway, or two tools swapped after a crossing, count as misses. Prints
names handed out vs true, and coverage overall and per part, and the same among the
detected rows (a part hidden in the masks is no identity error), and among the truth rows
visible in the masks (>= 20 px in the folder's ``mask_areas.csv``, written by ``mistool
synth``; "nan" without it) with the share of such rows, the
sequence's ceiling; then the means. Stricter than
``scripts/eval_identity.py`` (which maps several names to one tool).

Usage::

    mistool synth /tmp/a --frames 100 --instruments 2 --seed 1 --jitter 1 --holes 3 --speckle 10
    python scripts/eval_coverage.py /tmp/a sample_masks
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mistool.api import track
from mistool.evaluation import identity_coverage, with_mask_areas
from mistool.export import read_csv


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    args = ap.parse_args()
    overall, shaft, det, vis = [], [], [], []
    for folder in args.folders:
        truth = read_csv(folder / "truth.csv")
        if (folder / "mask_areas.csv").is_file():
            truth = with_mask_areas(truth, read_csv(folder / "mask_areas.csv"))
        c = identity_coverage(track(folder, metric=False), truth)
        overall.append(c.coverage)
        det.append(c.detected)
        vis.append(c.visible)
        shaft.append(c.parts.get("shaft", float("nan")))
        cov = "  ".join(f"{p} {100 * v:5.1f}%" for p, v in c.parts.items())
        print(
            f"{folder.name:20s} names {c.names}/{c.true_names}  all {100 * c.coverage:5.1f}%  "
            f"{cov}  visible rows {100 * c.visible:5.1f}% (ceiling {100 * c.ceiling:5.1f}%)  "
            f"detected rows {100 * c.detected:5.1f}%"
        )
    n = len(overall)
    print(
        f"mean coverage {100 * sum(overall) / n:.1f}% (shaft {100 * sum(shaft) / n:.1f}%, "
        f"visible rows {100 * sum(vis) / n:.1f}%, detected rows {100 * sum(det) / n:.1f}%) "
        f"over {n} sequence(s)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
