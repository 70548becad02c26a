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
moved against a saved run and each set's mean before and after (the sets the team's
rules name: a change must not lower any). Score another checkout with ``PYTHONPATH=TREE``::

    python scripts/crowd_sets.py render /tmp/crowdsets
    python scripts/crowd_sets.py score /tmp/crowdsets --save /tmp/base.txt
    PYTHONPATH=/path/to/other python scripts/crowd_sets.py score /tmp/crowdsets \\
        --base /tmp/base.txt

For trying identity rules, ``cache ROOT --obs DIR`` keeps every sequence's per-frame
observations (the instances and border runs ``mistool.track`` hands the identity step,
no metric pose) in DIR once, and ``replay ROOT --obs DIR`` runs only the identity step and
the sequence-level refinement on them (about ten times faster than ``score``; the same
figures, as long as the per-frame code that made the cache is unchanged: the cache keeps
a digest of that code and ``replay`` refuses a cache of other code). DIR holds pickles
this script wrote: give it a folder of your own.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import pickle
import subprocess
import sys
import time
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


#: The modules whose code makes a frame's observations (``cache``): a cache made by other
#: code is refused by ``replay``.
OBSERVATION_CODE = (
    "mistool/parallel.py",
    "mistool/sequence.py",
    "mistool/pngdecode.py",
    "mistool/config.py",
    "mistool/model.py",
    "mistool/tracking/instances.py",
    "mistool/tracking/split.py",
    "mistool/kernels/png.py",
    "mistool/kernels/boxes.py",
    "mistool/kernels/instances.py",
    "mistool/kernels/split.py",
)


def _code_digest() -> str:
    import mistool

    top = Path(mistool.__file__).resolve().parent.parent
    digest = hashlib.sha256()
    for rel in OBSERVATION_CODE:
        digest.update(rel.encode() + b"\0" + (top / rel).read_bytes())
    return digest.hexdigest()


def _cache_file(obs: Path, name: str) -> Path:
    return obs / (name.replace("/", "__") + ".pkl")


def _cache(job: tuple[Path, Path, str]) -> str:
    root, obs, name = job
    from mistool.parallel import observe_labels
    from mistool.sequence import list_frames, open_sequence, read_label_image

    folder = root / name
    cfg = open_sequence(folder).config
    frames = []
    for path in list_frames(folder):
        r = observe_labels(read_label_image(path), cfg, False)
        frames.append((r.instances, r.runs))
    dst = _cache_file(obs, name)
    tmp = dst.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump((_code_digest(), cfg, frames), f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, dst)
    return name


def cache(root: Path, obs: Path, jobs: int) -> None:
    _check_rendered(root)
    obs.mkdir(parents=True, exist_ok=True)
    digest = _code_digest()
    todo = []
    for name in sequences():
        path = _cache_file(obs, name)
        if path.is_file():
            with open(path, "rb") as f:
                if pickle.load(f)[0] == digest:
                    continue
        todo.append(name)
    print(f"{len(sequences()) - len(todo)} cached, {len(todo)} to observe into {obs}")
    with ProcessPoolExecutor(jobs) as pool:
        for k, name in enumerate(pool.map(_cache, [(root, obs, n) for n in todo]), 1):
            print(f"{k}/{len(todo)} {name}", flush=True)


def _replay(job: tuple[Path, Path, str]) -> tuple[float, float]:
    """(visible %, identity step's CPU s) of one sequence from its cached observations:
    what ``_score`` gives, without the per-frame work."""
    root, obs, name = job
    from mistool import tracking
    from mistool.api import refine
    from mistool.evaluation import identity_coverage, with_mask_areas
    from mistool.export import read_csv
    from mistool.rows import RowBuilder

    with open(_cache_file(obs, name), "rb") as f:
        digest, cfg, frames = pickle.load(f)
    if digest != _code_digest():
        raise SystemExit(f"{obs}: {name} was observed by other code: run cache again")
    tracker = tracking.IdentityTracker(cfg)
    rows = RowBuilder(cfg.fps)
    start = time.process_time()
    for index, (instances, runs) in enumerate(frames):
        got, names = tracker.resolve(index, instances, runs)
        rows.add_frame(index, list(names), list(got), None)
    cpu = time.process_time() - start
    folder = root / name
    truth = with_mask_areas(read_csv(folder / "truth.csv"), read_csv(folder / "mask_areas.csv"))
    return 100 * identity_coverage(refine(rows.take(), cfg), truth).visible, cpu


def replay(root: Path, obs: Path, jobs: int, save: Path | None, base: Path | None) -> None:
    _check_rendered(root)
    names = list(sequences())
    missing = [n for n in names if not _cache_file(obs, n).is_file()]
    if missing:
        raise SystemExit(f"{obs}: {len(missing)} sequences not cached (run cache first)")
    with ProcessPoolExecutor(jobs) as pool:
        got = list(pool.map(_replay, [(root, obs, n) for n in names]))
    print(f"identity step: {sum(cpu for _, cpu in got):.1f} s of CPU in all")
    report(dict(zip(names, (v for v, _ in got), strict=True)), save, base)


def _check_rendered(root: Path) -> None:
    missing = [n for n in sequences() if not (root / n / "synth.json").is_file()]
    if missing:
        raise SystemExit(f"{root}: {len(missing)} sequences missing (run render first)")


def _set_of(name: str) -> str:
    """The set a sequence counts in for the team's rules (no set's mean may fall)."""
    folder, _, seq = name.partition("/")
    if folder in ("leave", "dev"):
        return f"{folder} ({'two' if seq.startswith('2-') else 'four'} tools)"
    return {"cross2500": "twox", "reg": "two"}.get(folder, folder)


def score(root: Path, jobs: int, save: Path | None, base: Path | None) -> None:
    _check_rendered(root)
    names = list(sequences())
    with ProcessPoolExecutor(jobs) as pool:
        values = dict(zip(names, pool.map(_score, [root / n for n in names]), strict=True))
    report(values, save, base)


def report(values: dict[str, float], save: Path | None, base: Path | None) -> None:
    """Print the figures (with ``base``: the sequences that moved and each set's mean)."""
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
        sets: dict[str, list[str]] = {}
        for name in values:
            if name in before:
                sets.setdefault(_set_of(name), []).append(name)
        for label, keys in sets.items():
            a = sum(before[k] for k in keys) / len(keys)
            b = sum(values[k] for k in keys) / len(keys)
            print(f"  set {label:20s} {a:7.3f} -> {b:7.3f} ({b - a:+.3f})")
    print(line)
    if save:
        save.write_text("".join(f"{k} {v!r}\n" for k, v in values.items()))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("command", choices=("render", "score", "cache", "replay"))
    ap.add_argument("root", type=Path)
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--save", type=Path, help="score, replay: keep the figures in this file")
    ap.add_argument("--base", type=Path, help="score, replay: compare with a saved run")
    ap.add_argument("--obs", type=Path, help="cache, replay: the observations' folder")
    args = ap.parse_args()
    if args.command in ("cache", "replay") and args.obs is None:
        ap.error(f"{args.command} needs --obs DIR")
    if args.command == "render":
        render(args.root, args.jobs)
    elif args.command == "score":
        score(args.root, args.jobs, args.save, args.base)
    elif args.command == "cache":
        cache(args.root, args.obs, args.jobs)
    else:
        replay(args.root, args.obs, args.jobs, args.save, args.base)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
