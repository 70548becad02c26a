#!/usr/bin/env python
"""Benchmark: ``mistool track`` throughput against decoding alone, 1 and N workers,
metric pose on and off, on one instrument and on two crossing instruments with merged
labels (the realistic EndoVis'17 case); then a small dataset, locally and on a 2-worker
Dask ``LocalCluster``.

In one run, on ``mistool synth`` sequences (720x576, ``--frames`` frames each, rendered
once into ``--data`` and reused):

- ``decode``: ``cv2.imread(path, cv2.IMREAD_UNCHANGED)`` over every file, one process;
- ``track metric wN`` / ``track no-metric wN``: ``mistool track SEQ -o out.csv -q
  --workers N [--no-metric]`` in-process (``mistool.cli.main``: reading, the per-frame
  work in N processes, identities, refinement and writing the CSV), N = 1 and
  ``--workers`` (default: the CPU cores);
- with ``--fresh``: the same metric runs, each in a new interpreter
  (``python -c "from mistool.cli import main; ..."``), as a user's one ``mistool track``
  command: start-up, imports and the worker processes' start included (the in-process
  runs above start the fork server once, in their first run); mistool's bytecode is
  compiled first where missing, as the set-up scripts do;
- per stage, in one process (``--stages``): decode, instances (Algorithm 1 +
  grouping), identity (``IdentityTracker.resolve``, the crossing split included),
  metric pose (of the instances the identity step returns: a blob it splits is never
  measured), rows, refinement (paper motion + metric refinement), CSV writing, in CPU
  ms per frame; the parent's sequential share is identity + rows + refinement + CSV;
- with ``--long N``: each case's sequence played forwards, backwards, forwards ... to N
  frames (copied once into ``--data``) in place of the sequence itself: an hour-long
  procedure's throughput, where the worker pool's start weighs nothing;
- with ``--process-cpu``: every process's CPU per frame (workers from ``/proc``, the
  caller) of ``mistool.track`` on a reused ``LocalPool(N)``, each case;
- with ``--video``: the crossing case as an mp4v mask video (decoded by the workers):
  ``cv2.VideoCapture.read`` decode-only frames/s and every process's CPU per frame;
- with ``--formats``: write/read times and sizes of the last case's table as CSV,
  ``.npz`` and ``.parquet``; with ``--memory N ...``: peak RSS of tracking N frames (the
  last case's frames repeated) in a fresh process;
- a dataset (``--dataset-sequences`` sequences of ``--dataset-frames`` frames, half
  with one instrument and half with two crossing): ``mistool track DATA -o OUT
  --workers N`` and ``--dask ADDRESS`` on ``LocalCluster(n_workers=2, processes=True,
  threads_per_worker=1)`` (cluster start-up not timed).

Every timing is the median of ``--runs`` runs, the configurations alternating; ratios
are frames/s divided by decode-only frames/s measured in the same run (> 1: faster than
one process only decoding). The machine's load average is printed: other programs on the
machine lower every wall-clock figure.

Usage::

    python scripts/bench_throughput.py                    # 2,500 frames, 3 runs
    python scripts/bench_throughput.py --frames 500 --runs 3 --workers 2
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2

CASES = {"one": 1, "cross": 2}  # case name -> instruments (merged labels, crossing)


def synth(folder: Path, frames: int, instruments: int, seed: int) -> Path:
    """A ``mistool synth`` sequence, rendered once (reused when already there)."""
    from mistool.synth import synthesize

    if not (folder / "synth.json").is_file():
        synthesize(folder, frames=frames, instruments=instruments, seed=seed, force=True)
    return folder


def ping_pong(source: Path, frames: int) -> Path:
    """A copy of ``source``'s mask PNGs played forwards, backwards, forwards ... to
    ``frames`` frames (an hour-long procedure stands in; the motion stays continuous at
    every turn), in ``source``'s parent (made once, reused). Each frame is its own file,
    copied, so decoding it reads it as a distinct file does."""
    folder = source.parent / f"{source.name}_pingpong_{frames}"
    done = folder / "complete"
    if done.is_file():
        return folder
    files = sorted(source.glob("*.png"))
    order = files + files[-2:0:-1]
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source / "mistool.toml", folder / "mistool.toml")
    for k in range(frames):
        shutil.copyfile(order[k % len(order)], folder / f"{k:06d}.png")
    done.write_text(f"{frames} frames of {source} played forwards and backwards\n")
    return folder


def timed(fn: Callable[[], object]) -> float:
    """Wall-clock seconds of one call."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def timed_cpu(fn: Callable[[], object]) -> tuple[float, float]:
    """(wall-clock seconds, CPU seconds of this process) of one call: with workers, this
    process's CPU time is the sequential part (identity, rows, refinement, writing)."""
    start, cpu = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - start, time.process_time() - cpu


