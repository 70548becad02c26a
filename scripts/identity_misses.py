#!/usr/bin/env python
"""Where a sequence's identity coverage is lost: the missed visible truth rows, by cause.

For each ``mistool synth`` folder (with ``mask_areas.csv``), tracks it frame by frame
with :class:`mistool.tracking.IdentityTracker` (the same instances and splits as
``mistool track``), scores it with :func:`mistool.evaluation.identity_hits`, and prints
for the truth rows visible in the masks that were missed:

- per truth instrument and part, the frame runs missed (e.g. ``3 wrist: 60-75, 130-149``);
- per cause, the count: what the tracker did with the name matched to that instrument
  in that frame: ``blob K: split`` / ``blob K: not split`` (it was one of K tracks in a
  blob holding several, which the crossing handler split or not; a split whose pieces
  are wrong counts here), ``tracked`` (seen apart: its instance lacks that part, or
  holds another tool's, e.g. a head grouped with another tool's shaft), or the
  track's state.

Usage::

    python scripts/identity_misses.py /tmp/crowd/4-e17-occ2-s3
"""

from __future__ import annotations

import argparse
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mistool.api import track
from mistool.config import load_config
from mistool.evaluation import identity_hits, match_instruments, with_mask_areas
from mistool.export import read_csv
from mistool.tracking import IdentityTracker, observe_frame

#: Truth rows with fewer pixels in the masks are not visible (the evaluation's default).
MIN_AREA_PX = 20


class _Tracer(IdentityTracker):
    """An IdentityTracker that records, per frame and name, what happened to it."""

    def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
        super().__init__(*args, **kwargs)
        self.what: dict[int, dict[str, str]] = defaultdict(dict)

    def _split_crossings(self, fr: Any) -> None:  # (a private step, traced)
        super()._split_crossings(fr)
        for b, hidden in fr.blob_of.items():
            group = [fr.live[fr.owner[b]]] + [fr.live[a] for a in hidden]
            done = "split" if b in fr.pieces else "not split"
            for t in group:
                self.what[fr.index][t.name] = f"blob {len(group)}: {done}"


def _runs(frames: list[int]) -> str:
    """``[1, 2, 3, 7]`` -> ``"1-3, 7"``."""
    out: list[str] = []
    for f in sorted(frames):
        if out and int(out[-1].split("-")[-1]) == f - 1:
            out[-1] = f"{out[-1].split('-')[0]}-{f}"
        else:
            out.append(str(f))
    return ", ".join(out)


def misses(folder: Path) -> Counter[str]:
    """Print one sequence's missed visible rows; return the counts by cause."""
    cfg = load_config(folder / "mistool.toml")
    tracer = _Tracer(cfg)
    for f, path in enumerate(sorted(folder.glob("[0-9]*.png"))):
        labels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        tracer.resolve(f, observe_frame(labels, cfg))
        for t in tracer.tracks:
            if t.last_frame == f:
                tracer.what[f].setdefault(t.name, t.state.value)
    pred = track(folder, metric=False)
    truth = with_mask_areas(read_csv(folder / "truth.csv"), read_csv(folder / "mask_areas.csv"))
    scored, hit, _ = identity_hits(pred, truth, MIN_AREA_PX)
    name_of = {t: p for p, t in match_instruments(pred, scored, join_fragments=False).items()}
    visible = np.asarray(scored["mask_area_px"]) >= MIN_AREA_PX
    lost = np.flatnonzero(visible & ~hit)
    by_part: dict[tuple[str, str], list[int]] = defaultdict(list)
    causes: Counter[str] = Counter()
    for k in lost:
        f, tool, part = (
            int(scored["frame"][k]),
            str(scored["instrument"][k]),
            str(scored["part"][k]),
        )
        by_part[(tool, part)].append(f)
        name = name_of.get(tool)
        causes["no name matched" if name is None else tracer.what[f].get(name, "unseen")] += 1
    print(f"{folder.name}: {int(visible.sum())} visible truth rows, {len(lost)} missed")
    for (tool, part), frames in sorted(by_part.items()):
        print(f"  {tool} ({name_of.get(tool, '-')}) {part}: {len(frames)}: {_runs(frames)}")
    print("  by cause: " + ", ".join(f"{c} {n}" for c, n in causes.most_common()))
    return causes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    args = ap.parse_args()
    total: Counter[str] = Counter()
    for folder in args.folders:
        total.update(misses(folder))
    if len(args.folders) > 1:
        print("all: " + ", ".join(f"{c} {n}" for c, n in total.most_common()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
