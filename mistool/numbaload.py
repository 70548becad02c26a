"""Loading cached numba kernels without parsing their LLVM bitcode.

numba caches a compiled function as its machine code (an object file) *and* its LLVM
bitcode, the latter only so that a function compiled later in the same process can
inline it. At each load it parses that bitcode and walks it for the names the library
defines (so that a later symbol look-up never asks the JIT for a name it lacks). In a
mistool process nothing is compiled once the kernels are loaded (they are closed:
:func:`mistool.kernels.kernel`), yet the parse and the walk were ~80% of loading the
workers' kernels (~0.45 s of ~0.57 in a new process, ``instance_from_masks`` alone
~0.1 s), paid by the caller and by the workers' fork server at every ``mistool track``.

:func:`install` changes two things in numba's CPU code library, and nothing else:

- a library loaded from an ELF object file (Linux) takes its defined names from the
  object file's symbol table, which lists the same names (every cached kernel checked:
  ``tests/test_numbaload.py``), instead of from the parsed bitcode;
- the bitcode is kept as bytes and parsed only when another function is compiled
  against the library (numba's ``_get_module_for_linking``), as before, just later.

Any other object format (macOS, Windows), numba version or cache entry takes numba's
own path.

:func:`start_without_blas`, for mistool's own processes only (``mistool track`` and the
workers' fork server), starts numba's CPU target with what loading cached kernels needs
and no more: without its check for a BLAS, which imports ``scipy.linalg`` (~0.14 s of
the ~0.27 s numba's start took on an idle core) only to learn whether ``np.dot`` could
be compiled (no mistool kernel calls a BLAS; ``kernels.split`` reproduces its rounding
without it), and without installing the implementations of all numba can compile
(~0.1 s more), which loading machine code from the cache does not use.

This module imports nothing at import time; its functions import numba.
"""

from __future__ import annotations

import importlib
import struct
import sys
import threading
from typing import Any

__all__ = ["defined_symbols", "install", "start_without_blas"]

_INSTALLED = False
_LOCK = threading.Lock()

_SHT_SYMTAB = 2
_SHN_UNDEF = 0
_STT_SECTION, _STT_FILE = 3, 4


def defined_symbols(obj: bytes) -> set[str] | None:
    """The names an ELF64 little-endian object file defines (its symbol table's
    symbols with a section, a name and a type other than section or file), or None
    if ``obj`` is not such a file."""
    if len(obj) < 64 or obj[:4] != b"\x7fELF" or obj[4] != 2 or obj[5] != 1:
        return None
    try:
        (shoff,) = struct.unpack_from("<Q", obj, 0x28)
        shentsize, shnum = struct.unpack_from("<HH", obj, 0x3A)
        sections = [
            struct.unpack_from("<IIQQQQIIQQ", obj, shoff + i * shentsize) for i in range(shnum)
        ]
        names: set[str] = set()
        for _, kind, _, _, offset, size, link, _, _, entsize in sections:
            if kind != _SHT_SYMTAB or entsize < 24:
                continue
            strings = sections[link][4]
            for at in range(offset, offset + size, entsize):
                name, info, _, shndx = struct.unpack_from("<IBBH", obj, at)
                if shndx == _SHN_UNDEF or name == 0 or info & 0xF in (_STT_SECTION, _STT_FILE):
                    continue
                start = strings + name
                names.add(obj[start : obj.index(b"\0", start)].decode())
        return names
    except (struct.error, IndexError, ValueError, UnicodeDecodeError):
        return None


