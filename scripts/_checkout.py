"""Import another mistool checkout's modules into this process (the A/B benchmarks)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from types import ModuleType


def import_checkout(root: Path, *names: str) -> tuple[ModuleType, ...]:
    """``mistool.<name>`` for each name, imported from the checkout at ``root``.

    Every ``mistool`` module already imported is forgotten first, so the modules returned
    (and everything they import) are ``root``'s own copy of the package; the ones loaded
    before stay usable through the references their callers hold."""
    for name in [m for m in sys.modules if m == "mistool" or m.startswith("mistool.")]:
        del sys.modules[name]
    sys.path.insert(0, str(root))
    try:
        modules = tuple(importlib.import_module(f"mistool.{name}") for name in names)
    finally:
        sys.path.remove(str(root))
    for module in modules:
        assert Path(str(module.__file__)).is_relative_to(root), module.__file__
    return modules
