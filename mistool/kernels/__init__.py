"""Compiled kernels: the per-frame inner loops, compiled by numba (one module per domain).

A kernel is a plain Python function over numpy arrays and scalars, compiled to machine code
by :func:`kernel` with its signatures given, so that:

- it is loaded from numba's on-disk cache (``__pycache__`` beside the module, or the
  user's cache folder when that is not writable), or compiled when the cache does not
  hold it, at its first call and for its declared signatures only: a process pays
  (~1-20 ms per kernel, its bitcode left unparsed: :mod:`mistool.numbaload`) only for
  the kernels it calls, and importing a kernel module
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

import contextlib
import hashlib
import importlib
import os
import pkgutil
import tempfile
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from types import ModuleType
from typing import Any, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

__all__ = ["cache_is_fresh", "helper", "kernel", "load", "load_named", "renew_stale_cache", "warm"]

_LOADING = threading.RLock()


def kernel(*signatures: str) -> Callable[[F], F]:
    """Compile a function with numba for the given signatures (numba's string form,
    e.g. ``"void(uint8[:], uint8[:, ::1])"``), cached on disk, releasing the GIL, with
    numpy's error model (a division by zero gives inf or nan, as in numpy).

    The machine code is loaded (from the cache, or compiled) at the kernel's first call,
    by :func:`load`, or when a kernel calling it is compiled, for exactly these
    signatures; after that the kernel is closed: a
    call with other argument types is a ``TypeError``, never a new compilation. (Loading
    costs ~1-20 ms per kernel: a process loads only the kernels it calls.)"""
    if not signatures:
        raise ValueError("kernel(): give the signatures (compiled at import, not at a call)")

    def wrap(fn: F) -> F:
        njit = _njit()
        compiled: Any = njit(cache=True, nogil=True, error_model="numpy")(fn)
        unmatched = compiled._compile_for_args  # numba's path for a call no overload fits

        def first_call(*args: Any, **kwargs: Any) -> Any:
            # numba's dispatcher calls what this returns with the call's arguments; a
            # thread calling meanwhile waits in _load, then finds the kernel loaded
            _load(compiled)
            compiled._compile_for_args = unmatched  # (a later mismatch: numba's TypeError)
            return compiled

        typed = compiled.get_call_template  # numba types a call from another kernel so

        def call_template(args: Any, kws: Any) -> Any:
            # another kernel calling this one is being compiled: this one is loaded by
            # its signatures first, never compiled for the caller's argument types
            # (numba caches such a callee under those types, not under the signature,
            # so that a process loading it by its signature compiled it again)
            _load(compiled)
            return typed(args, kws)

        compiled._compile_for_args = first_call
        compiled.get_call_template = call_template
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


def load_named(module: ModuleType, names: Iterable[str]) -> int:
    """Load the kernels of ``module`` with these names now; how many (a name that is not
    one of its kernels is skipped: the others still load)."""
    n = 0
    for name in names:
        value = getattr(module, name, None)
        if getattr(value, "mistool_signatures", None):
            _load(value)
            n += 1
    return n


def helper(fn: F) -> F:
    """Compile a function called only from other kernels: typed and compiled within each
    caller's compilation, its machine code linked into the caller's (cached with it), so
    loading a module from the cache does not load it on its own (each kernel loaded costs
    ~1-20 ms of numba's linking). Calling it from Python would compile it then: don't."""
    njit = _njit()
    compiled = njit(cache=True, nogil=True, error_model="numpy")(fn)
    setattr(compiled, "mistool_helper", True)  # noqa: B010 - numba types the dispatcher
    return cast(F, compiled)


def _njit() -> Any:
    """numba's ``njit``, with the package's cache renewed if stale and cached kernels
    loaded without parsing their bitcode (:mod:`mistool.numbaload`)."""
    from numba import njit

    from mistool.numbaload import install

    install()
    _renew_stale_cache_once()
    return njit


_STAMP = "mistool-kernels.stamp"
_renewed = False


def _renew_stale_cache_once() -> None:
    global _renewed
    with _LOADING:
        if not _renewed:
            _renewed = True
            folder = _cache_folder()
            if folder is not None:
                renew_stale_cache(folder, _sources_digest())


def _sources_digest() -> str:
    """A digest of every kernel module's source."""
    h = hashlib.sha1(usedforsecurity=False)
    for path in sorted(Path(__file__).parent.glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def _cache_folder() -> Path | None:
    """Where numba keeps this package's kernels' machine code: the folder of the first
    of its cache locators that takes a function of this package, as numba chooses."""
    from numba.core.caching import FunctionCache

    locators: list[Any] = list(FunctionCache._impl_class._locator_classes)
    for locator in locators:
        with contextlib.suppress(Exception):  # a locator that does not apply here
            found = locator.from_function(_sources_digest, __file__)
            if found is not None:
                return Path(found.get_cache_path())
    return None


def cache_is_fresh() -> bool:
    """Whether the package's own cache folder (``__pycache__`` beside the kernels, where
    numba caches when it can write there) holds kernels made from these sources; False
    when unsure. Does not import numba."""
    stamp = Path(__file__).parent / "__pycache__" / _STAMP
    try:
        return stamp.read_text() == _sources_digest()
    except OSError:
        return False


def renew_stale_cache(folder: Path, digest: str) -> bool:
    """Drop numba's cached machine code in ``folder`` unless it was made from these
    very kernel sources (``digest``); whether it was dropped.

    numba renews a kernel's cache when the kernel's own file changes, but a kernel calls
    helpers and kernels of other modules (``pose`` calls ``contours`` and ``polygon``),
    whose machine code is linked into the caller's and cached with it: after an edit or
    an upgrade of those modules alone the caller would go on running their old code.
    So the cache of every kernel is dropped when any kernel module changed (at most once
    per change: the next process recompiles what it calls, ``python -m mistool.kernels``
    everything)."""
    stamp = folder / _STAMP
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    for cached in [*folder.glob("*.nbi"), *folder.glob("*.nbc")]:
        with contextlib.suppress(OSError):
            cached.unlink()
    with contextlib.suppress(OSError):  # not writable: numba then caches elsewhere
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".stamp-")
        with os.fdopen(fd, "w") as f:
            f.write(digest)
        os.replace(tmp, stamp)
    return True


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
