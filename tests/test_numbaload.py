"""mistool.numbaload: cached kernels loaded without parsing their bitcode.

The names a cached library defines are read from its ELF object file instead of its
parsed bitcode: checked here to be the same names for every kernel the workers load,
and the bitcode is still there (parsed late) when a new function links against one."""

from __future__ import annotations

import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from mistool.numbaload import defined_symbols
from mistool.synth import synthesize

ELF = sys.platform.startswith("linux")


def test_not_an_elf_object_gives_none() -> None:
    assert defined_symbols(b"") is None
    assert defined_symbols(b"\x7fELF" + b"\0" * 60) is None  # 32-bit class byte: 0
    assert defined_symbols(b"MZ" + b"\0" * 200) is None


def test_a_truncated_elf_object_gives_none() -> None:
    head = bytearray(64)
    head[:6] = b"\x7fELF\x02\x01"
    struct.pack_into("<Q", head, 0x28, 10_000)  # section headers past the end
    struct.pack_into("<HH", head, 0x3A, 64, 3)
    assert defined_symbols(bytes(head)) is None


_CHECK = textwrap.dedent(
    """
    import importlib, json

    import llvmlite.binding as ll
    from numba.core import codegen
    from mistool.numbaload import defined_symbols, install

    install()
    loaded = []  # every cached library's state as numba unpickles it, and the library
    patched = codegen.CPUCodeLibrary._unserialize.__func__

    def recording(cls, code, state):
        library = patched(cls, code, state)
        loaded.append((state, library))
        return library

    codegen.CPUCodeLibrary._unserialize = classmethod(recording)
    importlib.import_module("mistool.kernels._worker")  # loads the workers' kernels
    lazy = same = 0
    differ = []
    for (name, kind, data), library in loaded:
        lazy += "_mistool_bitcode" in library.__dict__
        shared = ll.parse_bitcode(data[1])
        from_bitcode = {
            gv.name
            for group in (shared.functions, shared.global_variables)
            for gv in group
            if not gv.is_declaration
        }
        if from_bitcode and defined_symbols(data[0]) == from_bitcode:
            same += 1
        else:
            differ.append(name)
    print(json.dumps({"loaded": len(loaded), "lazy": lazy, "same": same, "differ": differ}))
    """
)


def _warm(code: str) -> None:
    """Run ``code`` in a new process: what it loads is in the cache afterwards (a
    cache made before these loaders, or emptied by an edit, is filled first)."""
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


@pytest.mark.skipif(not ELF, reason="numba's object files are ELF on Linux only")
def test_every_worker_kernel_defines_the_same_names_as_its_bitcode() -> None:
    # a new process: every worker kernel loaded from the cache, none compiled there
    _warm("import mistool.kernels._worker")
    out = subprocess.run(
        [sys.executable, "-c", _CHECK], check=True, capture_output=True, text=True
    ).stdout
    import json

    found = json.loads(out.strip().splitlines()[-1])
    assert found["differ"] == []
    assert found["loaded"] >= 15  # the workers' kernels and their signatures
    assert found["lazy"] == found["same"] == found["loaded"]


_LINK = textwrap.dedent(
    """
    import numpy as np
    from numba import njit
    from mistool.kernels import _load, split

    _load(split.pairwise_sum)  # from the cache: its bitcode kept unparsed
    library = next(iter(split.pairwise_sum.overloads.values())).library
    kept = "_mistool_bitcode" in library.__dict__

    @njit
    def twice(a, n):  # compiled here, linking pairwise_sum's library
        return 2.0 * split.pairwise_sum(a, n)

    a = np.array([0.1, 0.2, 0.3, 1e-3, 7.0])
    sums = twice(a, 4), split.pairwise_sum(a, 4), np.add.reduce(a[:4])
    print(kept, *(repr(float(x)) for x in sums))
    """
)


@pytest.mark.skipif(not ELF, reason="numba's object files are ELF on Linux only")
def test_a_function_compiled_later_links_a_cached_kernel() -> None:
    _warm("from mistool.kernels import _load, split; _load(split.pairwise_sum)")
    out = subprocess.run(
        [sys.executable, "-c", _LINK], check=True, capture_output=True, text=True
    ).stdout.split()
    kept, twice, once, numpy_sum = out[0], float(out[1]), float(out[2]), float(out[3])
    assert kept == "True"
    assert once == numpy_sum
    assert twice == 2.0 * numpy_sum


