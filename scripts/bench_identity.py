#!/usr/bin/env python
"""The sequential identity step alone: CPU time of ``IdentityTracker.resolve`` over a
sequence's observed frames, and a digest of what it returns (A/B, bit for bit).

Each sequence's frames are decoded and observed once (``observe_frame`` and the border
runs, as a worker does: ``parallel.observe_labels`` without the pose); then a fresh
``IdentityTracker(config).resolve`` runs over them ``--runs`` times (CPU time,
``time.process_time``; best and median). With ``--ref DIR`` (another checkout's root, e.g.
a commit exported with ``git archive``) both versions run alternately (A B A B ...), each
in its own child process (two copies of one compiled kernel module cannot share a
process: numba's symbols collide), on the same observations (made here, pickled to
both), and their outputs are compared: every frame's names and returned instances
(centroid, area, bounds, every part's box, corners, area, offset and mask bits).
``--pieces`` times the step's pieces (the assignment, the split's fit and pixel
assignment, ...) in one more run. ``--cprofile N`` prints the N costliest functions
under ``resolve`` (this checkout, one more run, in this process). The decode-only
baseline (``cv2.imread(path, cv2.IMREAD_UNCHANGED)``) is timed in the same run. Usage::

    git archive main | tar -x -C /tmp/ref
    python scripts/bench_identity.py /tmp/cross2500 [SEQ ...] [--ref /tmp/ref] [--runs 3]

Exit status 1 when ``--ref`` gives a different output.
"""

from __future__ import annotations

import argparse
import cProfile
import hashlib
import io
import os
import pickle
import pstats
import statistics
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent.parent


