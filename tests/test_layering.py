"""The structure rules of STYLE.md: the core never imports viser, imports flow one way."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "mistool"

# Layers, lowest first; a module may import only from its own layer or lower ones.
LAYERS: list[tuple[str, ...]] = [
    # kernels: compiled inner loops (numba, numpy only), imported by any layer above;
    # numbaload: how numba loads their cache (numba only)
    ("errors", "kernels", "parts", "forksafe", "numbaload"),
    ("model",),
    # export (CSV and atomic writes) needs only errors and model; synth writes truth.csv
    # calibration (camera files) is read by config (a lazy import: same layer)
    ("config", "resources", "export", "annotations", "columnar", "calibration"),
    # assignment: the one min-cost matching solver (tracking and evaluation share it);
    # pngdecode: the PNG decoder (numpy, zlib-ng, OpenCV only), read by sequence
    ("geometry", "assignment", "lens", "pngdecode"),
    ("sequence", "tracking", "paper", "pose", "synth", "evaluation"),
    # rows (growing numpy columns) and parallel (per-frame work, process / Dask pools;
    # worker_signals: imported by its workers' fork server only); heap: the collector
    # during a run (gc only); forkserver: the workers' fork server (multiprocessing only)
    ("rows", "parallel", "worker_signals", "heap", "forkserver"),
    # teaching: skill metrics, the report and the video export (tables and sequences in)
    ("skill", "report", "video"),
    ("api",),
    # a whole dataset: one api.run per sequence
    ("dataset",),
    # the table cache and background tracking into it (mistool serve, resumable)
    ("cache", "background"),
    ("viewer",),
    ("cli",),
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _top(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "mistool" and len(parts) > 1 else None


def _modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "_bundled" not in p.parts)


def _dotted(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def test_every_module_belongs_to_a_layer() -> None:
    for path in _modules():
        top = _top(_dotted(path))
        if top is not None:
            assert top in RANK, f"{path}: mistool.{top} is in no layer of tests/test_layering.py"


@pytest.mark.parametrize("path", _modules(), ids=lambda p: _dotted(p))
def test_imports_flow_one_way(path: Path) -> None:
    me = _top(_dotted(path))
    if me is None:
        return
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        for name in names:
            other = _top(name)
            if other is None or other == me:
                continue
            # The CLI may import the viewer, but only lazily inside a function body.
            assert RANK[other] <= RANK[me], (
                f"{path.name}: mistool.{me} (layer {RANK[me]}) imports mistool.{other} "
                f"(layer {RANK[other]}); imports must flow errors -> ... -> cli"
            )
        if me != "viewer" and isinstance(node, (ast.Import, ast.ImportFrom)):
            mods = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
            )
            assert not any(m.split(".")[0] == "viser" for m in mods) or me == "cli", (
                f"{path}: only mistool.viewer may import viser"
            )


CORE = sorted({_dotted(p) for p in _modules() if _top(_dotted(p)) not in (None, "viewer")})


@pytest.mark.parametrize("module", CORE)
def test_core_module_does_not_load_viser(module: str) -> None:
    code = (
        f"import sys, importlib; importlib.import_module({module!r}); "
        "sys.exit(3 if 'viser' in sys.modules else 0)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, f"{module} loads viser (or failed):\n{proc.stderr}"


def test_cli_parser_does_not_load_viser() -> None:
    code = (
        "import sys; from mistool.cli import build_parser; build_parser(); "
        "sys.exit(3 if 'viser' in sys.modules else 0)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
