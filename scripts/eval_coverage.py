#!/usr/bin/env python
"""Strict identity coverage against truth per sequence (mistool synth folders).

For each folder, tracks it (``mistool.track``, no metric pose) and scores it with
:func:`mistool.evaluation.identity_coverage` against its ``truth.csv``: instruments are
matched one-to-one (Hungarian on box centres), and a truth row counts only when the name
matched to its tool has a row there nearer to this tool than to any other; so a tool the
tracker renamed midway, or two tools swapped after a crossing, count as misses. Prints
names handed out vs true, and coverage overall and per part, and the same among the
detected rows (a part hidden in the masks is no identity error); then the means. Stricter than
``scripts/eval_identity.py`` (which maps several names to one tool).

Usage::

    mistool synth /tmp/a --frames 100 --instruments 2 --seed 1 --jitter 1 --holes 3 --speckle 10
    python scripts/eval_coverage.py /tmp/a sample_masks
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mistool.api import track
from mistool.evaluation import identity_coverage
from mistool.export import read_csv


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    args = ap.parse_args()
    overall, shaft, det = [], [], []
    for folder in args.folders:
        c = identity_coverage(track(folder, metric=False), read_csv(folder / "truth.csv"))
        overall.append(c.coverage)
        det.append(c.detected)
        shaft.append(c.parts.get("shaft", float("nan")))
        cov = "  ".join(f"{p} {100 * v:5.1f}%" for p, v in c.parts.items())
        print(
            f"{folder.name:20s} names {c.names}/{c.true_names}  all {100 * c.coverage:5.1f}%  "
            f"{cov}  detected rows {100 * c.detected:5.1f}%"
        )
    n = len(overall)
    print(
        f"mean coverage {100 * sum(overall) / n:.1f}% (shaft {100 * sum(shaft) / n:.1f}%, "
        f"detected rows {100 * sum(det) / n:.1f}%) over {n} sequence(s)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
