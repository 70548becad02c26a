"""Identity and instance quality on sequences with ground truth (mistool synth folders).

For each folder (label PNGs + mistool.toml + truth.csv), runs ``observe_frame`` and an
``IdentityTracker`` with ``assign`` (one name per connected instance) and ``resolve``
(blobs of touching instruments split), and prints per method:

- ``names``: names handed out vs true instruments (extra names = identity churn);
- ``purity``: share of named part rows whose name maps to its majority true instrument
  (each row attributed to the true instrument whose box of that part is nearest, within
  40 px);
- ``coverage``: share of truth part rows found under the name mapped to that instrument;
- ``shaft err``: median distance of shaft box centres to the true ones (px).

Usage::

    mistool synth /tmp/s3 --frames 200 --instruments 3 --seed 3 --leave-view --occluders 2
    python scripts/eval_identity.py sample_masks /tmp/s3
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from mistool.config import load_config
from mistool.export import read_csv
from mistool.tracking import IdentityTracker, observe_frame


def evaluate(folder: Path, method: str) -> dict[str, float]:
    cfg = load_config(folder)
    truth = read_csv(folder / "truth.csv")
    boxes: dict[tuple[int, str], list[tuple[str, float, float]]] = {}
    for f, i, p, x, y in zip(
        truth["frame"],
        truth["instrument"],
        truth["part"],
        truth["cx_px"],
        truth["cy_px"],
        strict=True,
    ):
        boxes.setdefault((int(f), str(p)), []).append((str(i), float(x), float(y)))
    tracker = IdentityTracker(cfg)
    rows: list[tuple[int, str, str, str | None, float]] = []
    names: set[str] = set()
    for k, path in enumerate(sorted(folder.glob("*.png"))):
        insts = observe_frame(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), cfg)
        if method == "resolve":
            insts, got = tracker.resolve(k, insts)
        else:
            got = tracker.assign(k, insts)
        for inst, name in zip(insts, got, strict=True):
            names.add(name)
            for part, obs in inst.parts.items():
                cands = [
                    (math.hypot(obs.box.cx - x, obs.box.cy - y), i)
                    for i, x, y in boxes.get((k, part), [])
                ]
                d, who = min(cands) if cands else (math.inf, None)
                rows.append((k, name, part, who if d < 40 else None, d))
    votes: dict[str, dict[str, int]] = {}
    for _, name, _, who, _ in rows:
        if who is not None:
            votes.setdefault(name, {}).setdefault(who, 0)
            votes[name][who] += 1
    mapping = {n: max(v, key=v.get) for n, v in votes.items()}
    attributed = [r for r in rows if r[3] is not None]
    pure = sum(mapping[r[1]] == r[3] for r in attributed)
    found = {(k, mapping.get(n), p) for k, n, p, _, _ in rows}
    want = {
        (int(f), str(i), str(p))
        for f, i, p in zip(truth["frame"], truth["instrument"], truth["part"], strict=True)
    }
    shaft = [d for _, _, p, who, d in rows if p == "shaft" and who is not None]
    return {
        "names": len(names),
        "true": len(set(truth["instrument"])),
        "purity": pure / max(len(attributed), 1),
        "coverage": len(found & want) / max(len(want), 1),
        "shaft_err": float(np.median(shaft)) if shaft else math.nan,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path)
    args = parser.parse_args()
    print(
        f"{'sequence':<28} {'method':<8} {'names':>9} {'purity':>7} {'coverage':>9} "
        f"{'shaft err':>10}"
    )
    totals: dict[str, list[dict[str, float]]] = {"assign": [], "resolve": []}
    for folder in args.folders:
        for method in ("assign", "resolve"):
            r = evaluate(folder, method)
            totals[method].append(r)
            print(
                f"{str(folder)[-28:]:<28} {method:<8} {r['names']:>4} / {r['true']:<2} "
                f"{r['purity']:>7.1%} {r['coverage']:>9.1%} {r['shaft_err']:>8.2f} px"
            )
    if len(args.folders) > 1:  # names summed, the rest averaged over the sequences
        for method, rs in totals.items():
            n, t = sum(r["names"] for r in rs), sum(r["true"] for r in rs)
            pur = float(np.mean([r["purity"] for r in rs]))
            cov = float(np.mean([r["coverage"] for r in rs]))
            print(f"{'all (mean)':<28} {method:<8} {n:>4} / {t:<2} {pur:>7.1%} {cov:>9.1%}")


if __name__ == "__main__":
    main()
