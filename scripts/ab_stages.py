#!/usr/bin/env python
"""A/B: CPU time of the per-frame stages of another mistool checkout (REF, e.g. an
earlier commit exported with ``git archive``) against this one, on the same frames.

Both versions are imported into this one process (REF's modules first, then this
checkout's) and timed alternately, best of ``--runs``, on frames decoded once:

- ``instances``: ``mistool.tracking.observe_frame`` (Algorithm 1 + instance grouping);
- ``pose``: the per-frame metric pose of those instances (``parallel.measure``).

OpenCV runs on one thread, as in the worker processes. Usage::

    git archive 0feefde | tar -x -C /tmp/ref
    python scripts/ab_stages.py /tmp/ref SEQ [SEQ ...] [--runs 5]
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
from _checkout import import_checkout

HERE = Path(__file__).resolve().parent.parent


def _load(root: Path) -> tuple[ModuleType, ModuleType]:
    """``(mistool.tracking, mistool.parallel)`` of the checkout at ``root``."""
    tracking, parallel = import_checkout(root, "tracking", "parallel")
    return tracking, parallel


def _cpu_ms(fn: Any, frames: int, runs: int) -> float:
    best = float("inf")
    for _ in range(runs):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return 1e3 * best / frames


def _instances(tracking: Any, labels: list[Any], cfg: Any) -> None:
    for x in labels:
        tracking.observe_frame(x, cfg)


def _pose(parallel: Any, found: list[Any], shape: tuple[int, int], cfg: Any) -> None:
    for insts in found:
        for inst in insts:
            parallel.measure(inst, shape, cfg, True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ref", type=Path, help="the other checkout's root (holds mistool/)")
    ap.add_argument("seqs", type=Path, nargs="+", help="sequence folders")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    versions = {"ref": _load(args.ref.resolve()), "this": _load(HERE)}
    from mistool.config import load_config
    from mistool.sequence import list_frames, read_label_image

    for seq in args.seqs:
        cfg = load_config(seq / "mistool.toml")
        labels = [read_label_image(f) for f in list_frames(seq)]
        shape = (int(labels[0].shape[0]), int(labels[0].shape[1]))
        found = {k: [t.observe_frame(x, cfg) for x in labels] for k, (t, _) in versions.items()}
        ms: dict[str, dict[str, float]] = {k: {} for k in versions}
        for _ in range(2):  # alternate: A B A B
            for k, (tr, par) in versions.items():
                fns = {
                    "instances": functools.partial(_instances, tr, labels, cfg),
                    "pose": functools.partial(_pose, par, found[k], shape, cfg),
                }
                for stage, fn in fns.items():
                    t = _cpu_ms(fn, len(labels), args.runs)
                    ms[k][stage] = min(ms[k].get(stage, t), t)
        print(
            f"{seq.name}: {len(labels)} frames, CPU ms/frame (best of {2 * args.runs}): "
            + "; ".join(
                f"{stage} {ms['ref'][stage]:.3f} -> {ms['this'][stage]:.3f}"
                for stage in ("instances", "pose")
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
