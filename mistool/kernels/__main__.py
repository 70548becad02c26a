"""``python -m mistool.kernels``: compile every kernel into numba's cache once."""

from __future__ import annotations

import time

from mistool.kernels import warm

start = time.perf_counter()
names = warm()
print(f"mistool kernels ready ({', '.join(names)}) in {time.perf_counter() - start:.1f} s")
