"""Sequence-level refinement of the metric pose (:func:`refine_sequence`).

1. **Trocar**: per instrument, the robust least-squares intersection of the shaft's 3D axis
   lines (:mod:`mistool.pose.trocar`), after zero-phase smoothing of the lines, written
   to ``trocar_*_mm`` on every row of that instrument; NaN when the tool pivots too
   little (directions' spread < twice their frame-to-frame noise) for it to be trusted.
2. **Trocar constraint**, per frame (``"offline"`` and ``"none"``; ``"online"`` skips it,
   since the trocar is estimated from the whole sequence, future frames included):

   - *one limb line* (the shaft along the image border): the axis lies at distance r from
     the visible line's tangent plane, passes through the trocar and meets the joint's
     viewing ray: closed form (:func:`mistool.pose.cylinder.axis_through_point`);
   - *two limb lines*: the axis direction from the lines does not depend on the apparent
     width, but the depth does (a 1 px width error at 150 mm is ~3% of depth). A second
     estimate of J comes from the line through the trocar with the measured direction,
     met with the joint's viewing ray; both are fused by their expected variances.
3. **Temporal filtering** (:mod:`mistool.pose.filtering`) of end, start and axis per
   (instrument, part): ``"offline"`` zero-phase smoother, ``"online"`` causal filter,
   ``"none"``. Quaternions are recomputed from the filtered axes.
4. ``pose_status`` says per row whether the pose is filled (``"ok"``) or why not
   (:mod:`mistool.pose.status`); the per-frame auxiliary columns (``aux_*``) are dropped.
"""

from __future__ import annotations

import math

import numpy as np

from mistool.errors import ConfigError
from mistool.model import COLUMN_DTYPES, TrackTable, group_rows
from mistool.pose.filtering import MODES, filter_series, noise_scale
from mistool.pose.measure import AUX_KEYS, MAX_SIGMA_DEG
from mistool.pose.status import status_column
from mistool.pose.trocar import Trocar, intersect_lines

__all__ = ["ACCEL_MM_S2", "refine_sequence"]

#: White-acceleration scale of the Kalman filter for positions (mm/s^2) and axes (1/s^2).
ACCEL_MM_S2 = 50.0
_ACCEL_AXIS = 0.5

_END = ("end_x_mm", "end_y_mm", "end_z_mm")
_START = ("start_x_mm", "start_y_mm", "start_z_mm")
_AXIS = ("axis_x", "axis_y", "axis_z")
_QUAT = ("qw", "qx", "qy", "qz")
_TROCAR = ("trocar_x_mm", "trocar_y_mm", "trocar_z_mm")


def _get3(cols: dict[str, np.ndarray], names: tuple[str, ...], idx: np.ndarray) -> np.ndarray:
    return np.stack([cols[n][idx] for n in names], axis=1)


def _set3(
    cols: dict[str, np.ndarray], names: tuple[str, ...], idx: np.ndarray, values: np.ndarray
) -> None:
    for j, n in enumerate(names):
        cols[n][idx] = values[:, j]


def _trocar_fusion(
    cols: dict[str, np.ndarray], idx: np.ndarray, trocar: Trocar, K: np.ndarray, radius: float
) -> None:
    """Re-solve the shaft rows ``idx`` (one instrument) with the trocar constraint.

    Two limb lines: (1) a second joint estimate, the line through the trocar with the
    measured direction met with the joint's viewing ray, fused with the measured joint
    by inverse variances; (2) the direction fused with ``unit(J - T)``, whose error is
    the joint's and the trocar's over their distance (small: the trocar is far).
    One limb line: the closed-form solve through the trocar. The proximal point follows
    the new axis where the shaft's entry pixel is known.

    Row by row in a compiled kernel (:func:`mistool.kernels.refine.trocar_fusion`): the
    former numpy arithmetic to ~1e-13 mm on tracked sequences (``tests/test_refine.py``).
    """
    if not len(idx):
        return
    from mistool.kernels.refine import FUSION_INPUTS, trocar_fusion  # numba: at first use

    rows = np.stack([cols[n][idx] for n in FUSION_INPUTS], axis=1)
    out = np.empty((len(idx), 9))
    what = trocar_fusion(
        rows,
        np.ascontiguousarray(K, np.float64),
        np.ascontiguousarray(trocar.point, np.float64),
        np.ascontiguousarray(trocar.cov, np.float64),
        float(radius),
        float(MAX_SIGMA_DEG),
        out,
    )
    solved, started = what >= 1, what == 2
    for j, n in enumerate((*_END, *_AXIS)):
        cols[n][idx[solved]] = out[solved, j]
    for j, n in enumerate(_START):
        cols[n][idx[started]] = out[started, 6 + j]


