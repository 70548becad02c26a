"""``python -m mistool.kernels`` (the set-up scripts' warm step) writes the package's
bytecode too, where the environment says not to write it at import
(``PYTHONDONTWRITEBYTECODE``): else every new ``mistool track`` process compiles each
module from source again, in its caller and in its fork server."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import mistool


def test_warm_step_writes_missing_bytecode() -> None:
    source = Path(mistool.__file__).parent / "errors.py"
    cached = Path(importlib.util.cache_from_source(str(source)))
    cached.unlink(missing_ok=True)
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    env["PYTHONPATH"] = str(Path(mistool.__file__).parents[1])
    subprocess.run(
        [sys.executable, "-m", "mistool.kernels", "--if-stale"],
        env=env,
        check=True,
        capture_output=True,
    )
    data = cached.read_bytes()
    # A pyc's header: magic number, flags (0: checked by the source's mtime and size),
    # the source's mtime and size; the import system reads it only when these match.
    assert data[:4] == importlib.util.MAGIC_NUMBER
    assert int.from_bytes(data[4:8], "little") == 0
    stat = source.stat()
    assert int.from_bytes(data[8:12], "little") == int(stat.st_mtime) & 0xFFFFFFFF
    assert int.from_bytes(data[12:16], "little") == stat.st_size & 0xFFFFFFFF