def decode_all(files: list[str]) -> None:
    for f in files:
        cv2.imread(f, cv2.IMREAD_UNCHANGED)


def track_cli(seq: Path, out: Path, workers: int, metric: bool) -> None:
    from mistool.cli import main

    argv = ["track", str(seq), "-o", str(out), "-q", "--workers", str(workers)]
    if main(argv + ([] if metric else ["--no-metric"])) != 0:
        raise SystemExit(f"mistool track {seq} failed")


def stages(seq: Path, out: Path) -> dict[str, float]:
    """CPU milliseconds per frame of each stage, in this process (metric pose on; CPU
    time, so that other programs on the machine inflate the figures less than they do
    wall-clock times).

    ``identity`` is ``IdentityTracker.resolve`` (the crossing split included);
    ``metric pose`` the pose of the instances it returns (the pieces of a split blob
    included; a blob that is split is never measured: its pose is deferred, see
    ``mistool.parallel.observe_labels``), as ``mistool track`` measures them."""
    from mistool import parallel, tracking
    from mistool.api import refine
    from mistool.export import write_csv
    from mistool.model import TrackTable
    from mistool.rows import RowBuilder
    from mistool.sequence import list_frames, open_sequence, read_label_image

    seqo = open_sequence(seq)
    cfg = seqo.config
    metric = parallel.metric_pose(True, cfg)
    tracker = tracking.IdentityTracker(cfg)
    rows = RowBuilder(cfg.fps)
    keys = ("decode", "instances", "identity", "metric pose", "rows")
    t = dict.fromkeys(keys, 0.0)
    files = list_frames(seq)
    clock = time.process_time
    for i, f in enumerate(files):
        t0 = clock()
        labels = read_label_image(f)
        t1 = clock()
        found = tracking.observe_frame(labels, cfg)
        t2 = clock()
        instances, names = tracker.resolve(i, found)
        t3 = clock()
        shape = (labels.shape[0], labels.shape[1])
        metrics = parallel.measure_all(list(instances), shape, cfg, metric)
        t4 = clock()
        rows.add_frame(i, list(names), list(instances), metrics)
        t5 = clock()
        for key, a, b in zip(keys, (t0, t1, t2, t3, t4), (t1, t2, t3, t4, t5), strict=True):
            t[key] += b - a
    raw = TrackTable.concat([rows.take()])
    t0 = clock()
    table = refine(raw, cfg)
    t["refinement"] = clock() - t0
    t0 = clock()
    write_csv(table, out)
    t["CSV"] = clock() - t0
    return {k: 1e3 * v / len(files) for k, v in t.items()}


def compile_bytecode() -> None:
    """Compile mistool's modules to bytecode where it is missing, as the set-up's warm
    step does (``python -m mistool.kernels``) and as ``pip install`` does for an installed
    package: a new interpreter then reads them compiled even where the environment says
    not to write bytecode (``PYTHONDONTWRITEBYTECODE``, set on the machine these figures
    come from)."""
    import compileall

    import mistool

    compileall.compile_dir(str(Path(mistool.__file__).parent), quiet=2)


def track_fresh(seq: Path, out: Path, workers: int) -> None:
    """``mistool track SEQ -o OUT -q --workers N`` in a new interpreter (metric pose)."""
    import subprocess

    argv = ["track", str(seq), "-o", str(out), "-q", "--workers", str(workers)]
    code = f"from mistool.cli import main; raise SystemExit(main({argv!r}))"
    subprocess.run([sys.executable, "-c", code], check=True)