class _Child:
    """A checkout's ``resolve`` in a child process (``--serve``): frames sent once, runs
    on request."""

    def __init__(self, root: Path, cv_threads: int | None) -> None:
        env = dict(os.environ, PYTHONPATH=str(root))
        cmd = [sys.executable, str(Path(__file__).resolve()), "--serve", str(root)]
        if cv_threads is not None:
            cmd += ["--cv-threads", str(cv_threads)]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)

    def ask(self, *msg: Any) -> Any:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        pickle.dump(msg, self.proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
        self.proc.stdin.flush()
        got = pickle.load(self.proc.stdout)
        if isinstance(got, BaseException):
            raise got
        return got

    def close(self) -> None:
        self.ask("quit")
        self.proc.wait()


def _serve(root: Path) -> int:
    """``--serve ROOT``: the child's loop over the parent's requests (pickled on stdin,
    answers pickled on stdout): ``("frames", cfg, frames)``, ``("run",)`` -> ``(CPU
    seconds, digests)``, ``("quit",)``."""
    import mistool.tracking as tracking
    from mistool.kernels import warm

    warm()  # every kernel loaded before timing

    assert Path(str(tracking.__file__)).is_relative_to(root), tracking.__file__
    out = sys.stdout.buffer
    sys.stdout = sys.stderr  # (nothing else on the answers' pipe)
    cfg: Any = None
    frames: list[Any] = []
    while True:
        msg = pickle.load(sys.stdin.buffer)
        try:
            if msg[0] == "quit":
                pickle.dump(None, out)
                out.flush()
                return 0
            if msg[0] == "frames":
                _, cfg, frames = msg
                got: Any = None
            else:
                got = _run(tracking, cfg, frames)
        except Exception as e:  # (the parent raises it)
            got = e
        pickle.dump(got, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


def _observe(seq: Path) -> tuple[Any, list[tuple[list[Any], Any]], float]:
    """(config, per frame (instances, border runs), decode-only CPU seconds)."""
    from mistool import parallel
    from mistool.sequence import list_frames, open_sequence, read_label_image
    from mistool.tracking.instances import foreground_bounds

    cfg = open_sequence(seq).config
    paths = list_frames(seq)
    t0 = time.process_time()
    for p in paths:
        cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    decode = time.process_time() - t0
    frames = []
    for p in paths:
        labels = read_label_image(p)
        insts = parallel.tracking.observe_frame(labels, cfg, bounds=foreground_bounds(labels))
        runs = (
            [parallel.border_runs(i) for i in insts]
            if any(i.label is None for i in insts)
            else None
        )
        frames.append((insts, runs))
    return cfg, frames, decode


def _digest_instance(h: Any, inst: Any) -> None:
    h.update(repr((inst.label, inst.centroid_px, inst.area_px, inst.bbox_xywh)).encode())
    for name, p in inst.parts.items():
        b = p.box
        h.update(repr((name, b.cx, b.cy, b.length, b.width, b.angle_deg)).encode())
        h.update(repr((p.area_px, p.offset, p.mask.shape)).encode())
        h.update(np.ascontiguousarray(p.corners, dtype=np.float64).tobytes())
        h.update(np.packbits(p.mask).tobytes())


def _run(tracking: ModuleType, cfg: Any, frames: list[Any]) -> tuple[float, list[str]]:
    """(CPU seconds of resolve over every frame, per-frame digests)."""
    tracker = tracking.IdentityTracker(cfg)
    outs = []
    t0 = time.process_time()
    for k, (insts, runs) in enumerate(frames):
        outs.append(tracker.resolve(k, insts, runs))
    spent = time.process_time() - t0
    digests = []
    for out, names in outs:
        h = hashlib.blake2b(digest_size=12)
        h.update(repr(names).encode())
        for inst in out:
            _digest_instance(h, inst)
        digests.append(h.hexdigest())
    return spent, digests


#: ``--pieces``: (module, function) timed inside ``resolve`` (inclusive CPU time).
PIECES = (
    ("identity", "IdentityTracker._match"),
    ("identity", "gated_assignment"),
    ("identity", "track_cost"),
    ("identity", "IdentityTracker._split_crossings"),
    ("identity", "IdentityTracker._expected_boxes"),
    ("identity", "fit_split"),
    ("split", "BlobPixels.shaft_sample"),
    ("split", "_initial_axes"),
    ("split", "_refit"),
    ("split", "_score"),
    ("identity", "split_with_heads"),
    ("split", "_shaft_pieces"),
    ("split", "_head_labels"),
    ("split", "_measure_runs"),
    ("split", "_instance"),
    ("identity", "IdentityTracker._split_entries"),
    ("identity", "IdentityTracker._update_all"),
    ("identity", "IdentityTracker._update"),
    ("identity", "border_runs"),
    ("identity", "reference_boxes"),
    ("identity", "hand_over_heads"),
    ("heads", "_shows"),
    ("heads", "_pixels"),
    ("heads", "_with_part"),
)


def _pieces(tracking: ModuleType, cfg: Any, frames: list[Any]) -> None:
    """One more run with CPU timers around :data:`PIECES`; prints each one's calls and
    time (per call and per frame)."""
    mods = {"identity": sys.modules[tracking.__name__ + ".identity"]}
    for name in ("split", "heads"):
        mods[name] = sys.modules.get(f"{tracking.__name__}.{name}")
    pieces = [
        (m, name)
        for m, name in PIECES
        if mods[m] is not None and hasattr(mods[m], name.split(".")[0])
    ]
    spent = {name: [0, 0.0] for _, name in pieces}
    saved = []
    for mod_name, name in pieces:
        owner: Any = mods[mod_name]
        attr = name
        if "." in name:
            cls, attr = name.split(".")
            owner = getattr(owner, cls)
        fn = getattr(owner, attr)
        saved.append((owner, attr, fn))

        def timed(*a: Any, _fn: Any = fn, _name: str = name, **k: Any) -> Any:
            t0 = time.process_time()
            try:
                return _fn(*a, **k)
            finally:
                spent[_name][0] += 1
                spent[_name][1] += time.process_time() - t0

        setattr(owner, attr, timed)
    try:
        total, _ = _run(tracking, cfg, frames)
    finally:
        for owner, attr, fn in reversed(saved):
            setattr(owner, attr, fn)
    n = len(frames)
    print(f"  pieces (inclusive CPU, timers on; resolve {1e3 * total / n:.3f} ms/frame):")
    for name, (calls, t) in spent.items():
        per = f"{1e6 * t / calls:9.1f} us/call" if calls else " " * 17
        print(f"    {name:<34} {calls:6d} calls {per} {1e3 * t / n:7.3f} ms/frame")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("seqs", type=Path, nargs="*", help="sequence folders (label images)")
    ap.add_argument("--ref", type=Path, help="another checkout's root (holds mistool/)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--cprofile", type=int, default=0, metavar="N")
    ap.add_argument("--sort", default="tottime", help="cProfile order (e.g. cumulative)")
    ap.add_argument("--pieces", action="store_true", help="time the identity step's pieces")
    ap.add_argument(
        "--cv-threads",
        type=int,
        default=None,
        help="OpenCV threads (default: OpenCV's own, as in the caller of mistool track)",
    )
    ap.add_argument("--serve", type=Path, help=argparse.SUPPRESS)  # (a child process)
    args = ap.parse_args()
    if args.cv_threads is not None:
        cv2.setNumThreads(args.cv_threads)
    if args.serve is not None:
        return _serve(args.serve)
    sys.path.insert(0, str(HERE))  # this checkout: the observations, --pieces, --cprofile
    import mistool.tracking as this
    from mistool.kernels import warm

    warm()  # every kernel loaded before timing

    assert Path(str(this.__file__)).is_relative_to(HERE), this.__file__
    children = {}
    if args.ref is not None:
        children = {
            "ref": _Child(args.ref.resolve(), args.cv_threads),
            "this": _Child(HERE, args.cv_threads),
        }
    differ = False
    for seq in args.seqs:
        cfg, frames, decode = _observe(seq)
        n = len(frames)
        times: dict[str, list[float]] = {k: [] for k in children or ["this"]}
        digests: dict[str, list[str]] = {}
        for child in children.values():
            child.ask("frames", cfg, frames)
        for _ in range(args.runs):  # alternate: A B A B ...
            for k in times:
                got = children[k].ask("run") if children else _run(this, cfg, frames)
                spent, digests[k] = got
                times[k].append(spent)
        line = [f"{seq}: {n} frames; decode-only (cv2.imread) {1e3 * decode / n:.3f} ms/frame"]
        for k, ts in times.items():
            med, best = statistics.median(ts), min(ts)
            line.append(
                f"  {k}: identity {1e3 * med / n:.3f} ms/frame median, {1e3 * best / n:.3f}"
                f" best of {len(ts)} ({med / decode:.2f}x decode-only)"
            )
        if "ref" in digests:
            bad = [i for i, (a, b) in enumerate(zip(*digests.values(), strict=True)) if a != b]
            differ = differ or bool(bad)
            line.append(
                "  outputs: identical"
                if not bad
                else f"  outputs: {len(bad)} frames differ (first: {bad[:10]})"
            )
        print("\n".join(line), flush=True)
        if args.pieces:
            _pieces(this, cfg, frames)
        if args.cprofile:
            prof = cProfile.Profile()
            prof.runcall(_run, this, cfg, frames)
            s = io.StringIO()
            pstats.Stats(prof, stream=s).sort_stats(args.sort).print_stats(args.cprofile)
            print(s.getvalue())
    for child in children.values():
        child.close()
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
