"""mistool: 3D motion of surgical instruments from segmentation masks.

The public API (imported lazily, so ``import mistool`` stays light and never imports
viser)::

    table = mistool.track("masks/")                    # a folder, a mask video or arrays
    tracker = mistool.Tracker(mistool.load_config("mistool.toml"))   # frame by frame
    viewer = mistool.Viewer("mistool.toml"); viewer.add(labels)       # live 3D replay
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = [
    "Config",
    "MistoolError",
    "RotatedBox",
    "TrackTable",
    "Tracker",
    "Viewer",
    "load_config",
    "skill",
    "track",
]

# name -> module that defines it
_LAZY = {
    "track": "mistool.api",
    "Tracker": "mistool.api",
    "Viewer": "mistool.viewer",  # imports viser, only when asked for
    "load_config": "mistool.config",
    "Config": "mistool.config",
    "TrackTable": "mistool.model",
    "RotatedBox": "mistool.model",
    "MistoolError": "mistool.errors",
}

if TYPE_CHECKING:  # pragma: no cover
    from mistool.api import Tracker, track
    from mistool.config import Config, load_config
    from mistool.errors import MistoolError
    from mistool.model import RotatedBox, TrackTable
    from mistool.viewer import Viewer


def __getattr__(name: str) -> Any:
    if name == "skill":  # the module mistool.skill is callable: mistool.skill(table)
        import importlib

        return importlib.import_module("mistool.skill")
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'mistool' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