_HIDDEN = textwrap.dedent(
    """
    import sys
    import numpy as np
    from mistool.numbaload import start_without_blas

    start_without_blas()
    import numba.np.arraymath as arraymath
    from mistool.kernels import split

    hidden = "scipy.linalg" not in sys.modules
    a = np.array([0.1, 0.2, 0.3, 1e-3])
    kernel_ok = float(split.pairwise_sum(a, 4)) == float(np.add.reduce(a))
    scipy_before = sys.modules["scipy"]
    import scipy.linalg
    from scipy.optimize import linear_sum_assignment

    rows, cols = linear_sum_assignment(np.array([[4.0, 1.0], [2.0, 8.0]]))
    print(hidden, arraymath._HAVE_BLAS, kernel_ok, sys.modules["scipy"] is scipy_before,
          scipy.linalg.__name__, rows.tolist(), cols.tolist())
    """
)


def test_numba_starts_without_scipy_linalg_which_stays_importable() -> None:
    out = subprocess.run(
        [sys.executable, "-c", _HIDDEN], check=True, capture_output=True, text=True
    ).stdout.split()
    assert out == ["True", "False", "True", "True", "scipy.linalg", "[0,", "1]", "[1,", "0]"]


def test_the_command_and_the_workers_never_import_scipy_linalg(tmp_path: Path) -> None:
    """``mistool track`` on a crossing sequence, and the workers' preload, in new
    processes: numba started without its BLAS check, nothing else needed SciPy's
    linalg (the check is what imported it); nor did they install the implementations
    numba needs only to compile (its target was never refreshed), and the table is the
    one this process (numba's own start, refreshed by the tests before) writes."""
    from mistool.cli import main

    seq = tmp_path / "seq"
    synthesize(seq, frames=20, instruments=2, seed=4, force=True)
    compile_only = "numba.np.polynomial.polynomial_core"  # imported by a refresh only
    command = (
        "import sys\n"
        "from mistool.cli import main\n"
        f"code = main(['track', {str(seq)!r}, '-o', {str(tmp_path / 'm.csv')!r}, '-q',"
        " '--workers', '1'])\n"
        f"print(code, 'scipy.linalg' in sys.modules, {compile_only!r} in sys.modules)\n"
    )
    preload = (
        "import sys, mistool.kernels._worker\n"
        f"print('scipy.linalg' in sys.modules, {compile_only!r} in sys.modules)"
    )
    ran = subprocess.run([sys.executable, "-c", command], capture_output=True, text=True)
    assert ran.stdout.split() == ["0", "False", "False"], ran.stderr
    assert main(["track", str(seq), "-o", str(tmp_path / "here.csv"), "-q", "--workers", "1"]) == 0
    assert (tmp_path / "m.csv").read_bytes() == (tmp_path / "here.csv").read_bytes()
    assert (tmp_path / "m.csv").stat().st_size > 1000
    ran = subprocess.run([sys.executable, "-c", preload], capture_output=True, text=True)
    assert ran.stdout.split() == ["False", "False"], ran.stderr


_COMPILE_LATER = textwrap.dedent(
    """
    import sys
    import numpy as np
    from numba import njit
    from mistool.numbaload import start_without_blas

    start_without_blas()
    from mistool.kernels import _load, split

    _load(split.pairwise_sum)  # from the cache, the target not refreshed
    before = "numba.np.polynomial.polynomial_core" in sys.modules

    @njit
    def counted(a):  # compiled here: numba's compiler refreshes the target first
        seen = {a[0]: 0}
        for v in a:
            seen[v] = seen.get(v, 0) + 1
        return len(seen), np.median(a), split.pairwise_sum(a, 4)

    a = np.array([3.0, 1.0, 3.0, 2.0, 5.0])
    n, med, total = counted(a)
    after = "numba.np.polynomial.polynomial_core" in sys.modules
    print(before, after, n, repr(float(med)), float(total) == float(np.add.reduce(a[:4])))
    """
)


def test_a_function_compiled_after_the_lean_start_finds_every_implementation() -> None:
    _warm("from mistool.kernels import _load, split; _load(split.pairwise_sum)")
    out = subprocess.run(
        [sys.executable, "-c", _COMPILE_LATER], check=True, capture_output=True, text=True
    ).stdout.split()
    assert out == ["False", "True", "4", "3.0", "True"]


def test_every_kernel_loads_from_the_cache_after_the_lean_start() -> None:
    """Every cached kernel's machine code finds the symbols it links to (a missing one
    aborts the process) and the environment it needs, with the target never refreshed."""
    code = textwrap.dedent(
        """
        import sys
        from numba.core import base
        from mistool.numbaload import start_without_blas

        start_without_blas()
        refreshed = []
        base.BaseContext.refresh = lambda self: refreshed.append(self)
        import mistool.kernels as kernels

        names = kernels.warm()
        print(len(names), len(refreshed))
        """
    )
    _warm("import mistool.kernels as k; k.warm()")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    loaded, refreshed = map(int, out.stdout.split())
    assert loaded >= 10
    assert refreshed == 0
