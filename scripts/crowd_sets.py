#!/usr/bin/env python
"""The 108 crowded-scene sequences of issue 10 item 5, rendered and scored in one place.

Every pass of docs/tracking.md ("Crowded scenes") judged its changes on the visible rows of
the strict identity coverage (``scripts/eval_coverage.py``) over the same sets of
``mistool synth`` sequences, all with merged EndoVis'17 labels, 150 frames unless said:

- ``crowd/4-e17-occ2-sN``, N = 0-35: four tools, two occluders (0-5 the first set, 6-23
  and 24-35 the held-out ones);
- ``fresh/4-e17-occ2-sN``, N = 36-59: the same, fresh seeds;
- ``two/2-e17-occ2-sN``, N = 0-3: two tools, two occluders;
- ``leave/{4,2}-e17-occ2-leave-sN``: tools leaving the view (four: N = 0-7, two: 0-3);
- ``cross2500``: two tools crossing, 2,500 frames, seed 0, no occluders;
- ``twox/2-e17-sN``, N = 1-3: two tools crossing, 600 frames;
- ``dev/...``: made for development: four tools seeds 60-79, leaving the view seeds 8-11,
  two tools crossing 600 frames seeds 4-6;
- ``reg/2-e17-cross-s0``: the regression case (two tools, 100 frames, seed 0).

``render ROOT`` writes the ones missing (``mistool synth`` commands, two at a time; the
same command, the same files). ``score ROOT`` tracks each one (``mistool.track``, no metric
pose, as ``scripts/eval_coverage.py``), prints the share of its visible truth rows that
keep their tool's one name, the mean and how many reach 95% (the issue's target); with
``--save FILE`` it keeps the figures, with ``--base FILE`` it prints the sequences that
moved against a saved run. Score another checkout with ``PYTHONPATH=TREE``::

    python scripts/crowd_sets.py render /tmp/crowdsets
    python scripts/crowd_sets.py score /tmp/crowdsets --save /tmp/base.txt
    PYTHONPATH=/path/to/other python scripts/crowd_sets.py score /tmp/crowdsets \\
        --base /tmp/base.txt
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

OCC2 = ["--preset", "endovis17", "--occluders", "2"]


def sequences() -> dict[str, list[str]]:
    """Relative folder -> ``mistool synth`` options (OUT excluded)."""
    seqs: dict[str, list[str]] = {}

    def four(folder: str, seed: int, *extra: str) -> None:
        seqs[folder] = ["--frames", "150", "--instruments", "4", *OCC2, *extra]
        seqs[folder] += ["--seed", str(seed)]

    for s in range(36):
        four(f"crowd/4-e17-occ2-s{s}", s)
    for s in range(36, 60):
        four(f"fresh/4-e17-occ2-s{s}", s)
    for s in range(4):
        seqs[f"two/2-e17-occ2-s{s}"] = ["--frames", "150", "--instruments", "2", *OCC2]
        seqs[f"two/2-e17-occ2-s{s}"] += ["--seed", str(s)]
    for s in range(8):
        four(f"leave/4-e17-occ2-leave-s{s}", s, "--leave-view")
    for s in range(4):
        seqs[f"leave/2-e17-occ2-leave-s{s}"] = [
            *["--frames", "150", "--instruments", "2", *OCC2, "--leave-view"],
            *["--seed", str(s)],
        ]
    seqs["cross2500"] = ["--frames", "2500", "--instruments", "2", "--preset", "endovis17"]
    seqs["cross2500"] += ["--seed", "0"]
    for s in (1, 2, 3):
        seqs[f"twox/2-e17-s{s}"] = ["--frames", "600", "--instruments", "2"]
        seqs[f"twox/2-e17-s{s}"] += ["--preset", "endovis17", "--seed", str(s)]
    for s in range(60, 80):
        four(f"dev/4-e17-occ2-s{s}", s)
    for s in range(8, 12):
        four(f"dev/4-e17-occ2-leave-s{s}", s, "--leave-view")
    for s in (4, 5, 6):
        seqs[f"dev/2-e17-s{s}"] = ["--frames", "600", "--instruments", "2"]
        seqs[f"dev/2-e17-s{s}"] += ["--preset", "endovis17", "--seed", str(s)]
    seqs["reg/2-e17-cross-s0"] = ["--frames", "100", "--instruments", "2"]
    seqs["reg/2-e17-cross-s0"] += ["--preset", "endovis17", "--seed", "0"]
    return seqs


def _render(job: tuple[Path, list[str]]) -> str:
    out, options = job
    cmd = [sys.executable, "-c", "from mistool.cli import main; raise SystemExit(main())"]
    subprocess.run([*cmd, "synth", str(out), *options, "-q"], check=True)
    return out.name


def render(root: Path, jobs: int) -> None:
    todo = [(root / k, v) for k, v in sequences().items()]
    todo = [job for job in todo if not (job[0] / "synth.json").is_file()]
    print(f"{len(sequences()) - len(todo)} there, {len(todo)} to render into {root}")
    for job in todo:
        job[0].parent.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(jobs) as pool:
        for k, name in enumerate(pool.map(_render, todo), 1):
            print(f"{k}/{len(todo)} {name}", flush=True)


def _score(folder: Path) -> float:
    from mistool.api import track
    from mistool.evaluation import identity_coverage, with_mask_areas
    from mistool.export import read_csv

    truth = with_mask_areas(read_csv(folder / "truth.csv"), read_csv(folder / "mask_areas.csv"))
    return 100 * identity_coverage(track(folder, metric=False, workers=1), truth).visible


def _read(path: Path) -> dict[str, float]:
    out = {}
    for line in path.read_text().splitlines():
        name, value = line.split()
        out[name] = float(value)
    return out


def score(root: Path, jobs: int, save: Path | None, base: Path | None) -> None:
    names = list(sequences())
    missing = [n for n in names if not (root / n / "synth.json").is_file()]
    if missing:
        raise SystemExit(f"{root}: {len(missing)} sequences missing (run render first)")
    with ProcessPoolExecutor(jobs) as pool:
        values = dict(zip(names, pool.map(_score, [root / n for n in names]), strict=True))
    before = _read(base) if base else {}
    for name, v in values.items():
        moved = f"  ({before[name]:6.2f} -> {v - before[name]:+.2f})" if name in before else ""
        if not before or abs(v - before.get(name, v)) > 1e-9:
            print(f"{name:32s} {v:6.2f}{moved}")
    n = len(values)
    mean = sum(values.values()) / n
    hit = sum(v >= 95.0 for v in values.values())
    line = f"visible rows: mean {mean:.2f}%, {hit}/{n} sequences >= 95%"
    if before:
        bmean = sum(before.values()) / len(before)
        bhit = sum(v >= 95.0 for v in before.values())
        up = sum(values[k] > before[k] + 1e-9 for k in values if k in before)
        down = sum(values[k] < before[k] - 1e-9 for k in values if k in before)
        line += f" (base {bmean:.2f}%, {bhit}; {up} up, {down} down)"
    print(line)
    if save:
        save.write_text("".join(f"{k} {v!r}\n" for k, v in values.items()))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("command", choices=("render", "score"))
    ap.add_argument("root", type=Path)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--save", type=Path, help="score: keep the figures in this file")
    ap.add_argument("--base", type=Path, help="score: compare with a saved run")
    args = ap.parse_args()
    if args.command == "render":
        render(args.root, args.jobs)
    else:
        score(args.root, args.jobs, args.save, args.base)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
