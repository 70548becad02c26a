"""Where mistool's bundled files live: ``sample_masks/`` and ``web_assets/``.

In a source checkout or an editable install they sit beside the package (the repository
root); a wheel install carries copies inside the package (``mistool/_bundled/``).
"""

from __future__ import annotations

from pathlib import Path

from mistool.errors import InputPathError

_PACKAGE = Path(__file__).resolve().parent


def _find(name: str) -> Path:
    for candidate in (_PACKAGE.parent / name, _PACKAGE / "_bundled" / name):
        if candidate.is_dir():
            return candidate
    raise InputPathError(
        f"bundled folder {name!r} not found beside {_PACKAGE}; "
        "reinstall mistool or pass a folder explicitly"
    )


def sample_masks_dir() -> Path:
    """The bundled sample sequence (what ``mistool serve`` shows with no argument)."""
    return _find("sample_masks")


def web_assets_dir() -> Path:
    """Static files the viewer ships (meshes, logo, styles)."""
    return _find("web_assets")
