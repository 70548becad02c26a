"""The worker processes' fork server preloads the kernels the per-frame work calls
(mistool.kernels._worker), and mistool track starts that server early when it will
use worker processes (mistool.forkserver, mistool.cli.track._pool_likely)."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

from mistool import api, forkserver, kernels
from mistool.cli.track import _POOL_MIN_FRAMES, _pool_likely
from mistool.kernels._worker import WORKER_KERNELS
from mistool.synth import Corruptions, synthesize


def _loaded() -> set[str]:
    """``module.kernel`` of every kernel this process has loaded."""
    out = set()
    for info in pkgutil.iter_modules(kernels.__path__):
        if info.name.startswith("_"):
            continue
        module = sys.modules.get(f"mistool.kernels.{info.name}")
        if module is None:
            continue
        for name, value in vars(module).items():
            if getattr(value, "mistool_signatures", None) and not value._can_compile:
                if value.__module__ == f"mistool.kernels.{info.name}":
                    out.add(f"{info.name}.{name}")
    return out


def test_every_listed_worker_kernel_exists() -> None:
    for module, names in WORKER_KERNELS.items():
        mod = importlib.import_module(f"mistool.kernels.{module}")
        for name in names:
            assert getattr(getattr(mod, name, None), "mistool_signatures", None), f"{module}.{name}"


@pytest.mark.parametrize(
    ("instruments", "occluders"), [(1, 0), (2, 0), (4, 2)], ids=["one", "crossing", "crowded"]
)
def test_the_per_frame_work_calls_only_listed_kernels(
    tmp_path: Path, instruments: int, occluders: int
) -> None:
    """In a new process: observe every frame of a synthetic sequence (metric pose on)
    as a worker does; every kernel that got loaded is in WORKER_KERNELS."""
    seq = tmp_path / "seq"
    synthesize(
        seq,
        frames=40,
        instruments=instruments,
        seed=3,
        preset="endovis17",
        corruptions=Corruptions(occluders=occluders),
        force=True,
    )
    code = f"""
import sys
sys.path.insert(0, {str(Path(__file__).parent)!r})
from pathlib import Path
from mistool import parallel
from mistool.sequence import open_sequence
from test_worker_kernels import _loaded
seq = open_sequence(Path({str(seq)!r}))
for _, batch in parallel.batches(seq, True, 8):
    parallel.observe_batch(batch)
print(" ".join(sorted(_loaded())))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    used = set(out.stdout.split())
    listed = {f"{m}.{n}" for m, names in WORKER_KERNELS.items() for n in names}
    assert used, out.stderr
    assert used <= listed, sorted(used - listed)


def _args(workers: int | None = None, dask: str | None = None) -> argparse.Namespace:
    return argparse.Namespace(workers=workers, dask=dask)


def test_pool_likely_follows_the_pool_rule(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert _POOL_MIN_FRAMES == api.POOL_MIN_FRAMES
    few, many = tmp_path / "few", tmp_path / "many"
    for folder, n in ((few, _POOL_MIN_FRAMES - 1), (many, _POOL_MIN_FRAMES)):
        folder.mkdir()
        for i in range(n):
            (folder / f"{i:05d}.png").touch()
    (few / "notes.txt").touch()
    assert _pool_likely(_args(2), few)
    assert not _pool_likely(_args(1), many)
    assert not _pool_likely(_args(dask="tcp://x:8786"), many)
    monkeypatch.setattr(forkserver, "default_workers", lambda: 2)
    assert _pool_likely(_args(), many)
    assert not _pool_likely(_args(), few)
    assert not _pool_likely(_args(), tmp_path / "missing")
    monkeypatch.setattr(forkserver, "default_workers", lambda: 1)
    assert not _pool_likely(_args(), many)


def test_an_early_fork_server_serves_the_pool(tmp_path: Path) -> None:
    """In a new process: the fork server started ahead (with the workers' preload) is
    the one the pool's workers fork from, and the output is the pool-less one."""
    seq = tmp_path / "seq"
    synthesize(seq, frames=30, instruments=2, seed=5, force=True)
    code = f"""
from pathlib import Path
from multiprocessing import forkserver as fs
from mistool import api, forkserver, parallel
import os, signal
forkserver.start()
pid = fs._forkserver._forkserver_pid
assert pid is not None and fs._forkserver._preload_modules == forkserver.PRELOAD
def blocked(p):
    line = [x for x in open("/proc/%d/status" % p) if x.startswith("SigBlk:")][0]
    return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))
assert blocked(pid), "the fork server must start with Ctrl+C blocked"
assert not blocked(os.getpid())
with parallel.LocalPool(2) as pool:
    table = api.track(Path({str(seq)!r}), pool=pool)
    assert fs._forkserver._forkserver_pid == pid
alone = api.track(Path({str(seq)!r}), workers=1)
for c in table.columns:
    a, b = table[c], alone[c]
    assert list(a) == list(b) if a.dtype == object else a.tobytes() == b.tobytes(), c
print("ok", table.num_rows)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("ok ") and int(out.stdout.split()[1]) > 0


def test_the_command_line_reaches_the_early_start_without_numpy() -> None:
    """``mistool track`` starts the fork server after building its parser and entering
    its stderr filter: neither imports numpy (~45 ms) or the modules behind it (OpenCV,
    mistool.background's ~100 ms), so the server's loading starts ~70 ms after the
    process instead of ~150."""
    code = """
import sys
from mistool import cli, forkserver
started = []
heavy = ("numpy", "cv2", "mistool.background")
forkserver.start = lambda: started.append([m for m in heavy if m in sys.modules])
cli.main(["track", sys.argv[1], "--workers", "2", "-o", "/nonexistent-folder/x.csv"])
print(started)
"""
    out = subprocess.run(
        [sys.executable, "-c", code, "/nonexistent-sequence"], capture_output=True, text=True
    )
    assert out.stdout.strip() == "[[]]", (out.stdout, out.stderr)