def bench_case(
    name: str, seq: Path, tmp: Path, workers: list[int], runs: int, fresh: bool = False
) -> dict[str, float]:
    """Median seconds of decode and of each track configuration."""
    from mistool.sequence import list_frames

    files = [str(p) for p in list_frames(seq)]
    configs: dict[str, Callable[[], object]] = {"decode": lambda: decode_all(files)}
    for w in workers:
        for metric in (True, False):
            key = f"track {'metric' if metric else 'no-metric'} w{w}"
            out = tmp / f"{name}_{w}_{metric}.csv"
            configs[key] = lambda w=w, metric=metric, out=out: track_cli(seq, out, w, metric)
        if fresh:
            out = tmp / f"{name}_{w}_fresh.csv"
            configs[f"track metric w{w}, new process"] = lambda w=w, out=out: track_fresh(
                seq, out, w
            )
    times: dict[str, list[float]] = {k: [] for k in configs}
    cpus: dict[str, list[float]] = {k: [] for k in configs}
    for _ in range(runs):
        for key, fn in configs.items():
            wall, cpu = timed_cpu(fn)
            times[key].append(wall)
            cpus[key].append(cpu)
    med = {k: statistics.median(v) for k, v in times.items()}
    med.update({f"cpu {k}": statistics.median(v) for k, v in cpus.items()})
    return med


def print_case(name: str, n: int, med: dict[str, float], load: tuple[float, ...]) -> None:
    dec = n / med["decode"]
    print(f"\n{name}: {n} frames, load average {load[0]:.1f}")
    print(
        f"  {'decode (cv2.imread UNCHANGED, 1 process)':44s} {dec:8.1f} frames/s   "
        f"CPU {1e3 * med['cpu decode'] / n:5.2f} ms/frame"
    )
    for key, secs in med.items():
        if key == "decode" or key.startswith("cpu "):
            continue
        fps = n / secs
        cpu = 1e3 * med["cpu " + key] / n
        print(
            f"  {key:44s} {fps:8.1f} frames/s   ratio to decode {fps / dec:5.2f}   "
            + ("" if "new process" in key else f"CPU of the calling process {cpu:5.2f} ms/frame")
        )
    for w in sorted({int(k.split()[2].strip(",")[1:]) for k in med if k.startswith("track")}):
        on, off = med[f"track metric w{w}"], med[f"track no-metric w{w}"]  # wall-clock
        print(f"  metric / no-metric time, w{w}: {on / off:.2f}")


