"""Scoring motion tables against ground truth (``mistool eval``).

How rows are matched: a prediction's instruments are matched one-to-one to the truth's
instruments of the sequence by the Hungarian algorithm on the mean distance between their
parts' box centres over the (frame, part) pairs both have; instrument names may therefore
differ (merged masks: the tracker names instances itself). A pair with no common
(frame, part) is never matched. A predicted instrument left over is a *fragment* (the
tracker gave a tool a new identity, e.g. after a crossing): it joins its nearest truth
instrument if it shares no frame with the predicted instruments already matched to it; the
report counts fragments. Rows are then joined on (frame, matched instrument, part).

What is scored, per method and part (mistool's own extension of the paper's tables):

- **coverage**: truth rows (the part visible: clean area >= ``min_area_px``) that have a
  predicted row, over all such truth rows; the metric coverage counts predicted rows with a
  finite ``end_*_mm``. Truth rows below ``min_area_px`` are left out of every score.
- **Table 1** (the paper's Table 1 layout): mean ± sd of the absolute error of the box
  centre x, y (px) and of the box angle theta (degrees, modulo 180: a box's direction has
  no sign, so the error is ``min(d, 180 - d)``).
- **Table 2** (the paper's Table 2 layout, here per part): mean ± sd of the absolute error
  of the part's distal end x, y, z (``end_*_mm``), the median of the 3D end-point distance,
  and the axis angle error (degrees, between directed unit axes) as median and p90.

``sd`` is the sample standard deviation (ddof = 1; 0 for a single value). Rows a
prediction has but the truth does not are counted as ``extra`` (false positives).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mistool.assignment import linear_assignment
from mistool.errors import TableError
from mistool.model import PARTS, TrackTable, require_columns

_BOX = ("cx_px", "cy_px", "angle_deg")
_END = ("end_x_mm", "end_y_mm", "end_z_mm")
_AXIS = ("axis_x", "axis_y", "axis_z")

__all__ = [
    "EvalReport",
    "IdentityCoverage",
    "MethodReport",
    "evaluate",
    "evaluate_one",
    "format_report",
    "identity_coverage",
    "identity_hits",
    "with_mask_areas",
    "linear_assignment",
    "match_instruments",
]


def match_instruments(
    pred: TrackTable, truth: TrackTable, *, join_fragments: bool = True
) -> dict[str, str]:
    """Map predicted instrument names to truth names (see the module docstring).

    Args:
        pred: the predicted motion table.
        truth: the truth table.
        join_fragments: let a left-over predicted instrument join its nearest truth
            instrument when they never share a frame; False keeps the mapping strictly
            one-to-one (every renamed tool's later rows then count as misses).
    """
    p_names = sorted({str(x) for x in pred["instrument"]})
    t_names = sorted({str(x) for x in truth["instrument"]})
    if not p_names or not t_names:
        return {}
    t_index = {
        (int(f), str(i), str(p)): k
        for k, (f, i, p) in enumerate(
            zip(truth["frame"], truth["instrument"], truth["part"], strict=True)
        )
    }
    sums = np.zeros((len(p_names), len(t_names)))
    counts = np.zeros((len(p_names), len(t_names)))
    pi = {n: k for k, n in enumerate(p_names)}
    tx, ty = truth["cx_px"], truth["cy_px"]
    for r, (f, inst, part) in enumerate(
        zip(pred["frame"], pred["instrument"], pred["part"], strict=True)
    ):
        px, py = pred["cx_px"][r], pred["cy_px"][r]
        if not (math.isfinite(px) and math.isfinite(py)):
            continue
        for tj, tname in enumerate(t_names):
            k = t_index.get((int(f), tname, str(part)))
            if k is not None:
                sums[pi[str(inst)], tj] += math.hypot(px - tx[k], py - ty[k])
                counts[pi[str(inst)], tj] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.inf)
    big = (np.nanmax(mean[np.isfinite(mean)]) + 1.0) * 1e3 if np.isfinite(mean).any() else 1.0
    cost = np.where(np.isfinite(mean), mean, big)
    mapping = {
        p_names[a]: t_names[b] for a, b in linear_assignment(cost) if np.isfinite(mean[a, b])
    }
    if not join_fragments:
        return dict(sorted(mapping.items()))
    # fragments: a predicted instrument left over (the tracker changed the identity of a
    # tool, e.g. after a crossing) joins its nearest truth instrument if it never shares a
    # frame with the predicted instruments already matched to it
    frames: dict[str, set[int]] = {}
    for f, inst in zip(pred["frame"], pred["instrument"], strict=True):
        frames.setdefault(str(inst), set()).add(int(f))
    left = sorted(
        (float(mean[pi[n]].min()), n)
        for n in p_names
        if n not in mapping and np.isfinite(mean[pi[n]]).any()
    )
    for _, name in left:
        for tj in np.argsort(mean[pi[name]]):
            if not np.isfinite(mean[pi[name], tj]):
                break
            taken = set().union(*(frames[q] for q, t in mapping.items() if t == t_names[tj]))
            if not taken & frames[name]:
                mapping[name] = t_names[tj]
                break
    return dict(sorted(mapping.items()))


def _stats(values: np.ndarray) -> dict[str, float]:
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"n": 0, "mean": math.nan, "sd": math.nan, "median": math.nan, "p90": math.nan}
    return {
        "n": int(len(v)),
        "mean": float(v.mean()),
        "sd": float(v.std(ddof=1)) if len(v) > 1 else 0.0,
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
    }


@dataclass
class MethodReport:
    """One prediction's scores."""

    name: str
    """Method name (the file's stem, or the key given)."""
    instrument_map: dict[str, str]
    """Predicted instrument name -> truth instrument name."""
    parts: dict[str, dict[str, Any]]
    """Part -> scores: ``n_truth``, ``n_estimated``, ``coverage``, ``n_metric``,
    ``metric_coverage``, ``extra``, and per error (``x_px``, ``y_px``, ``theta_deg``,
    ``x_mm``, ``y_mm``, ``z_mm``, ``end_mm``, ``axis_deg``) a dict of
    ``n, mean, sd, median, p90``."""
    per_row: TrackTable
    """Per truth row: frame, instrument (truth), part, estimated (0/1), the errors."""

    @property
    def fragments(self) -> int:
        """Predicted instruments matched beyond one per truth instrument (identity
        changes of the tracker)."""
        return len(self.instrument_map) - len(set(self.instrument_map.values()))


@dataclass
class EvalReport:
    """Scores of one or more predictions against one truth."""

    methods: list[MethodReport] = field(default_factory=list)
    """One report per prediction, in the order given."""
    min_area_px: int = 20
    """Truth rows with a smaller clean area were left out."""

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (NaN -> None)."""

        def clean(x: Any) -> Any:
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, float) and not math.isfinite(x):
                return None
            return x

        return {
            "min_area_px": self.min_area_px,
            "methods": [
                {
                    "name": m.name,
                    "instrument_map": m.instrument_map,
                    "fragments": m.fragments,
                    "parts": clean(m.parts),
                }
                for m in self.methods
            ],
        }

    def per_frame(self) -> TrackTable:
        """Every method's per-row errors stacked, with a leading ``method`` column."""
        tables = []
        for m in self.methods:
            cols = {"method": [m.name] * m.per_row.num_rows}
            cols.update({c: m.per_row[c] for c in m.per_row.columns})
            tables.append(TrackTable(cols))
        return TrackTable.concat(tables)


def _angle_diff_mod180(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.abs(np.asarray(a, dtype=np.float64) - b) % 180.0
    return np.minimum(d, 180.0 - d)


def _visible_truth(truth: TrackTable, min_area_px: int) -> TrackTable:
    """The truth rows whose clean ``area_px`` is at least ``min_area_px`` (all without it)."""
    if "area_px" in truth and min_area_px > 0:
        area = truth["area_px"]
        truth = truth[~(np.isfinite(area) & (area < min_area_px))]
    return truth


def evaluate_one(
    pred: TrackTable,
    truth: TrackTable,
    name: str = "pred",
    min_area_px: int = 20,
    *,
    join_fragments: bool = True,
) -> MethodReport:
    """Score one prediction against the truth (see the module docstring).

    ``join_fragments=False`` matches instruments strictly one-to-one (see
    :func:`match_instruments`).
    """
    for t, what in ((pred, f"prediction {name}"), (truth, "truth")):
        require_columns(t, ("frame", "instrument", "part", "cx_px", "cy_px", "angle_deg"), what)
    truth = _visible_truth(truth, min_area_px)
    mapping = match_instruments(pred, truth, join_fragments=join_fragments)
    p_index: dict[tuple[int, str, str], int] = {}
    for r, (f, inst, part) in enumerate(
        zip(pred["frame"], pred["instrument"], pred["part"], strict=True)
    ):
        tname = mapping.get(str(inst))
        if tname is not None:
            p_index.setdefault((int(f), tname, str(part)), r)
    n = truth.num_rows
    j = np.array(
        [
            p_index.get((int(f), str(i), str(p)), -1)
            for f, i, p in zip(truth["frame"], truth["instrument"], truth["part"], strict=True)
        ],
        dtype=np.int64,
    )
    has = j >= 0

    def take(col: str) -> np.ndarray:
        out = np.full(n, np.nan)
        out[has] = pred[col][j[has]]
        return out

    err: dict[str, np.ndarray] = {
        "err_x_px": np.abs(take("cx_px") - truth["cx_px"]),
        "err_y_px": np.abs(take("cy_px") - truth["cy_px"]),
        "err_theta_deg": _angle_diff_mod180(take("angle_deg"), truth["angle_deg"]),
    }
    pe = np.stack([take(c) for c in _END], axis=1)
    te = np.stack([truth[c] for c in _END], axis=1)
    for k, ax in enumerate("xyz"):
        err[f"err_{ax}_mm"] = np.abs(pe[:, k] - te[:, k])
    err["err_end_mm"] = np.linalg.norm(pe - te, axis=1)
    pa = np.stack([take(c) for c in _AXIS], axis=1)
    ta = np.stack([truth[c] for c in _AXIS], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        pa = pa / np.linalg.norm(pa, axis=1, keepdims=True)
        ta = ta / np.linalg.norm(ta, axis=1, keepdims=True)
        cosang = np.clip(np.sum(pa * ta, axis=1), -1.0, 1.0)
    err["err_axis_deg"] = np.degrees(np.arccos(cosang))
    metric = has & np.all(np.isfinite(pe), axis=1)

    parts: dict[str, dict[str, Any]] = {}
    matched_pred = np.zeros(pred.num_rows, dtype=bool)
    matched_pred[j[has]] = True
    part_names = [p for p in PARTS if p in set(truth["part"]) | set(pred["part"])]
    for part in part_names:
        sel = truth["part"] == part
        nt = int(sel.sum())
        ne = int((sel & has).sum())
        nm = int((sel & metric).sum())
        extra = int(((pred["part"] == part) & ~matched_pred).sum())
        rep: dict[str, Any] = {
            "n_truth": nt,
            "n_estimated": ne,
            "coverage": ne / nt if nt else math.nan,
            "n_metric": nm,
            "metric_coverage": nm / nt if nt else math.nan,
            "extra": extra,
        }
        for key in ("x_px", "y_px", "theta_deg", "x_mm", "y_mm", "z_mm", "end_mm", "axis_deg"):
            rep[key] = _stats(err[f"err_{key}"][sel])
        parts[part] = rep
    per_row = TrackTable(
        {
            "frame": truth["frame"],
            "instrument": truth["instrument"],
            "part": truth["part"],
            "pred_instrument": [str(pred["instrument"][k]) if k >= 0 else "" for k in j],
            "estimated": has.astype(np.int64),
            **err,
        }
    )
    return MethodReport(name, mapping, parts, per_row)


def evaluate(
    preds: Mapping[str, TrackTable], truth: TrackTable, min_area_px: int = 20
) -> EvalReport:
    """Score several predictions against one truth.

    Args:
        preds: method name -> predicted motion table, in display order.
        truth: the ground truth (e.g. ``truth.csv`` of ``mistool synth``).
        min_area_px: truth rows whose clean ``area_px`` is smaller are left out.

    Returns:
        An :class:`EvalReport`; format it with :func:`format_report`.
    """
    if not preds:
        raise TableError("evaluate: no prediction given")
    if truth.num_rows == 0:
        raise TableError("truth table has no rows: nothing to score against")
    return EvalReport(
        [evaluate_one(t, truth, name, min_area_px) for name, t in preds.items()], min_area_px
    )


@dataclass(frozen=True)
class IdentityCoverage:
    """Strict (one-to-one) identity coverage of one prediction against the truth."""

    coverage: float
    """Truth rows (all parts, visible: ``area_px >= min_area_px``) found under the one
    predicted name matched to their instrument *and* nearer to that instrument's box
    than to any other instrument's box of the part, over all such rows; NaN without
    truth rows."""
    parts: dict[str, float]
    """The same per part (``shaft``, ``wrist``, ``clasper``), in :data:`PARTS` order."""
    names: int
    """Distinct instrument names the prediction handed out."""
    true_names: int
    """Distinct instruments of the truth."""
    detected: float = math.nan
    """The same share among the *detected* truth rows only: those for which the
    prediction has some row of that part in that frame nearer to this instrument than
    to any other (under any name). A part hidden in the masks themselves (an occluder
    over a head: the truth comes from the clean render) is then no identity error."""
    visible: float = math.nan
    """The same share among the truth rows whose part keeps at least ``min_area_px``
    pixels in the masks tracked (the truth's ``mask_area_px``: :func:`with_mask_areas`
    of ``mistool synth``'s ``mask_areas.csv``; NaN without that column): the rows a
    tracker can find at all, so
    ``coverage`` is at most the share of such rows (the sequence's ceiling)."""
    ceiling: float = math.nan
    """The share of the truth rows (those of ``coverage``) visible in that sense."""


def identity_coverage(
    pred: TrackTable, truth: TrackTable, min_area_px: int = 20
) -> IdentityCoverage:
    """Strict identity coverage: how much of the truth one stable name per tool explains.

    Predicted instruments are matched one-to-one to the truth's by the Hungarian algorithm
    on mean box-centre distance (:func:`match_instruments` with ``join_fragments=False``).
    A visible truth row counts when the name matched to its instrument has a row of that
    part in that frame whose box centre is nearer to this instrument's box than to every
    other truth instrument's box of the part in that frame. So a tool the tracker renamed
    midway counts its second name's rows as misses, and two tools whose names swapped
    after a crossing count the swapped rows as misses.

    Args:
        pred: the predicted motion table (``frame``, ``instrument``, ``part``, box centre).
        truth: the truth (e.g. ``truth.csv`` of ``mistool synth``).
        min_area_px: truth rows whose clean ``area_px`` is smaller are left out.

    Returns:
        An :class:`IdentityCoverage`.
    """
    truth, hit, found = identity_hits(pred, truth, min_area_px)
    hits: dict[str, list[bool]] = {}
    for p, ok in zip(truth["part"], hit, strict=True):
        hits.setdefault(str(p), []).append(bool(ok))
    n_det = int(found.sum())
    visible, ceiling = math.nan, math.nan
    if "mask_area_px" in truth and len(hit):
        shown = np.asarray(truth["mask_area_px"], dtype=np.float64) >= max(min_area_px, 1)
        ceiling = float(shown.mean())
        visible = float(hit[shown].mean()) if shown.any() else math.nan
    return IdentityCoverage(
        coverage=float(hit.mean()) if len(hit) else math.nan,
        parts={p: sum(hits[p]) / len(hits[p]) for p in PARTS if p in hits},
        names=len({str(x) for x in pred["instrument"]}),
        true_names=len({str(x) for x in truth["instrument"]}),
        detected=float(hit[found].sum()) / n_det if n_det else math.nan,
        visible=visible,
        ceiling=ceiling,
    )


def with_mask_areas(truth: TrackTable, areas: TrackTable) -> TrackTable:
    """The truth with a ``mask_area_px`` column from ``areas`` (``frame``, ``instrument``,
    ``part``, ``mask_area_px``: ``mask_areas.csv`` of ``mistool synth``), by row key;
    NaN for a row ``areas`` lacks."""
    require_columns(areas, ("frame", "instrument", "part", "mask_area_px"), "mask areas")
    by_key = {
        (int(f), str(i), str(p)): float(a)
        for f, i, p, a in zip(
            areas["frame"], areas["instrument"], areas["part"], areas["mask_area_px"], strict=True
        )
    }
    col = np.array(
        [
            by_key.get((int(f), str(i), str(p)), math.nan)
            for f, i, p in zip(truth["frame"], truth["instrument"], truth["part"], strict=True)
        ],
        dtype=np.float64,
    )
    return truth.with_columns(mask_area_px=col)


def identity_hits(
    pred: TrackTable, truth: TrackTable, min_area_px: int = 20
) -> tuple[TrackTable, np.ndarray, np.ndarray]:
    """Per truth row, whether :func:`identity_coverage` counts it.

    Returns:
        ``(truth, hit, detected)``: the truth rows scored (``area_px >= min_area_px``,
        in the truth's order), and per row (bool arrays of that length) whether it is
        found under its matched name, and whether the prediction detected it at all
        (some row of that part in that frame nearer to this instrument than to any
        other, under any name).
    """
    for t, what in ((pred, "prediction"), (truth, "truth")):
        require_columns(t, ("frame", "instrument", "part", "cx_px", "cy_px"), what)
    truth = _visible_truth(truth, min_area_px)
    mapping = match_instruments(pred, truth, join_fragments=False)
    name_of = {t: p for p, t in mapping.items()}
    p_xy: dict[tuple[int, str, str], tuple[float, float]] = {}
    for f, i, p, x, y in zip(
        pred["frame"], pred["instrument"], pred["part"], pred["cx_px"], pred["cy_px"], strict=True
    ):
        p_xy.setdefault((int(f), str(i), str(p)), (float(x), float(y)))
    t_rows = list(
        zip(
            (int(f) for f in truth["frame"]),
            (str(i) for i in truth["instrument"]),
            (str(p) for p in truth["part"]),
            truth["cx_px"].astype(float),
            truth["cy_px"].astype(float),
            strict=True,
        )
    )
    by_frame_part: dict[tuple[int, str], list[tuple[str, float, float]]] = {}
    for f, i, p, x, y in t_rows:
        by_frame_part.setdefault((f, p), []).append((i, x, y))

    def nearest(f: int, p: str, xy: tuple[float, float]) -> str:
        rows = by_frame_part[(f, p)]
        return min(rows, key=lambda r: math.hypot(r[1] - xy[0], r[2] - xy[1]))[0]

    detected: set[tuple[int, str, str]] = set()  # (frame, truth instrument, part)
    for (f, _, p), xy in p_xy.items():
        if (f, p) in by_frame_part:
            detected.add((f, nearest(f, p, xy), p))
    hit = np.zeros(len(t_rows), bool)
    found = np.zeros(len(t_rows), bool)
    for k, (f, i, p, _, _) in enumerate(t_rows):
        got = p_xy.get((f, name_of.get(i, ""), p))
        hit[k] = got is not None and nearest(f, p, got) == i
        found[k] = (f, i, p) in detected
    return truth, hit, found


#: Frame offset between stacked runs in :func:`tag_run` (longer runs would collide).
RUN_FRAME_STRIDE = 100_000


def tag_run(table: TrackTable, run: int, frame_stride: int = RUN_FRAME_STRIDE) -> TrackTable:
    """One run's rows made distinct, so that several runs (e.g. seeds) stack into one table
    for :func:`evaluate`: frames offset by ``run * frame_stride``, instrument names prefixed
    with ``"<run>:"``.

    Raises:
        ValueError: a frame index at or beyond ``frame_stride``.
    """
    frames = np.asarray(table["frame"])
    if len(frames) and int(frames.max()) >= frame_stride:
        raise ValueError(f"frame {int(frames.max())} >= frame_stride {frame_stride}")
    return table.with_columns(
        frame=frames + run * frame_stride,
        instrument=np.array([f"{run}:{i}" for i in table["instrument"]], dtype=object),
    )


def paper_3d_oracle(
    pred: TrackTable, truth: TrackTable, fx: float, fy: float, cx: float, cy: float
) -> TrackTable:
    """The paper's per-frame output turned into a *generous* 3D estimate, with oracle help
    from the truth: a baseline for the metric pose (the paper's z has no unit).

    Depth ``Z = k * paper_z``, with ``k`` the least-squares scale to the true depth per part
    over the table (an oracle); the end point the box centre back-projected at ``Z``; the
    axis the box's long side in the image plane, with the sign of the truth's axis (another
    oracle). Instruments are matched to the truth as :func:`evaluate` matches them.

    Args:
        pred: a motion table with the paper columns (``paper_z``, ``paper_x_px``,
            ``paper_y_px``) and the boxes (``angle_deg``).
        truth: the ground truth (``truth.csv`` of ``mistool synth``).
        fx, fy, cx, cy: the camera intrinsics (px).

    Returns:
        ``pred`` with ``end_*_mm`` (mm) and ``axis_*`` (unit) filled as above; NaN where the
        row has no matching truth row or no paper depth.
    """
    key = {
        (int(f), str(i), str(p)): k
        for k, (f, i, p) in enumerate(
            zip(truth["frame"], truth["instrument"], truth["part"], strict=True)
        )
    }
    n = pred.num_rows
    tz = np.full(n, np.nan)
    ta = np.full((n, 3), np.nan)
    mapping = match_instruments(pred, truth)
    for r in range(n):
        k = key.get(
            (
                int(pred["frame"][r]),
                mapping.get(str(pred["instrument"][r]), ""),
                str(pred["part"][r]),
            )
        )
        if k is not None:
            tz[r] = truth["end_z_mm"][k]
            ta[r] = [truth["axis_x"][k], truth["axis_y"][k], truth["axis_z"][k]]
    z = np.full(n, np.nan)
    pz = pred["paper_z"]
    for part in set(pred["part"]):
        sel = (pred["part"] == part) & np.isfinite(pz) & np.isfinite(tz)
        if sel.any():
            scale = float(np.sum(pz[sel] * tz[sel]) / np.sum(pz[sel] ** 2))
            z[pred["part"] == part] = scale * pz[pred["part"] == part]
    px, py = pred["paper_x_px"], pred["paper_y_px"]
    theta = np.radians(pred["angle_deg"])
    axis = np.stack([np.cos(theta), np.sin(theta), np.zeros(n)], axis=1)
    flip = np.sum(axis * np.nan_to_num(ta), axis=1) < 0
    axis[flip] *= -1
    return pred.with_columns(
        end_x_mm=(px - cx) / fx * z,
        end_y_mm=(py - cy) / fy * z,
        end_z_mm=z,
        axis_x=axis[:, 0],
        axis_y=axis[:, 1],
        axis_z=axis[:, 2],
    )


def _pm(s: dict[str, float], digits: int = 2) -> str:
    if not s["n"]:
        return "-"
    return f"{s['mean']:.{digits}f} ± {s['sd']:.{digits}f}"


def _pct(x: float) -> str:
    return "-" if not math.isfinite(x) else f"{100 * x:.1f}%"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    widths = [max(len(r[k]) for r in [header, *rows]) for k in range(len(header))]
    fmt = "  ".join(f"{{:<{w}}}" if k < 2 else f"{{:>{w}}}" for k, w in enumerate(widths))
    lines = [fmt.format(*header), "  ".join("-" * w for w in widths)]
    lines += [fmt.format(*r) for r in rows]
    return lines


def format_report(report: EvalReport) -> str:
    """Both tables as aligned text (the paper's Table 1 and Table 2 layouts)."""
    parts = [p for p in PARTS if any(p in m.parts for m in report.methods)]
    rows1, rows2 = [], []
    for part in parts:
        for k, m in enumerate(report.methods):
            s = m.parts.get(part)
            if s is None:
                continue
            label = part if k == 0 else ""
            rows1.append(
                [
                    label,
                    m.name,
                    _pct(s["coverage"]),
                    str(s["extra"]),
                    _pm(s["x_px"]),
                    _pm(s["y_px"]),
                    _pm(s["theta_deg"]),
                ]
            )
            ax = s["axis_deg"]
            rows2.append(
                [
                    label,
                    m.name,
                    _pct(s["metric_coverage"]),
                    _pm(s["x_mm"]),
                    _pm(s["y_mm"]),
                    _pm(s["z_mm"]),
                    "-" if not s["end_mm"]["n"] else f"{s['end_mm']['median']:.2f}",
                    "-" if not ax["n"] else f"{ax['median']:.2f}",
                    "-" if not ax["n"] else f"{ax['p90']:.2f}",
                ]
            )
    out = [
        f"Table 1 - 2D box error per part, mean ± sd of |error| (truth rows with "
        f"area >= {report.min_area_px} px)"
    ]
    out += _table(["part", "method", "coverage", "extra", "x (px)", "y (px)", "θ (deg)"], rows1)
    out += [
        "",
        "Table 2 - 3D error per part (distal end: shaft J, wrist W, clasper tip), "
        "mean ± sd of |error|",
    ]
    out += _table(
        [
            "part",
            "method",
            "coverage",
            "x (mm)",
            "y (mm)",
            "z (mm)",
            "3D med (mm)",
            "axis med (deg)",
            "axis p90 (deg)",
        ],
        rows2,
    )
    maps = [
        f"  {m.name}: "
        + (
            ", ".join(f"{p}->{t}" for p, t in sorted(m.instrument_map.items()))
            or "no instrument matched"
        )
        + (
            f"  ({m.fragments} fragment(s): the tracker changed a tool's identity)"
            if m.fragments
            else ""
        )
        for m in report.methods
    ]
    out += ["", "Instruments matched (Hungarian on mean box-centre distance):", *maps]
    return "\n".join(out) + "\n"