def _realign_clasper(
    cols: dict[str, np.ndarray], shaft_idx: np.ndarray, clasper_idx: np.ndarray, frames: np.ndarray
) -> None:
    """Move each clasper row's start (= J) and end with its shaft row's joint (the shaft
    row of the same frame; the last one when a frame has several).

    Column arithmetic, element by element the former per-row loop's (the same
    subtraction then addition per coordinate), every value read before any is written:
    only clasper rows are written, and no shaft row is one."""
    if not len(shaft_idx) or not len(clasper_idx):
        return
    shaft_frames = frames[shaft_idx]
    order = np.argsort(shaft_frames, kind="stable")  # equal frames: the last one last
    ordered = shaft_frames[order]
    wanted = frames[clasper_idx]
    at = np.searchsorted(ordered, wanted, side="right") - 1
    have = at >= 0
    at[~have] = 0
    have &= ordered[at] == wanted
    src = shaft_idx[order[at]]
    J = np.stack([cols[n][src] for n in _END], axis=1)
    start = np.stack([cols[n][clasper_idx] for n in _START], axis=1)
    tip = np.stack([cols[n][clasper_idx] for n in _END], axis=1)
    ok = have & np.isfinite(J).all(axis=1) & np.isfinite(start).all(axis=1)
    moved = ok & np.isfinite(tip).all(axis=1)
    for j, n in enumerate(_START):
        cols[n][clasper_idx[ok]] = J[ok, j]
    for j, n in enumerate(_END):
        cols[n][clasper_idx[moved]] = tip[moved, j] + (J[moved, j] - start[moved, j])


def _reliable_trocar(cols: dict[str, np.ndarray], idx: np.ndarray, t: np.ndarray) -> Trocar | None:
    """The trocar of one instrument's shaft rows ``idx`` (time order), or None when the
    pivoting is too small for it to be trusted.

    Noisy per-frame directions make a bundle of nearly parallel lines look like it
    pivots: its least-squares point then slides toward the scene. So the lines are
    first smoothed (zero phase) and the trocar is kept only when the directions' spread
    is at least twice their frame-to-frame noise (estimated from second differences).
    """
    J = _get3(cols, _END, idx)
    a = _get3(cols, _AXIS, idx)
    ok = np.all(np.isfinite(J), axis=1) & np.all(np.isfinite(a), axis=1)
    if ok.sum() < 5:
        return None
    noise = max(noise_scale(a[ok, k], 1e-4) for k in range(3))  # ~ rad per frame
    Js = filter_series(t[idx], np.where(ok[:, None], J, np.nan), "offline", ACCEL_MM_S2, 0.05)
    As = filter_series(t[idx], np.where(ok[:, None], a, np.nan), "offline", _ACCEL_AXIS, 1e-4)
    As /= np.linalg.norm(As, axis=1, keepdims=True)
    trocar = intersect_lines(Js, As)
    if trocar is None or math.radians(trocar.spread_deg) < 2.0 * noise:
        return None
    return trocar


def _trocar_step(
    cols: dict[str, np.ndarray],
    config: object,
    smoothing: str,
    name: str,
    rows: np.ndarray,
    part: np.ndarray,
    frames: np.ndarray,
    fps: float,
) -> None:
    """One instrument (``name``, its ``rows`` as a bool mask): its trocar, the
    trocar-constrained solves (not online) and the distal orientation of axes without a
    distal cue; in place."""
    shaft_idx = np.flatnonzero(rows & (part == "shaft"))
    shaft_idx = shaft_idx[np.argsort(frames[shaft_idx], kind="stable")]
    trocar = _reliable_trocar(cols, shaft_idx, frames / fps)
    if trocar is None:
        return
    for j, n in enumerate(_TROCAR):
        cols[n][rows] = trocar.point[j]
    camera = getattr(config, "camera", None)
    diameter = None
    if hasattr(config, "shaft_diameter_for"):
        diameter = config.shaft_diameter_for(name)
    if camera is not None and diameter and smoothing != "online":
        _trocar_fusion(cols, shaft_idx, trocar, np.asarray(camera.K, float), diameter / 2)
        _realign_clasper(cols, shaft_idx, np.flatnonzero(rows & (part != "shaft")), frames)
    # orient axes away from the trocar (distal) where the frame had no distal cue
    nod = shaft_idx[cols["aux_distal"][shaft_idx] == 0]
    if len(nod):
        mid = _get3(cols, _START, nod)
        ax = _get3(cols, _AXIS, nod)
        flip = np.einsum("ij,ij->i", mid - trocar.point, ax) < 0
        _set3(cols, _AXIS, nod[flip], -ax[flip])


