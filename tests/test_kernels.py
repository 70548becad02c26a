"""mistool.kernels: every kernel is loaded for its declared signatures at its first call
(or by ``warm``/``load``), then closed."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import mistool.kernels
from mistool.kernels import kernel, warm


def _kernels() -> list[tuple[str, object]]:
    from numba.core.registry import CPUDispatcher

    found = []
    for info in pkgutil.iter_modules(mistool.kernels.__path__):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"mistool.kernels.{info.name}")
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher):
                found.append((f"{info.name}.{name}", value))
    return found


_CLOSED = """
import importlib, pkgutil
import mistool.kernels
from numba.core.registry import CPUDispatcher
from mistool.kernels import warm
warm()
found = []
for info in pkgutil.iter_modules(mistool.kernels.__path__):
    if not info.name.startswith("_"):
        module = importlib.import_module(f"mistool.kernels.{info.name}")
        found += [(f"{info.name}.{n}", v) for n, v in vars(module).items()
                  if isinstance(v, CPUDispatcher)]
helpers = [name for name, d in found if getattr(d, "mistool_helper", False)]
assert found and helpers
for name, dispatcher in found:
    if name in helpers:
        assert not dispatcher.signatures, name  # linked into its callers only
        continue
    assert dispatcher.signatures, name  # compiled by warm()
    declared = getattr(dispatcher, "mistool_signatures", ())  # (none: compiled eagerly)
    assert len(dispatcher.signatures) >= len(declared), name
    assert not dispatcher._can_compile, name  # no second compilation at a call
print("ok", len(found), len(helpers))
"""


def test_there_are_kernels_and_each_is_compiled_and_closed() -> None:
    """Once loaded (``warm``), a kernel is compiled for its signatures and closed; a
    helper (called by kernels only) is never compiled on its own, not even once every
    kernel module is loaded. Checked in a new process once another has made the cache
    fresh, as every run finds it (``scripts/_env.sh`` warms it first): the process that
    compiles a kernel also compiles the helpers it calls, for their types."""
    subprocess.run([sys.executable, "-c", "from mistool.kernels import warm; warm()"], check=True)
    out = subprocess.run([sys.executable, "-c", _CLOSED], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("ok"), out.stdout


_LAZY = """
import numpy as np
from mistool.kernels import png, pose
kernels = [v for v in vars(pose).values() if getattr(v, "mistool_signatures", None)]
assert len(kernels) > 10 and not any(k.signatures for k in kernels), "pose loaded"
assert not png.unfilter_rows.signatures
rows = np.array([[1, 5, 6], [2, 1, 1]], np.uint8)
out = np.zeros((2, 2), np.uint8)
try:
    png.unfilter_rows(rows.astype(np.int16), 1, out)  # a first call of other types
except TypeError:
    print("TypeError", len(png.unfilter_rows.signatures), png.unfilter_rows._can_compile)
png.unfilter_rows(rows, 1, out)
print(out.tolist(), len(png.unfilter_rows.signatures))
"""


def test_a_kernel_is_loaded_at_its_first_call_only() -> None:
    """Importing a kernel module loads no machine code (~5-15 ms per kernel): a process
    pays only for the kernels it calls; the first call loads the declared signatures
    and closes the kernel: a call of other types is refused, the declared ones run."""
    out = subprocess.run([sys.executable, "-c", _LAZY], capture_output=True, text=True, check=True)
    assert out.stdout.split("\n")[:2] == ["TypeError 1 False", "[[5, 11], [6, 12]] 1"]


def test_an_argument_of_another_dtype_is_an_error_not_a_new_compilation() -> None:
    from mistool.kernels.png import unfilter_rows

    rows = np.zeros((2, 5), np.uint8)
    with pytest.raises(TypeError):
        unfilter_rows(rows.astype(np.int16), 1, np.zeros((2, 4), np.uint8))
    assert len(unfilter_rows.signatures) == 1


def test_a_kernel_needs_its_signatures() -> None:
    with pytest.raises(ValueError, match="signatures"):
        kernel()


def test_warm_imports_every_kernel_module() -> None:
    names = warm()
    assert "png" in names and not any(n.startswith("_") for n in names)
    out = subprocess.run(
        [sys.executable, "-m", "mistool.kernels"], capture_output=True, text=True, check=True
    )
    assert out.stdout.startswith("mistool kernels ready (") and "png" in out.stdout


_THREADS = """
import threading
import numpy as np
from mistool.kernels import png
rows = np.array([[1, 5, 6], [2, 1, 1]], np.uint8)
outs, errors = [np.zeros((2, 2), np.uint8) for _ in range(8)], []
def call(out):
    try:
        png.unfilter_rows(rows, 1, out)
    except Exception as exc:
        errors.append(repr(exc))
