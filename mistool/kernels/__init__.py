"""Compiled kernels: the per-frame inner loops, compiled by numba (one module per domain).

A kernel is a plain Python function over numpy arrays and scalars, compiled to machine code
by :func:`kernel` with its signatures given, so that:

- it is loaded from numba's on-disk cache (``__pycache__`` beside the module, or the
  user's cache folder when that is not writable), or compiled when the cache does not
  hold it, at its first call and for its declared signatures only: a process pays
  (~5-15 ms per kernel) only for the kernels it calls, and importing a kernel module
  costs nothing more than numba's import; the fork server of
  :class:`mistool.parallel.LocalPool` loads every kernel once (:func:`warm`) and every
  worker inherits them;
- once loaded the kernel is closed: an argument of another dtype or layout is a
  ``TypeError`` at the call, not a silent second compilation;
- the arithmetic is IEEE (no ``fastmath``): the same operations in the same order give the
  same bits as numpy's.

A function only kernels call is a :func:`helper` instead: compiled into its callers, not
loaded by itself.

The modules that use a kernel wrap it in a typed Python function; tests compare each kernel
with the former numpy definition (``kernel.py_func`` runs the uncompiled Python).

``python -m mistool.kernels`` loads every kernel, so a fresh install compiles them all at
once (``scripts/_env.sh`` does it after installing); without it the first call of each
kernel compiles it (about a second per kernel), once.
"""

from __future__ import annotations

import importlib
import pkgutil
import threading
from collections.abc import Callable
from types import ModuleType
from typing import Any, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

__all__ = ["helper", "kernel", "load", "warm"]

_LOADING = threading.RLock()


def kernel(*signatures: str) -> Callable[[F], F]:
    """Compile a function with numba for the given signatures (numba's string form,
    e.g. ``"void(uint8[:], uint8[:, ::1])"``), cached on disk, releasing the GIL, with
    numpy's error model (a division by zero gives inf or nan, as in numpy).

    The machine code is loaded (from the cache, or compiled) at the kernel's first call
    or by :func:`load`, for exactly these signatures; after that the kernel is closed: a
    call with other argument types is a ``TypeError``, never a new compilation. (Loading
    costs ~5-15 ms per kernel: a process loads only the kernels it calls.)"""
    if not signatures:
        raise ValueError("kernel(): give the signatures (compiled at import, not at a call)")

    def wrap(fn: F) -> F:
        from numba import njit

        compiled: Any = njit(cache=True, nogil=True, error_model="numpy")(fn)
        unmatched = compiled._compile_for_args  # numba's path for a call no overload fits

        def first_call(*args: Any, **kwargs: Any) -> Any:
            # numba's dispatcher calls what this returns with the call's arguments; a
            # thread calling meanwhile waits in _load, then finds the kernel loaded
            _load(compiled)
            compiled._compile_for_args = unmatched  # (a later mismatch: numba's TypeError)
            return compiled

        compiled._compile_for_args = first_call
        compiled.mistool_signatures = signatures
        return cast(F, compiled)  # a dispatcher, called as the function it compiles

    return wrap


def _load(dispatcher: Any) -> None:
    """Load (or compile) a kernel's declared signatures and close it."""
    with _LOADING:
        if dispatcher._can_compile:
            for signature in dispatcher.mistool_signatures:
                dispatcher.compile(signature)
            dispatcher.disable_compile()


def load(module: ModuleType) -> int:
    """Load every kernel of a kernel module now (not at its first call); how many."""
    n = 0
    for value in vars(module).values():
        if getattr(value, "mistool_signatures", None) and value.__module__ == module.__name__:
            _load(value)
            n += 1
    return n


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
    """Import every kernel module and load its kernels (compiling what the cache does
    not hold); their names."""
    names = []
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        load(importlib.import_module(f"{__name__}.{info.name}"))
        names.append(info.name)
    return names
