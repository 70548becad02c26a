"""``python -m mistool.kernels``: compile every kernel into numba's cache once, and the
package's Python modules into their bytecode.

``--if-stale``: the kernels only when the cache was not made from these kernel sources
(its stamp, :func:`mistool.kernels.renew_stale_cache`), so a set-up script can run it
every time: a fresh cache costs a Python start, not numba's; several processes compiling
the same kernels at once (pytest's workers) are avoided.

The bytecode (``__pycache__/*.pyc``, what ``pip install`` compiles for an installed
package) is written every time, for the modules whose bytecode is missing or older than
their source: an editable install writes it at the first import, unless the environment
says not to (``PYTHONDONTWRITEBYTECODE``); then every new process would compile each
module from source again (~0.1 s in each of ``mistool track``'s caller and fork server,
docs/throughput.md)."""

from __future__ import annotations

import compileall
import sys
import time
from pathlib import Path

from mistool.kernels import cache_is_fresh, warm

compileall.compile_dir(str(Path(__file__).parents[1]), quiet=2)  # (where it can write)
if "--if-stale" in sys.argv[1:] and cache_is_fresh():
    sys.exit(0)
start = time.perf_counter()
names = warm()
print(f"mistool kernels ready ({', '.join(names)}) in {time.perf_counter() - start:.1f} s")
