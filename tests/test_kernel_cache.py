"""A kernel called by another kernel is cached under its own signatures, so that a
process loading it after ``python -m mistool.kernels`` finds it in the cache.

numba caches a function compiled for a caller's argument types under those types, and
one loaded by a declared signature under the signature: the same machine code, two
keys. A callee first compiled for its caller was then compiled again (seconds) by the
next process that loaded it by its signature (a worker, after the warm-up)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

MODULE = textwrap.dedent(
    """
    from mistool.kernels import kernel

    @kernel("float64(float64, int64)")
    def callee(x, n):
        return x * n + 0.5

    @kernel("float64(float64)")
    def caller(x):
        return callee(x, 4) - 1.0
    """
)

RUN = textwrap.dedent(
    """
    import json, sys
    sys.path.insert(0, sys.argv[1])
    import twokernels as m
    first = sys.argv[2]
    if first == "caller":
        value = m.caller(2.0)
    else:
        value = m.callee(2.0, 4)
    stats = {
        name: [sum(d._cache_hits.values()), sum(d._cache_misses.values())]
        for name, d in (("callee", m.callee), ("caller", m.caller))
    }
    print(json.dumps({"value": value, "stats": stats}))
    """
)


def _run(folder: Path, first: str) -> dict[str, object]:
    out = subprocess.run(
        [sys.executable, "-c", RUN, str(folder), first], check=True, capture_output=True, text=True
    ).stdout
    result: dict[str, object] = json.loads(out.strip().splitlines()[-1])
    return result


def test_a_callee_compiled_for_its_caller_is_cached_under_its_signature(tmp_path: Path) -> None:
    (tmp_path / "twokernels.py").write_text(MODULE)
    # a new cache: the caller's compilation loads (compiles) the callee first
    compiled = _run(tmp_path, "caller")
    assert compiled["value"] == 2.0 * 4 + 0.5 - 1.0
    assert compiled["stats"] == {"callee": [0, 1], "caller": [0, 1]}
    # the next process calls the callee alone: found in the cache, not compiled again
    loaded = _run(tmp_path, "callee")
    assert loaded["value"] == 2.0 * 4 + 0.5
    assert loaded["stats"] == {"callee": [1, 0], "caller": [0, 0]}
