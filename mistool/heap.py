"""The garbage collector's view of a long run's heap.

Python's cyclic garbage collector walks every tracked object of its oldest generation in
each full collection. A tracking run's caller holds the whole import graph (numpy, OpenCV,
numba's compiled kernels: ~130,000 objects) there, so each full collection, triggered by
the many short-lived result objects of the per-frame work, paused the run for ~50 ms
while nothing else moved: the worker processes wait for the caller's next batch, and the
caller waits for the result that the collecting thread is unpickling (one such pause in
a 2,500-frame run, ~7% of its time; see docs/throughput.md, tenth session).
"""

from __future__ import annotations

import contextlib
import gc
import threading
from collections.abc import Iterator

_LOCK = threading.Lock()
_HOLDERS = [0]


@contextlib.contextmanager
def frozen_heap() -> Iterator[None]:
    """Leave the objects alive on entry out of the collector's walks until exit.

    ``gc.freeze()`` on entry moves them to the permanent generation; ``gc.unfreeze()``
    on the last exit (nested or concurrent uses count) puts them back in the oldest
    generation, as if this had not run. Objects created inside are collected as usual;
    a cycle among the frozen ones that becomes garbage meanwhile is collected after
    exit."""
    with _LOCK:
        _HOLDERS[0] += 1
        gc.freeze()
    try:
        yield
    finally:
        with _LOCK:
            _HOLDERS[0] -= 1
            if _HOLDERS[0] == 0:
                gc.unfreeze()