def _smooth(
    cols: dict[str, np.ndarray],
    smoothing: str,
    frames: np.ndarray,
    inst: np.ndarray,
    part: np.ndarray,
    fps: float,
) -> None:
    """Temporal filtering of end, start and axis per (instrument, part); in place."""
    for _key, idx in group_rows(inst, part):
        idx = idx[np.argsort(frames[idx], kind="stable")]
        t = frames[idx] / fps
        for names, acc, floor in (
            (_END, ACCEL_MM_S2, 0.05),
            (_START, ACCEL_MM_S2, 0.05),
            (_AXIS, _ACCEL_AXIS, 1e-4),
        ):
            y = _get3(cols, names, idx)
            f = filter_series(t, y, smoothing, acc, floor)
            if names is _AXIS:
                f /= np.linalg.norm(f, axis=1, keepdims=True)
            _set3(cols, names, idx, f)


def refine_sequence(table: TrackTable, config: object, smoothing: str = "offline") -> TrackTable:
    """Sequence-level metric refinement: trocar, trocar constraint, temporal filtering.

    Args:
        table: the motion table with the per-frame metric columns of
            :func:`~mistool.pose.measure_instance` (and its ``aux_*`` columns).
        config: the sequence's ``mistool.config.Config`` (camera, fps, diameters).
        smoothing: ``"none"``, ``"offline"`` (zero-phase smoother) or ``"online"``
            (causal filter).

    Returns:
        A new table: metric columns updated, ``trocar_*_mm`` and ``pose_status`` filled,
        ``aux_*`` dropped.

    Raises:
        ConfigError: unknown ``smoothing``.
    """
    if smoothing not in MODES:
        raise ConfigError(f"smoothing = {smoothing!r}: choose one of {', '.join(MODES)}")
    if table.num_rows == 0 or "end_x_mm" not in table:
        # no per-frame pose (e.g. measured without it): leave pose_status to the caller
        return TrackTable({c: v for c, v in table.items() if c not in AUX_KEYS})
    cols = {c: np.array(table[c], copy=True) for c in table.columns}
    for name in (*_END, *_START, *_AXIS, *_QUAT, *_TROCAR, "quality", *AUX_KEYS):
        if name not in cols:
            cols[name] = np.full(table.num_rows, np.nan)
    fps = float(getattr(config, "fps", 25.0) or 25.0)
    frames = np.asarray(cols["frame"])
    inst = np.asarray(cols["instrument"]).astype(str)
    part = np.asarray(cols["part"]).astype(str)
    for name in np.unique(inst):
        _trocar_step(cols, config, smoothing, str(name), inst == name, part, frames, fps)
    if smoothing != "none":
        _smooth(cols, smoothing, frames, inst, part, fps)
    ax = _get3(cols, _AXIS, np.arange(table.num_rows))
    rows = np.flatnonzero(np.all(np.isfinite(ax), axis=1))
    if len(rows):
        from mistool.kernels.refine import quats_of_axes  # numba: at first use

        quats = np.empty((len(rows), 4))  # quat_from_z(a / |a|) of each row, compiled
        quats_of_axes(np.ascontiguousarray(ax, np.float64), rows.astype(np.int64), quats)
        for j, n in enumerate(_QUAT):
            cols[n][rows] = quats[:, j]
    cols["pose_status"] = status_column(cols, table.num_rows)
    # the text columns are the table's (unchanged: not converted again)
    changed = {
        c: v
        for c, v in cols.items()
        if c not in AUX_KEYS and (COLUMN_DTYPES.get(c) is not object or c == "pose_status")
    }
    return table.without(*AUX_KEYS).with_columns(**changed)
