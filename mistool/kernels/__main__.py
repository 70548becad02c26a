"""``python -m mistool.kernels``: compile every kernel into numba's cache once.

``--if-stale``: only when the cache was not made from these kernel sources (its stamp,
:func:`mistool.kernels.renew_stale_cache`), so a set-up script can run it every time: a
fresh cache costs a Python start, not numba's; several processes compiling the same
kernels at once (pytest's workers) are avoided."""

from __future__ import annotations

import sys
import time

from mistool.kernels import cache_is_fresh, warm

if "--if-stale" in sys.argv[1:] and cache_is_fresh():
    sys.exit(0)
start = time.perf_counter()
names = warm()
print(f"mistool kernels ready ({', '.join(names)}) in {time.perf_counter() - start:.1f} s")