threads = [threading.Thread(target=call, args=(o,)) for o in outs]
for t in threads:
    t.start()
for t in threads:
    t.join()
print(errors, {str(o.tolist()) for o in outs}, len(png.unfilter_rows.signatures))
"""


def test_threads_calling_a_kernel_first_at_once_all_get_its_result() -> None:
    out = subprocess.run(
        [sys.executable, "-c", _THREADS], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[] {'[[5, 11], [6, 12]]'} 1"


def test_the_cache_is_dropped_when_any_kernel_source_changed(tmp_path: Path) -> None:
    """numba renews a kernel's cache when its own file changes, not when a module it
    calls into does (pose calls contours): every kernel's cached code goes when any
    kernel source changed, and stays while none did."""
    from mistool.kernels import renew_stale_cache

    cached = [tmp_path / "pose.shaft_from_masks-10.py311.nbi", tmp_path / "pose.x-1.py311.1.nbc"]
    other = tmp_path / "notes.txt"
    for p in (*cached, other):
        p.write_bytes(b"x")
    assert renew_stale_cache(tmp_path, "digest-a")  # no stamp yet: dropped, stamped
    assert not any(p.exists() for p in cached) and other.exists()
    for p in cached:
        p.write_bytes(b"x")  # compiled again from these sources
    assert not renew_stale_cache(tmp_path, "digest-a")
    assert all(p.exists() for p in cached)
    assert renew_stale_cache(tmp_path, "digest-b")  # a kernel source changed
    assert not any(p.exists() for p in cached)
    assert (tmp_path / "mistool-kernels.stamp").read_text() == "digest-b"


def test_the_cache_stamp_follows_every_kernel_source() -> None:
    from mistool import kernels

    folder = kernels._cache_folder()
    assert folder is not None
    kernels.warm()
    assert (folder / "mistool-kernels.stamp").read_text() == kernels._sources_digest()


def test_the_warm_up_if_stale_skips_a_fresh_cache() -> None:
    """``python -m mistool.kernels --if-stale`` (run by scripts/_env.sh before every
    serve and test) compiles nothing and does not import numba when the cache's stamp
    matches the sources."""
    from mistool import kernels

    kernels.warm()  # the stamp now matches (written when the cache was renewed)
    assert kernels.cache_is_fresh()
    code = (
        "import runpy, sys; sys.argv = ['x', '--if-stale']\n"
        "try:\n    runpy.run_module('mistool.kernels', run_name='__main__')\n"
        "except SystemExit as e:\n    print('exit', e.code, 'numba' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "exit 0 False"


def test_no_kernel_calls_itself() -> None:
    """numba cannot cache a function that calls itself (numba issue 6061): its machine
    code, loaded from the cache by a later process, has an unresolved symbol ("LLVM
    ERROR: Symbol not found" or a segmentation fault). So no function in a kernel module
    calls itself; a recursion is written with an explicit stack (``split._pairwise``)."""
    import ast

    calls_itself = []
    for path in sorted(Path(mistool.kernels.__file__).parent.glob("*.py")):
        for fn in ast.walk(ast.parse(path.read_text())):
            if not isinstance(fn, ast.FunctionDef):
                continue
            for node in ast.walk(fn):
                if (
                    isinstance(node, ast.Call)
                    and isinstance(node.func, ast.Name)
                    and node.func.id == fn.name
                ):
                    calls_itself.append(f"{path.name}:{node.lineno} {fn.name}")
    assert calls_itself == []


def test_a_kernel_compiled_first_in_one_process_loads_from_the_cache_in_the_next(
    tmp_path: Path,
) -> None:
    """The pairwise sum (numpy's summation order) compiled on its own into a new cache,
    then loaded from that cache by a second process, gives numpy's sum in both. (With
    the sum written as a recursion, the second process crashed: a segmentation fault,
    exit -11, from numba issue 6061; a process that compiled every kernel in module
    order did not show it, but one compiling the crossing split's score first did, after
    every cache renewal.)"""
    import os

    code = (
        "import numpy as np\n"
        "from mistool.kernels import split\n"
        "v = np.random.default_rng(1).uniform(0, 30, 1000)\n"
        "print(split.pairwise_sum(v, 1000) == float(np.add.reduce(v)))\n"
    )
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    for run in ("compiles", "loads"):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
        assert (run, out.returncode, out.stdout.strip()) == (run, 0, "True"), out.stderr[-2000:]
    assert list((tmp_path / "cache").rglob("*.nbc"))  # the second run did load a cache
