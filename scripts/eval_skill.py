"""Skill metrics from the tracked table versus the same metrics from the exact truth.

For each seed: ``mistool synth`` (two tools, 1 px boundary jitter, specular holes) ->
``mistool track`` (metric pose, offline smoothing) -> ``mistool.skill`` on the tracked
table and on ``truth.csv``; instruments are matched as ``mistool eval`` matches them.
Prints one line per seed x instrument x metric (truth, tracked, difference), then per
metric the median and the worst difference over all of them. Relative differences for
the extensive metrics (path, depth, speed, volume), absolute for the others.

    python scripts/eval_skill.py --frames 750 --seeds 0 1 2
    python scripts/eval_skill.py --frames 750 --seeds 0 1 2 --shared-labels
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

from mistool.cli import main as cli
from mistool.evaluation import match_instruments
from mistool.export import read_csv
from mistool.skill import skill

RELATIVE = ("path_length_mm", "depth_perception_mm", "mean_speed_mm_s", "working_volume_cm3")
ABSOLUTE = ("idle_fraction", "ldlj", "economy_of_volume", "bimanual_dexterity", "movements")
OTHER = ("visible_s", "out_of_view_s")


def one_seed(tmp: Path, seed: int, args: argparse.Namespace) -> list[tuple[str, str, float, float]]:
    seq = tmp / f"s{seed}"
    synth = ["synth", str(seq), "--frames", str(args.frames), "--fps", str(args.fps)]
    synth += ["--instruments", "2", "--jitter", str(args.jitter), "--holes", "1"]
    synth += ["--seed", str(seed), "-q"] + ([] if args.shared_labels else ["--distinct-labels"])
    if cli(synth) != 0:
        sys.exit(f"synth failed for seed {seed}")
    pred_csv = tmp / f"p{seed}.csv"
    if cli(["track", str(seq), "-o", str(pred_csv), "-q"]) != 0:
        sys.exit(f"track failed for seed {seed}")
    truth, pred = read_csv(seq / "truth.csv"), read_csv(pred_csv)
    rt = skill(truth, num_frames=args.frames)
    rp = skill(pred, num_frames=args.frames)
    mapping = match_instruments(pred, truth)
    out = []
    for j, name in enumerate(rp["instrument"]):
        tname = mapping.get(str(name))
        if tname is None:
            continue
        i = int(np.flatnonzero(rt["instrument"] == tname)[0])
        for m in RELATIVE + ABSOLUTE + OTHER:
            out.append((f"seed {seed} tool {tname} (pred {name})", m, rt[m][i], rp[m][j]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=750)
    ap.add_argument("--fps", type=float, default=25.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--jitter", type=float, default=1.0)
    ap.add_argument(
        "--shared-labels",
        action="store_true",
        help="all tools share the label values (identity from tracking, as EndoVis'17)",
    )
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for seed in args.seeds:
            rows += one_seed(Path(d), seed, args)
    diffs: dict[str, list[float]] = {}
    print(f"{'recording':32s} {'metric':22s} {'truth':>10s} {'tracked':>10s} {'diff':>9s}")
    for who, m, t, p in rows:
        if m in RELATIVE:
            d = (p - t) / t if t else math.nan
            text = f"{100 * d:+8.1f}%"
        else:
            d = p - t
            text = f"{d:+9.3f}"
        diffs.setdefault(m, []).append(d)
        print(f"{who:32s} {m:22s} {t:10.3f} {p:10.3f} {text}")
    print()
    print(f"{'metric':22s} {'median |diff|':>14s} {'max |diff|':>11s}  (n)")
    for m, ds in diffs.items():
        a = np.abs(np.asarray(ds, dtype=np.float64))
        a = a[np.isfinite(a)]
        if not len(a):
            print(f"{m:22s} {'-':>14s} {'-':>11s}  (0)")
            continue
        unit = "%" if m in RELATIVE else ""
        k = 100 if m in RELATIVE else 1
        print(f"{m:22s} {k * np.median(a):13.3f}{unit:1s} {k * a.max():10.3f}{unit:1s}  ({len(a)})")


if __name__ == "__main__":
    main()
