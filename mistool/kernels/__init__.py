"""Compiled kernels: the per-frame inner loops, compiled by numba (one module per domain).

A kernel is a plain Python function over numpy arrays and scalars, compiled to machine code
by :func:`kernel` with its signatures given, so that:

- it compiles (or loads from numba's on-disk cache, ``__pycache__`` beside the module, or
  the user's cache folder when that is not writable) when its module is imported, never in
  the middle of a frame; the fork server of :class:`mistool.parallel.LocalPool` imports the
  kernels once and every worker inherits them;
- an argument of another dtype or layout is a ``TypeError`` at the call, not a silent
  second compilation;
- the arithmetic is IEEE (no ``fastmath``): the same operations in the same order give the
  same bits as numpy's.

A function only kernels call is a :func:`helper` instead: compiled into its callers, not
loaded by itself.

The modules that use a kernel wrap it in a typed Python function; tests compare each kernel
with the former numpy definition (``kernel.py_func`` runs the uncompiled Python).

``python -m mistool.kernels`` imports every kernel module, so a fresh install compiles them
all at once (``scripts/_env.sh`` does it after installing); without it the first import
of each module compiles it (about a second per kernel), once.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from typing import Any, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

__all__ = ["helper", "kernel", "warm"]


def kernel(*signatures: str) -> Callable[[F], F]:
    """Compile a function with numba for the given signatures (numba's string form,
    e.g. ``"void(uint8[:], uint8[:, ::1])"``), cached on disk, releasing the GIL, with
    numpy's error model (a division by zero gives inf or nan, as in numpy)."""
    if not signatures:
        raise ValueError("kernel(): give the signatures (compiled at import, not at a call)")

    def wrap(fn: F) -> F:
        from numba import njit

        compiled = njit(list(signatures), cache=True, nogil=True, error_model="numpy")(fn)
        return cast(F, compiled)  # a dispatcher, called as the function it compiles

    return wrap


def helper(fn: F) -> F:
    """Compile a function called only from other kernels: typed and compiled within each
    caller's compilation, its machine code linked into the caller's (cached with it), so
    loading a module from the cache does not load it on its own (each kernel loaded costs
    ~5-15 ms of numba's linking). Calling it from Python would compile it then: don't."""
    from numba import njit

    compiled = njit(cache=True, nogil=True, error_model="numpy")(fn)
    setattr(compiled, "mistool_helper", True)  # noqa: B010 - numba types the dispatcher
    return cast(F, compiled)


def warm() -> list[str]:
    """Import every kernel module (compiling what the cache does not hold); their names."""
    names = []
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        importlib.import_module(f"{__name__}.{info.name}")
        names.append(info.name)
    return names
