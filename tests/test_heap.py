"""mistool.heap: the objects alive when a run starts stay out of the collector's walks
during it, and are handed back after."""

from __future__ import annotations

import gc
import threading

import numpy as np

from mistool.api import iter_track
from mistool.heap import frozen_heap


def _frames(n: int) -> list[np.ndarray]:
    out = []
    for i in range(n):
        a = np.zeros((64, 96), np.uint8)
        a[20 + i % 5 : 30 + i % 5, 10:60] = 160  # a shaft (EndoVis'15 values)
        a[18 + i % 5 : 32 + i % 5, 60:70] = 70  # its clasper
        out.append(a)
    return out


def test_frozen_inside_and_handed_back_after() -> None:
    before = gc.get_freeze_count()
    marker = [object()]  # alive on entry
    with frozen_heap():
        inside = gc.get_freeze_count()
        assert inside > before
        assert not any(o is marker for o in gc.get_objects())  # not walked
        with frozen_heap():  # nested: still frozen after the inner exit
            pass
        assert gc.get_freeze_count() >= inside
    assert gc.get_freeze_count() == before
    assert any(o is marker for o in gc.get_objects())  # back in a collected generation


def test_concurrent_uses_unfreeze_at_the_last_exit() -> None:
    before = gc.get_freeze_count()
    entered, release = threading.Event(), threading.Event()

    def other() -> None:
        with frozen_heap():
            entered.set()
            release.wait(5)

    t = threading.Thread(target=other)
    t.start()
    entered.wait(5)
    with frozen_heap():
        pass
    assert gc.get_freeze_count() > before  # the other thread's use still holds it
    release.set()
    t.join(5)
    assert gc.get_freeze_count() == before


def test_tracking_runs_with_the_heap_frozen() -> None:
    before = gc.get_freeze_count()
    seen = []
    for chunk in iter_track(_frames(6), chunk_frames=2):
        seen.append(gc.get_freeze_count())
        assert chunk.num_rows == 4  # two frames, shaft and clasper
    assert len(seen) == 3
    assert all(c > before for c in seen)
    assert gc.get_freeze_count() == before