def _proc_cpu(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def process_cpu(name: str, source: Path, frames: int, workers: int, runs: int) -> None:
    """Every process's CPU per frame of ``mistool.track(source)`` on a warm
    ``LocalPool(workers)`` (reused, as ``mistool track DATASET/`` does): the workers'
    (from ``/proc``) and the caller's; median of ``runs`` runs after one warm-up run, once
    every worker has started (before, the caller works alone: ``LocalPool.warming``)."""
    import warnings

    from mistool import api, parallel

    warnings.simplefilter("ignore")  # e.g. label values smeared by a video codec
    with parallel.LocalPool(workers) as pool:
        while pool.warming():  # until then the caller does the work itself
            time.sleep(0.05)
        api.track(source, pool=pool)
        pids = list(pool._executor._processes)  # type: ignore[union-attr]
        walls, callers, workers_cpu = [], [], []
        for _ in range(runs):
            before = sum(_proc_cpu(p) for p in pids)
            t0, c0 = time.perf_counter(), time.process_time()
            api.track(source, pool=pool)
            walls.append(time.perf_counter() - t0)
            callers.append(time.process_time() - c0)
            workers_cpu.append(sum(_proc_cpu(p) for p in pids) - before)
    wall, caller, work = (statistics.median(v) for v in (walls, callers, workers_cpu))
    print(
        f"  process CPU, {name}, {workers} workers (pool reused), load average "
        f"{os.getloadavg()[0]:.1f}: {frames / wall:.1f} frames/s; CPU ms/frame: workers "
        f"{1e3 * work / frames:.2f}, caller {1e3 * caller / frames:.2f}, total "
        f"{1e3 * (work + caller) / frames:.2f}"
    )


def bench_video(data: Path, frames: int, workers: int, runs: int) -> None:
    """The crossing case as an mp4v mask video: decode-only (``cv2.VideoCapture.read``,
    one process) and every process's CPU with ``workers`` workers."""
    from mistool.synth import synthesize

    folder = data / f"video_{frames}"
    if not (folder / "synth.json").is_file():
        synthesize(folder, frames=frames, instruments=2, seed=3, video="mp4v", force=True)
    video = folder / "masks.avi"

    def decode() -> None:
        cap = cv2.VideoCapture(str(video), cv2.CAP_FFMPEG)
        while cap.read()[0]:
            pass
        cap.release()

    secs = statistics.median(timed(decode) for _ in range(runs))
    print(f"\nmask video (crossing, mp4v): {frames} frames")
    print(f"  {'decode (cv2.VideoCapture.read, 1 process)':44s} {frames / secs:8.1f} frames/s")
    process_cpu("video", video, frames, workers, runs)


def bench_formats(seq: Path, tmp: Path, runs: int) -> None:
    """Write and read times and sizes of the sequence's table as CSV, .npz, .parquet."""
    from mistool.api import track
    from mistool.columnar import read_table, write_table

    table = track(seq, workers=1)
    print(f"\ntable formats: {table.num_rows} rows x {len(table.full().columns)} columns")
    for suffix in (".csv", ".npz", ".parquet"):
        path = tmp / f"table{suffix}"
        w = statistics.median(timed(lambda p=path: write_table(table, p)) for _ in range(runs))
        r = statistics.median(timed(lambda p=path: read_table(p)) for _ in range(runs))
        print(
            f"  {suffix:9s} write {1e3 * w:8.1f} ms   read {1e3 * r:8.1f} ms   "
            f"{path.stat().st_size / 2**20:7.2f} MB"
        )


def child_memory(seq: str, frames: int) -> None:
    """Track ``frames`` frames (the sequence's frames over and over) in this fresh
    process, one worker, metric pose on; print the peak RSS (MB) and rows."""
    import itertools
    import resource

    from mistool import api
    from mistool.sequence import open_sequence

    cfg = open_sequence(seq).config
    decoded = [labels for _, _, labels in open_sequence(seq)]
    result = api.run(itertools.islice(itertools.cycle(decoded), frames), cfg, workers=1)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{rss:.1f} {result.table.num_rows}")


def bench_memory(seq: Path, frames: list[int]) -> None:
    import subprocess

    print(f"\nmemory (fresh process, 1 worker, metric pose, frames of {seq.name} repeated):")
    for n in frames:
        cmd = [sys.executable, __file__, "--child-memory", str(seq), str(n)]
        rss, rows = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.split()
        print(f"  {n:6d} frames ({rows} rows): peak RSS {float(rss):7.1f} MB")


def make_dataset(root: Path, data: Path, sequences: int, frames: int) -> Path:
    """``sequences`` synth sequences (alternately 1 and 2 instruments) in ``root``."""
    root.mkdir(parents=True, exist_ok=True)
    for k in range(sequences):
        inst = 1 + k % 2
        src = synth(data / f"ds_{frames}_{k}", frames, inst, seed=10 + k)
        link = root / f"seq{k}"
        if not link.exists():
            link.symlink_to(src, target_is_directory=True)
    return root


def bench_dataset(args: argparse.Namespace, data: Path, tmp: Path, workers: int) -> None:
    from distributed import LocalCluster

    from mistool.cli import main
    from mistool.sequence import list_frames

    root = make_dataset(tmp / "dataset", data, args.dataset_sequences, args.dataset_frames)
    total = sum(len(list_frames(p)) for p in root.iterdir())
    files = [str(f) for p in sorted(root.iterdir()) for f in list_frames(p)]

    def run(extra: list[str]) -> None:
        out = tmp / "dataset_out"
        shutil.rmtree(out, ignore_errors=True)  # else the re-run skips up-to-date outputs
        if main(["track", str(root), "-o", str(out), "-q", *extra]) != 0:
            raise SystemExit("dataset run failed")

    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        configs: dict[str, Callable[[], object]] = {
            "decode": lambda: decode_all(files),
            f"local, {workers} worker processes": lambda: run(["--workers", str(workers)]),
            "Dask LocalCluster, 2 worker processes": lambda: run(
                ["--dask", cluster.scheduler_address]
            ),
        }
        times: dict[str, list[float]] = {k: [] for k in configs}
        for _ in range(args.runs):
            for key, fn in configs.items():
                times[key].append(timed(fn))
    med = {k: statistics.median(v) for k, v in times.items()}
    dec = total / med["decode"]
    print(
        f"\ndataset: {args.dataset_sequences} sequences x {args.dataset_frames} frames "
        f"({total} frames, metric pose on), load average {os.getloadavg()[0]:.1f}"
    )
    print(f"  {'decode (cv2.imread UNCHANGED, 1 process)':44s} {dec:8.1f} frames/s")
    for key, secs in med.items():
        if key != "decode":
            fps = total / secs
            print(
                f"  {key:44s} {fps:8.1f} frames/s   {secs:6.2f} s   ratio to decode "
                f"{fps / dec:5.2f}"
            )


def main(argv: list[str] | None = None) -> int:
    from mistool.parallel import default_workers

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=2500, help="frames per sequence")
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--workers", type=int, default=default_workers(), help="N (cores)")
    parser.add_argument("--cases", nargs="+", choices=sorted(CASES), default=list(CASES))
    parser.add_argument("--stages", action="store_true", help="also time each stage")
    parser.add_argument(
        "--long",
        type=int,
        metavar="N",
        help="instead, each case's sequence played forwards and backwards to N frames",
    )
    parser.add_argument(
        "--fresh", action="store_true", help="also each metric run in a new interpreter"
    )
    parser.add_argument("--dataset-sequences", type=int, default=4)
    parser.add_argument("--dataset-frames", type=int, default=100)
    parser.add_argument("--no-dataset", action="store_true")
    parser.add_argument("--formats", action="store_true", help="CSV vs .npz vs .parquet")
    parser.add_argument(
        "--process-cpu",
        action="store_true",
        help="every process's CPU per frame with N workers (pool reused), each case",
    )
    parser.add_argument(
        "--video", action="store_true", help="the crossing case as an mp4v mask video"
    )
    parser.add_argument(
        "--memory",
        type=int,
        nargs="+",
        metavar="N",
        help="peak RSS of tracking N frames (the crossing sequence repeated), each N",
    )
    parser.add_argument("--child-memory", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument(
        "--data",
        type=Path,
        default=Path(tempfile.gettempdir()) / "mistool_bench_throughput",
        help="where the synth sequences are rendered once and reused",
    )
    args = parser.parse_args(argv)
    if args.child_memory:
        child_memory(args.child_memory[0], int(args.child_memory[1]))
        return 0
    workers = sorted({1, args.workers})
    print(
        f"mistool track throughput: {os.cpu_count()} CPUs, workers {workers}, "
        f"{args.runs} runs (median), OpenCV {cv2.__version__}, Python "
        f"{sys.version.split()[0]}; load average {os.getloadavg()}"
    )
    with tempfile.TemporaryDirectory(prefix="mistool-bench-") as tmp_s:
        tmp = Path(tmp_s)
        for name in args.cases:
            seq = synth(args.data / f"{name}_{args.frames}", args.frames, CASES[name], seed=3)
            frames = args.frames
            if args.long:
                seq, frames = ping_pong(seq, args.long), args.long
            if args.fresh:
                compile_bytecode()
            med = bench_case(name, seq, tmp, workers, args.runs, args.fresh)
            print_case(
                f"{name} ({CASES[name]} instrument(s), merged labels)",
                frames,
                med,
                os.getloadavg(),
            )
            if args.process_cpu:
                process_cpu(name, seq, frames, args.workers, args.runs)
            if args.stages:
                ms = stages(seq, tmp / "stages.csv")
                parent = sum(ms[k] for k in ("identity", "rows", "refinement", "CSV"))
                print(
                    "  stages, CPU ms/frame (one process): "
                    + ", ".join(f"{k} {v:.2f}" for k, v in ms.items())
                    + f"; sequential in the parent: {parent:.2f} (identity, rows, "
                    "refinement, CSV)"
                )
        name = args.cases[-1]
        last = synth(args.data / f"{name}_{args.frames}", args.frames, CASES[name], seed=3)
        if args.video:
            bench_video(args.data, args.frames, args.workers, args.runs)
        if args.formats:
            bench_formats(last, tmp, args.runs)
        if args.memory:
            bench_memory(last, args.memory)
        if not args.no_dataset:
            bench_dataset(args, args.data, tmp, args.workers)
    print(f"\nload average after: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
