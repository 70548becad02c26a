#!/usr/bin/env python
"""A/B: CPU time of the per-frame stages of another mistool checkout (REF, e.g. an
earlier commit: ``git worktree add --detach /tmp/ref COMMIT``) against this one, on the
same frames.

Each version runs in its own process (``--child``), the two taking turns, ``--rounds``
times each; a child decodes the frames once, then times, best of ``--runs``:

- ``frame``: the worker's per-frame work before the pose: the label image's bounds (and
  runs, where the checkout has ``instances.scan_labels``), ``observe_frame`` (Algorithm 1 +
  instances) and the unknown label values;
- ``pose``: the per-frame metric pose of those instances (``parallel.measure``).

(Two checkouts imported into one process share ``sys.modules``: a module imported inside
a function, as the compiled kernels are, comes from whichever checkout was imported
last. Hence one process per version.) OpenCV runs on one thread, as in the worker
processes. Usage::

    python scripts/ab_stages.py /tmp/ref SEQ [SEQ ...] [--runs 3] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent.parent


def _cpu_ms(fn: Any, frames: int, runs: int) -> float:
    best = float("inf")
    for _ in range(runs):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return 1e3 * best / frames


def _child(seq: Path, runs: int) -> dict[str, float]:
    """The stages' CPU ms per frame with the mistool on ``sys.path`` (this process)."""
    import cv2

    from mistool import parallel, tracking
    from mistool.config import load_config
    from mistool.sequence import list_frames, read_label_image
    from mistool.tracking import instances

    cv2.setNumThreads(1)
    cfg = load_config(seq / "mistool.toml")
    labels = [read_label_image(f) for f in list_frames(seq)]
    scan = getattr(instances, "scan_labels", None)

    def frame() -> list[Any]:
        out = []
        for x in labels:
            if scan is not None:
                runs_ = scan(x)
                out.append(tracking.observe_frame(x, cfg, runs=runs_))
                parallel.unknown_values(x, cfg, False, runs=runs_)
            else:
                bounds = instances.foreground_bounds(x)
                out.append(tracking.observe_frame(x, cfg, bounds=bounds))
                parallel.unknown_values(x, cfg, False, bounds)
        return out

    found = frame()
    shape = (int(labels[0].shape[0]), int(labels[0].shape[1]))

    def pose() -> None:
        for insts in found:
            for inst in insts:
                parallel.measure(inst, shape, cfg, True)

    return {"frame": _cpu_ms(frame, len(labels), runs), "pose": _cpu_ms(pose, len(labels), runs)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("ref", type=Path, help="the other checkout's root (holds mistool/)")
    ap.add_argument("seqs", type=Path, nargs="+", help="sequence folders")
    ap.add_argument("--runs", type=int, default=3, help="timed runs per child (best kept)")
    ap.add_argument("--rounds", type=int, default=3, help="children per version, alternating")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(_child(args.seqs[0], args.runs)))
        return 0
    roots = {"ref": args.ref.resolve(), "this": HERE}
    for seq in args.seqs:
        ms: dict[str, dict[str, list[float]]] = {k: {"frame": [], "pose": []} for k in roots}
        for _ in range(args.rounds):
            for k, root in roots.items():
                env = {**os.environ, "PYTHONPATH": str(root)}
                cmd = [sys.executable, __file__, str(root), str(seq), "--child"]
                cmd += ["--runs", str(args.runs)]
                out = subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
                for stage, t in json.loads(out.stdout.splitlines()[-1]).items():
                    ms[k][stage].append(t)
        print(
            f"{seq.name}: CPU ms/frame, median of {args.rounds} processes (best of "
            f"{args.runs} runs each): "
            + "; ".join(
                f"{stage} {statistics.median(ms['ref'][stage]):.3f} -> "
                f"{statistics.median(ms['this'][stage]):.3f}"
                for stage in ("frame", "pose")
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