def install() -> None:
    """Make numba load cached CPU libraries without parsing their bitcode (see the
    module's docstring); idempotent, thread-safe. Does nothing when numba's code
    library does not have the shape this was written against."""
    global _INSTALLED
    with _LOCK:
        if _INSTALLED:
            return
        _INSTALLED = True
        from numba.core import codegen

        library = getattr(codegen, "CPUCodeLibrary", None)
        unserialize = getattr(library, "_unserialize", None)
        for_linking = getattr(library, "_get_module_for_linking", None)
        needed = ("enable_object_caching", "_set_compiled_object", "_finalize_final_module")
        if (
            library is None
            or unserialize is None
            or for_linking is None
            or not all(hasattr(library, name) for name in needed)
        ):
            return
        numbas_unserialize = unserialize.__func__
        parse_bitcode = codegen.ll.parse_bitcode

        def _unserialize(cls: Any, code: Any, state: Any) -> Any:
            name, kind, data = state
            known = getattr(getattr(code, "_engine", None), "_defined_symbols", None)
            names = None
            if kind == "object" and isinstance(known, set):
                names = defined_symbols(data[0])
            if names is None or known is None:
                return numbas_unserialize(cls, code, state)
            object_code, shared_bitcode = data
            self = code.create_library(name)
            self.enable_object_caching()
            self._set_compiled_object(object_code)
            self._mistool_bitcode = shared_bitcode  # parsed if another function links it
            self._finalize_final_module()
            known |= names  # the JIT engine's set of defined names
            return self

        def _get_module_for_linking(self: Any) -> Any:
            bitcode = self.__dict__.pop("_mistool_bitcode", None)
            if bitcode is not None and self._shared_module is None:
                self._shared_module = parse_bitcode(bitcode)
            return for_linking(self)

        library._unserialize = classmethod(_unserialize)
        library._get_module_for_linking = _get_module_for_linking


def start_without_blas() -> None:
    """Start numba's CPU target with only what loading its cached kernels needs, and
    without its check for a BLAS; ``scipy.linalg`` stays importable. Call it only in
    mistool's own processes (a command, the workers' fork server), never from the
    library's API, so that a user's own numba code keeps its BLAS. Does nothing if
    numba's target has started or ``scipy.linalg`` is imported.

    numba's first load of a cached kernel refreshes its target: it imports and installs
    the implementations of everything numba can compile (~50 modules; its BLAS check
    among them, which imports ``scipy.linalg``) and reads the installed packages' entry
    points for numba extensions, ~0.25 s of a new process on an idle core, though a
    kernel loaded from the cache is machine code that needs none of it. Here the target
    starts with its runtime (numba's NRT, the symbols machine code links to) and the
    modules whose import a cached kernel's environment or machine code needs
    (``numba.np.arraymath``, with ``scipy.linalg`` hidden for its BLAS check, and the
    hash secrets of ``numba.cpython.hashing``), and loading from the cache no longer
    refreshes. Anything compiled later (a kernel missing from the cache, a user's
    function) refreshes the target first, as numba's compiler always does, so it finds
    every implementation as before; in the process, numba then compiles no
    ``np.dot``/``@`` (no mistool kernel uses them). Where numba's cache has not the shape
    this was written against, the target is refreshed at once instead (numba's own way,
    still without the BLAS check)."""
    if "numba.np.arraymath" in sys.modules or "scipy.linalg" in sys.modules:
        return
    install()
    from numba.core import caching
    from numba.core.registry import cpu_target  # (numba imports scipy, not its linalg)

    context = cpu_target.target_context  # (its start: the JIT, C helpers, math symbols)
    cache = getattr(caching, "Cache", None)
    lean = all(
        hasattr(cache, name)
        for name in ("load_overload", "_load_overload", "_guard_against_spurious_io_errors")
    )
    hidden = "scipy.linalg"
    sys.modules[hidden] = None  # type: ignore[assignment]  # its import raises ImportError
    try:
        if lean:
            from numba.core.runtime import rtsys

            rtsys.initialize(context)
            importlib.import_module("numba.np.arraymath")  # (its BLAS check, hidden)
            importlib.import_module("numba.cpython.hashing")  # (its symbols)
        else:
            context.refresh()  # imports numba.np.arraymath: its BLAS check
    finally:
        if hidden in sys.modules and sys.modules[hidden] is None:
            del sys.modules[hidden]
    if lean:

        def load_overload(self: Any, sig: Any, target_context: Any) -> Any:
            # numba's, without its refresh of the target
            with self._guard_against_spurious_io_errors():
                return self._load_overload(sig, target_context)

        cache.load_overload = load_overload  # type: ignore[union-attr]
