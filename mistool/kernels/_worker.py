"""Loads the kernels that a worker's per-frame work calls (the worker processes' fork
server preloads this, :data:`mistool.forkserver.PRELOAD`, so each worker inherits them
loaded).

Only these: loading all ~105 kernels took the fork server ~1.0 s in a new process, these
~0.4 s (a new ``mistool track`` waits for its workers that long). A kernel not listed
here loads in a worker at its first call (~1-20 ms, once per worker);
``tests/test_worker_kernels.py`` checks that the per-frame work of synthetic sequences
(one instrument, crossing instruments with merged labels, crowded tools with occluders)
calls none that is not listed.
"""

from __future__ import annotations

import importlib

from mistool.kernels import load_named
from mistool.numbaload import start_without_blas

#: Per kernel module, the kernels :func:`mistool.parallel.observe_batch` calls.
WORKER_KERNELS: dict[str, tuple[str, ...]] = {
    "png": ("unfilter_runs",),
    "boxes": ("fit_mask", "grown_box_of"),
    "instances": ("chamfer_gap", "components", "fit_parts", "mask_sums", "values_present"),
    "pose": (
        "instance_from_masks",
        "one_cut_shaft",
        "rims_iou",
        "shaft_boundary",
        "shaft_from_masks",
        "shaft_pose",
    ),
    "split": ("border_runs",),
}

start_without_blas()  # (a worker's process is mistool's own: no BLAS needed)
for _module, _names in WORKER_KERNELS.items():
    load_named(importlib.import_module(f"mistool.kernels.{_module}"), _names)
