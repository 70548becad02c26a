"""Why a row has (or has not) a metric pose: the ``pose_status`` column.

Every row of a motion table gets a short text in ``pose_status``: ``"ok"`` when the
metric pose of that row is filled (shaft: joint and axis; clasper: tip and axis; wrist:
axis and its proximal end, the joint), else the first reason the pose was left empty:

===================== ==================================================================
``ok``                the part's metric pose is filled and trusted
``no camera``         the config has no ``[camera]`` (no metric 3D at all)
``off``               the metric pose was turned off (``metric=False``, ``--no-metric``)
``no shaft diameter`` the instrument's ``shaft_diameter_mm`` is not known
``not visible``       the instrument's shaft is not in the frame (the pose starts from it)
``no silhouette line`` neither of the shaft's two outline lines could be fitted (too
                      short a visible stretch, or too ragged an outline)
``one silhouette line`` only one outline line: the shaft runs along the image border or
                      is cut lengthwise (the trocar may fill it later in the sequence)
``pointing at camera`` the shaft is seen nearly end-on: its depth is too uncertain
``low quality``       the outline lines are too short or too noisy for a trusted depth
``rejected``          the geometry is inconsistent (e.g. the lines' apparent width does
                      not match the mask's; a numerically degenerate solve)
``joint out of view`` the shaft's distal end (the joint) is outside the image, or no
                      cue says which end is distal
``occluded``          the shaft's visible end is a cut by something in front of it, not
                      the shaft's round end: the joint is hidden
``uncertain axis``    the joint is known but the shaft's direction is too uncertain
``merged``            two tools touch in a merged mask: only the larger shaft is measured
``no clasper``        a wrist whose instrument shows no clasper (its axis comes from it)
``tip not found``     the clasper's jaw ends could not be located
===================== ==================================================================

A part without its own reason takes its shaft's (a clasper whose joint is unknown says
why the joint is). :func:`measure_instance` records a reason code per row in the
auxiliary column ``aux_status``; :func:`status_column` turns codes and the final metric
columns (after the sequence-level refinement, which may fill a row, e.g. a one-line
shaft through the trocar) into the text column.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

__all__ = [
    "AUX_STATUS",
    "OK",
    "REASONS",
    "reason_code",
    "status_column",
]

#: The ``pose_status`` values, in code order (see the module docstring).
REASONS: tuple[str, ...] = (
    "ok",
    "no camera",
    "off",
    "no shaft diameter",
    "not visible",
    "no silhouette line",
    "one silhouette line",
    "pointing at camera",
    "low quality",
    "rejected",
    "joint out of view",
    "occluded",
    "uncertain axis",
    "merged",
    "no clasper",
    "tip not found",
)
OK = "ok"
#: The auxiliary column holding a row's reason code (an index into :data:`REASONS`).
AUX_STATUS = "aux_status"

_CODE = {r: i for i, r in enumerate(REASONS)}

#: Per part, the metric columns that must be finite for the row to be ``"ok"``.
_REQUIRED: dict[str, tuple[str, ...]] = {
    "shaft": ("end_x_mm", "end_y_mm", "end_z_mm", "axis_x", "axis_y", "axis_z"),
    "clasper": ("end_x_mm", "end_y_mm", "end_z_mm", "axis_x", "axis_y", "axis_z"),
    "wrist": ("start_x_mm", "start_y_mm", "start_z_mm", "axis_x", "axis_y", "axis_z"),
}


def reason_code(reason: str) -> float:
    """The float code of a reason (stored in ``aux_status``); raises KeyError if unknown."""
    return float(_CODE[reason])


def status_column(cols: Mapping[str, np.ndarray], num_rows: int) -> np.ndarray:
    """The ``pose_status`` column (object array of str, (N,)) of a table's columns.

    A row is ``"ok"`` when its part's required metric columns are finite; otherwise its
    recorded reason (``aux_status``), or ``"rejected"`` when the row has no reason
    recorded (or was ``"ok"`` per frame and emptied later).
    """
    part = np.asarray(cols["part"]).astype(str) if num_rows else np.empty(0, dtype=str)
    nan = np.full(num_rows, math.nan)
    codes = np.asarray(cols.get(AUX_STATUS, nan), dtype=np.float64)
    ok = np.zeros(num_rows, dtype=bool)
    known = np.zeros(num_rows, dtype=bool)
    for name, req in (*_REQUIRED.items(), ("", _REQUIRED["shaft"])):
        sel = (part == name) if name else ~known
        known |= sel
        fin = np.ones(num_rows, dtype=bool)
        for c in req:
            fin &= np.isfinite(np.asarray(cols.get(c, nan), dtype=np.float64))
        ok[sel] = fin[sel]
    valid = np.isfinite(codes) & (codes >= 1) & (codes < len(REASONS))
    idx = np.where(valid, np.nan_to_num(codes), _CODE["rejected"]).astype(np.int64)
    out = np.asarray(REASONS, dtype=object)[idx]
    out[ok] = OK
    return out
