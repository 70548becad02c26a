#!/usr/bin/env python
"""A/B: CPU time of the per-frame metric pose of another mistool checkout (REF, e.g.
``git worktree add /tmp/pose-before <sha>``) against this one, on the very calls
``mistool track`` makes, with their outputs compared.

For each sequence, ``mistool.api.iter_track(seq, workers=1)`` runs once with this
checkout and every call of ``parallel.measure`` (the worker's pose of an instance, a
split piece's or a deferred frame's) is recorded. Both versions are then imported into
this one process (REF's modules first, then this checkout's; each version runs with its
own modules in ``sys.modules``, so that the imports inside functions, such as the
compiled kernels', find its own) and run over the recorded calls alternately (A B A B
...), ``--runs`` times each; the CPU time (``time.process_time``) per call and per frame
is the median. OpenCV runs on one thread, as in the worker processes.

Every cell of every output must be equal (NaN equal to NaN), else the script says which
and exits with 1. With ``--rtol R`` a float may differ by ``R`` relative (absolute for
values below 1); NaN patterns and ``aux_status`` must still be equal, and the worst
difference is reported (e.g. against a tree from before the compiled kernels, whose
sums and BLAS products round differently in the last bits).

Usage::

    git worktree add /tmp/pose-before main
    python scripts/ab_pose.py /tmp/pose-before SEQ [SEQ ...] [--runs 7] [--rtol 1e-7]
"""

from __future__ import annotations

import argparse
import importlib
import math
import statistics
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
from _checkout import import_checkout

HERE = Path(__file__).resolve().parent.parent


def _load(root: Path) -> tuple[ModuleType, dict[str, ModuleType]]:
    """``mistool.parallel`` of the checkout at ``root`` and its ``mistool`` modules (its
    compiled kernels imported, when it has them)."""
    (module,) = import_checkout(root, "parallel")
    try:
        importlib.import_module("mistool.kernels.pose")
    except ModuleNotFoundError:
        pass
    own = {k: m for k, m in sys.modules.items() if k == "mistool" or k.startswith("mistool.")}
    return module, own


def _activate(own: dict[str, ModuleType]) -> None:
    """Make ``own`` the ``mistool`` modules of ``sys.modules``."""
    for name in [m for m in sys.modules if m == "mistool" or m.startswith("mistool.")]:
        del sys.modules[name]
    sys.modules.update(own)


def _record(parallel: ModuleType, seq: Path) -> tuple[Any, list[tuple[Any, tuple[int, int]]], int]:
    """The config, the recorded ``(instance, shape)`` calls and the frame count."""
    from mistool import api
    from mistool.config import load_config
    from mistool.sequence import list_frames

    calls: list[tuple[Any, tuple[int, int]]] = []
    real = parallel.measure

    def spy(inst: Any, shape: tuple[int, int], config: Any, metric: bool, *out: Any) -> Any:
        if metric and config.camera is not None:
            calls.append((inst, shape))
        return real(inst, shape, config, metric, *out)

    cfg = load_config(seq)
    parallel.measure = spy
    try:
        for _ in api.iter_track(seq, cfg, workers=1):
            pass
    finally:
        parallel.measure = real
    return cfg, calls, len(list_frames(seq))


def _run(parallel: ModuleType, cfg: Any, calls: list[tuple[Any, tuple[int, int]]]) -> list[Any]:
    return [parallel.measure(inst, shape, cfg, True) for inst, shape in calls]


def _by_part(
    parallel: ModuleType, calls: list[tuple[Any, tuple[int, int]]], got: list[Any]
) -> list[Any]:
    """``_run``'s answers as part -> {column: value} (a checkout whose ``measure`` gives
    one array per instance: ``mistool.pose.measure.measure_rows``)."""
    if not hasattr(parallel, "measure_rows"):
        return got
    m = sys.modules[parallel.measure_rows.__module__]
    return [
        {p: dict(zip(m.ROW_KEYS, rows[m.SLOT_OF[p]].tolist(), strict=True)) for p in inst.parts}
        for (inst, _), rows in zip(calls, got, strict=True)
    ]


def _differences(ref: list[Any], got: list[Any], rtol: float) -> tuple[list[str], float]:
    """The cells that differ (beyond ``rtol``, see the module docstring) and the worst
    difference (relative, absolute below 1) of the floats allowed to differ."""
    bad = []
    worst = 0.0
    for k, (a, b) in enumerate(zip(ref, got, strict=True)):
        if a.keys() != b.keys():
            bad.append(f"call {k}: parts {sorted(a)} != {sorted(b)}")
            continue
        for part, row in a.items():
            for col, x in row.items():
                y = b[part].get(col)
                if y is not None and (x == y or (math.isnan(x) and math.isnan(y))):
                    continue
                if y is not None and rtol and col != "aux_status" and not math.isnan(x + y):
                    diff = abs(x - y) / max(abs(x), abs(y), 1.0)
                    worst = max(worst, diff)
                    if diff <= rtol:
                        continue
                bad.append(f"call {k} {part} {col}: {x!r} != {y!r}")
    return bad, worst


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ref", type=Path, help="the other checkout's root (holds mistool/)")
    ap.add_argument("seqs", type=Path, nargs="+", help="sequence folders")
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument(
        "--rtol",
        type=float,
        default=0.0,
        help="allowed relative difference (default 0: bit for bit)",
    )
    args = ap.parse_args()
    cv2.setNumThreads(1)
    loaded = {"ref": _load(args.ref.resolve()), "this": _load(HERE)}
    versions = {k: par for k, (par, _) in loaded.items()}
    status = 0
    for seq in args.seqs:
        _activate(loaded["this"][1])
        cfg, calls, frames = _record(versions["this"], seq)
        outs = {}
        for k, (par, own) in loaded.items():  # warm up
            _activate(own)
            outs[k] = _by_part(par, calls, _run(par, cfg, calls))
        bad, worst = _differences(outs["ref"], outs["this"], args.rtol)
        cpu: dict[str, list[float]] = {k: [] for k in versions}
        for _ in range(args.runs):
            for k, (par, own) in loaded.items():
                _activate(own)
                t0 = time.process_time()
                _run(par, cfg, calls)
                cpu[k].append(time.process_time() - t0)
        med = {k: statistics.median(v) for k, v in cpu.items()}
        print(
            f"{seq.name}: {frames} frames, {len(calls)} calls; pose CPU (median of "
            f"{args.runs}, alternating) ref {1e3 * med['ref'] / len(calls):.3f} -> this "
            f"{1e3 * med['this'] / len(calls):.3f} ms/call, {1e3 * med['ref'] / frames:.3f} -> "
            f"{1e3 * med['this'] / frames:.3f} ms/frame (x{med['ref'] / med['this']:.2f}); "
            + (
                f"{len(bad)} cells differ"
                if bad
                else "outputs identical"
                if not worst
                else f"outputs equal within {args.rtol:g} (worst {worst:.2g}), NaN and status equal"
            )
        )
        for line in bad[:20]:
            print("  " + line)
        status |= bool(bad)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
