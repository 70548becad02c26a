"""A teacher's report: one self-contained, offline HTML file (``mistool report``).

Per recording: the skill metrics per instrument (:mod:`mistool.skill`), the bookmarks,
and inline SVG plots (no script, no network, no external file): speed and depth over
time with the bookmarks marked, and the tip path in three projections (image x-y, top
x-z, side z-y; camera frame, mm). With two recordings, a side-by-side comparison first:
for each metric with a direction (lower or higher is better, stated per metric), which
recording is better and by how much.
"""

from __future__ import annotations

import datetime
import html
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mistool.annotations import Bookmark
from mistool.export import atomic_write
from mistool.model import TrackTable
from mistool.skill import (
    METRICS,
    SMOOTHING_S,
    MetricInfo,
    point_tracks,
    prepare,
    skill,
    speeds,
    table_fps,
)

#: One colour per instrument (RGB), in instrument name order; the viewer's palette.
PALETTE_RGB: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)
#: Metrics compared by their difference (fractions, ratios, log values) rather than in %.
ABSOLUTE_DIFF = frozenset({"idle_fraction", "ldlj", "economy_of_volume", "bimanual_dexterity"})
#: Most points drawn per plotted line (longer series are decimated).
MAX_PLOT_POINTS = 1500
_PLOT_W, _PLOT_H = 640, 190
_PROJ = 250
_MARGIN = (48, 12, 10, 30)  # left, right, top, bottom (px)


@dataclass
class ReportRecording:
    """One recording to report on."""

    name: str
    """Its name in titles."""
    table: TrackTable
    """Its motion table (needs the metric pose)."""
    num_frames: int | None = None
    """Frames in the recording (default: the table's last frame + 1)."""
    fps: float | None = None
    """Frame rate (default: from the table's ``time_s``)."""
    bookmarks: list[Bookmark] = field(default_factory=list)
    """Bookmarks to list and mark on the plots."""


def colour(k: int) -> str:
    """The CSS colour of the ``k``-th instrument."""
    r, g, b = PALETTE_RGB[k % len(PALETTE_RGB)]
    return f"#{r:02x}{g:02x}{b:02x}"


#: Metrics that are counts (shown without decimals).
COUNTS = frozenset({"movements"})


def _fmt(value: float, digits: int = 3, name: str = "") -> str:
    if value is None or not math.isfinite(value):
        return "–"
    if name in COUNTS:
        return f"{value:.0f}"
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    return f"{value:.{digits}g}" if abs(value) < 1 else f"{value:.{max(1, digits - 2)}f}"


def nice_ticks(lo: float, hi: float, count: int = 5) -> list[float]:
    """About ``count`` round tick values covering ``[lo, hi]``."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    raw = (hi - lo) / count
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    start = math.ceil(lo / step - 1e-9) * step
    return [start + k * step for k in range(int((hi - start) / step + 1e-9) + 1)]


def nice_floor(value: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above ``value`` (> 0)."""
    mag = 10 ** math.floor(math.log10(value))
    return max(m * mag for m in (1, 2, 5, 10) if m * mag <= value * (1 + 1e-9))


@dataclass
class Series:
    """One line of a plot."""

    x: np.ndarray
    """(N,) x values."""
    y: np.ndarray
    """(N,) y values; NaN breaks the line."""
    colour: str
    """CSS colour."""
    label: str
    """Legend text."""


def _decimate(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    step = max(1, int(math.ceil(len(x) / MAX_PLOT_POINTS)))
    return x[::step], y[::step]


def _path(px: np.ndarray, py: np.ndarray) -> str:
    parts, pen = [], False
    for a, b in zip(px, py, strict=True):
        if not (math.isfinite(a) and math.isfinite(b)):
            pen = False
            continue
        parts.append(f"{'L' if pen else 'M'}{a:.1f} {b:.1f}")
        pen = True
    return " ".join(parts)


def _range(values: list[np.ndarray]) -> tuple[float, float]:
    finite = [v[np.isfinite(v)] for v in values]
    finite = [v for v in finite if len(v)]
    if not finite:
        return 0.0, 1.0
    lo, hi = min(float(v.min()) for v in finite), max(float(v.max()) for v in finite)
    return (lo - 0.5, hi + 0.5) if hi - lo < 1e-9 else (lo, hi)


def svg_time_plot(
    series: Sequence[Series],
    *,
    xlabel: str,
    ylabel: str,
    marks: Sequence[tuple[float, str]] = (),
    x_range: tuple[float, float] | None = None,
    cursor: bool = False,
) -> str:
    """An inline SVG line plot with axes, ticks, and vertical marks (x, label).

    With ``cursor``, the SVG carries ``data-t0 data-t1`` (the x range) and ``data-px0
    data-px1`` (its pixels) and a ``line.cursor`` at x0 for a script to move."""
    w, h = _PLOT_W, _PLOT_H
    ml, mr, mt, mb = _MARGIN
    x0, x1 = x_range or _range([s.x for s in series])
    y0, y1 = _range([s.y for s in series])
    y0, y1 = min(y0, 0.0) if y0 >= 0 and y0 < 0.3 * y1 else y0, y1

    def sx(v: np.ndarray | float) -> np.ndarray | float:
        return ml + (np.asarray(v) - x0) / (x1 - x0) * (w - ml - mr)

    def sy(v: np.ndarray | float) -> np.ndarray | float:
        return mt + (y1 - np.asarray(v)) / (y1 - y0) * (h - mt - mb)

    data = (
        f' data-t0="{x0:g}" data-t1="{x1:g}" data-px0="{ml}" data-px1="{w - mr}"' if cursor else ""
    )
    out = [f'<svg class="plot" viewBox="0 0 {w} {h}" width="{w}" height="{h}"{data} role="img">']
    out.append(
        f'<rect x="{ml}" y="{mt}" width="{w - ml - mr}" height="{h - mt - mb}" class="frame"/>'
    )
    for t in nice_ticks(x0, x1):
        x = float(sx(t))
        out.append(f'<line x1="{x:.1f}" y1="{mt}" x2="{x:.1f}" y2="{h - mb}" class="grid"/>')
        out.append(f'<text x="{x:.1f}" y="{h - mb + 13}" class="tick" text-anchor="middle">')
        out.append(f"{t:g}</text>")
    for t in nice_ticks(y0, y1, 4):
        y = float(sy(t))
        out.append(f'<line x1="{ml}" y1="{y:.1f}" x2="{w - mr}" y2="{y:.1f}" class="grid"/>')
        out.append(f'<text x="{ml - 4}" y="{y + 4:.1f}" class="tick" text-anchor="end">')
        out.append(f"{t:g}</text>")
    for x, label in marks:
        if x0 <= x <= x1:
            px = float(sx(x))
            out.append(
                f'<line x1="{px:.1f}" y1="{mt}" x2="{px:.1f}" y2="{h - mb}" class="mark"/>'
                f'<text x="{px + 3:.1f}" y="{mt + 11}" class="marklabel">'
                f"{html.escape(label)}</text>"
            )
    for s in series:
        xs, ys = _decimate(s.x, s.y)
        d = _path(np.asarray(sx(xs)), np.asarray(sy(ys)))
        out.append(f'<path d="{d}" stroke="{s.colour}" class="line"><title>')
        out.append(f"{html.escape(s.label)}</title></path>")
    if cursor:
        out.append(f'<line class="cursor" x1="{ml}" y1="{mt}" x2="{ml}" y2="{h - mb}"/>')
    out.append(f'<text x="{(ml + w - mr) / 2}" y="{h - 2}" class="axis" text-anchor="middle">')
    out.append(f"{html.escape(xlabel)}</text>")
    out.append(
        f'<text x="11" y="{(mt + h - mb) / 2}" class="axis" text-anchor="middle" '
        f'transform="rotate(-90 11 {(mt + h - mb) / 2})">{html.escape(ylabel)}</text>'
    )
    out.append("</svg>")
    return "".join(out)


def svg_projection(series: Sequence[Series], *, title: str, flip_y: bool = False) -> str:
    """An inline SVG of paths in one plane at equal scale (mm), with a scale bar."""
    size, pad = _PROJ, 22
    x0, x1 = _range([s.x for s in series])
    y0, y1 = _range([s.y for s in series])
    scale = (size - 2 * pad) / max(x1 - x0, y1 - y0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    out = [f'<svg class="proj" viewBox="0 0 {size} {size}" width="{size}" height="{size}">']
    out.append(f'<rect x="1" y="1" width="{size - 2}" height="{size - 2}" class="frame"/>')
    for s in series:
        xs, ys = _decimate(s.x, s.y)
        px = size / 2 + (xs - cx) * scale
        py = size / 2 + (ys - cy) * scale * (1 if flip_y else -1)
        out.append(f'<path d="{_path(px, py)}" stroke="{s.colour}" class="line thin"/>')
        ok = np.flatnonzero(np.isfinite(px) & np.isfinite(py))
        if len(ok):  # the start of the path
            out.append(
                f'<circle cx="{px[ok[0]]:.1f}" cy="{py[ok[0]]:.1f}" r="3" fill="{s.colour}"/>'
            )
    bar = nice_floor((size - 2 * pad) / scale / 3)
    out.append(
        f'<line x1="{pad}" y1="{size - 8}" x2="{pad + bar * scale:.1f}" y2="{size - 8}" '
        f'class="scalebar"/><text x="{pad}" y="{size - 12}" class="tick">{bar:g} mm</text>'
    )
    out.append(f'<text x="{size / 2}" y="14" class="axis" text-anchor="middle">')
    out.append(f"{html.escape(title)}</text></svg>")
    return "".join(out)


def _metric_table(result: dict[str, np.ndarray]) -> str:
    names = [str(n) for n in result["instrument"]]
    head = "".join(
        f'<th><span class="swatch" style="background:{colour(k)}"></span>'
        f"instrument {html.escape(n)} ({html.escape(str(result['point'][k]))})</th>"
        for k, n in enumerate(names)
    )
    rows = []
    for m in METRICS:
        arrow = {"lower": "↓ lower is better", "higher": "↑ higher is better"}.get(m.better, "")
        cells = "".join(
            f"<td>{_fmt(float(result[m.name][k]), name=m.name)}</td>" for k in range(len(names))
        )
        unit = f" ({m.unit})" if m.unit else ""
        rows.append(
            f'<tr><th class="metric" title="{m.name}">{html.escape(m.label)}{unit}</th>'
            f'{cells}<td class="dir">{arrow}</td></tr>'
        )
    return (
        f'<table class="metrics"><thead><tr><th>metric</th>{head}<th>direction</th></tr>'
        f"</thead><tbody>{''.join(rows)}</tbody></table>"
    )


def verdict(info: MetricInfo, a: float, b: float, names: tuple[str, str]) -> str:
    """Which of two values is better and by how much, in words."""
    if not (math.isfinite(a) and math.isfinite(b)):
        return "–"
    if a == b:
        return "equal"
    if info.name in ABSOLUTE_DIFF or a == 0:
        size = f"by {abs(b - a):.3g}"
    else:
        size = f"by {abs(b - a) / abs(a) * 100:.0f}%"
    word = "lower" if b < a else "higher"
    if not info.better:
        return f"{names[1]} {word} {size} (no better direction)"
    winner = names[1] if (b < a) == (info.better == "lower") else names[0]
    return f"<b>{html.escape(winner)}</b> better: {html.escape(names[1])} {word} {size}"


def _comparison(recs: Sequence[ReportRecording], results: list[dict[str, np.ndarray]]) -> str:
    ra, rb = results
    na, nb = recs[0].name, recs[1].name
    pairs = list(zip(range(len(ra["instrument"])), range(len(rb["instrument"])), strict=False))
    if not pairs:
        return "<p>No instrument to compare.</p>"
    blocks = []
    for i, j in pairs:
        ia, ib = str(ra["instrument"][i]), str(rb["instrument"][j])
        rows = []
        for m in METRICS:
            direction = {"lower": "lower", "higher": "higher"}.get(m.better, "–")
            rows.append(
                f"<tr><th class='metric'>{html.escape(m.label)}"
                f"{f' ({m.unit})' if m.unit else ''}</th><td>{direction}</td>"
                f"<td>{_fmt(float(ra[m.name][i]), name=m.name)}</td>"
                f"<td>{_fmt(float(rb[m.name][j]), name=m.name)}</td>"
                f"<td>{verdict(m, float(ra[m.name][i]), float(rb[m.name][j]), (na, nb))}</td>"
                "</tr>"
            )
        blocks.append(
            f"<h3>instrument {html.escape(ia)} of {html.escape(na)} vs instrument "
            f"{html.escape(ib)} of {html.escape(nb)}</h3>"
            f'<table class="compare"><thead><tr><th>metric</th><th>better</th>'
            f"<th>{html.escape(na)}</th><th>{html.escape(nb)}</th><th>verdict</th></tr>"
            f"</thead><tbody>{''.join(rows)}</tbody></table>"
        )
    return "".join(blocks)


def _bookmark_list(marks: list[Bookmark], fps: float) -> str:
    if not marks:
        return '<p class="note">No bookmarks.</p>'
    items = "".join(
        f"<li><b>{b.time_s(fps):.1f} s</b> (frame {b.frame}) <i>{b.kind}</i>: "
        f"{html.escape(b.text)}</li>"
        for b in marks
    )
    return f'<ul class="bookmarks">{items}</ul>'


def tip_plots(
    table: TrackTable,
    *,
    num_frames: int | None = None,
    fps: float | None = None,
    bookmarks: Sequence[Bookmark] = (),
    smoothing_s: float = SMOOTHING_S,
    cursor: bool = False,
) -> tuple[list[Series], str]:
    """The speed and depth plots of each instrument's tip (``(speed series, SVG text)``),
    as in the report; ``cursor`` as :func:`svg_time_plot`."""
    rate = fps or table_fps(table)
    tracks = point_tracks(table, num_frames)
    speed: list[Series] = []
    depth: list[Series] = []
    for k, tr in enumerate(tracks):
        xyz = prepare(tr, rate, smoothing_s)
        t = np.arange(len(xyz)) / rate
        label = f"instrument {tr.instrument} ({tr.point})"
        speed.append(Series(t, speeds(xyz, rate), colour(k), label))
        depth.append(Series(t, xyz[:, 2], colour(k), label))
    if not tracks:
        return speed, ""
    n = len(tracks[0].seen)
    marks = [(b.time_s(rate), b.text) for b in bookmarks]
    xr = (0.0, max(n / rate, 1e-3))
    text = svg_time_plot(
        speed, xlabel="time (s)", ylabel="tip speed (mm/s)", marks=marks, x_range=xr, cursor=cursor
    ) + svg_time_plot(
        depth, xlabel="time (s)", ylabel="tip depth z (mm)", marks=marks, x_range=xr, cursor=cursor
    )
    return speed, text


def _recording_section(
    rec: ReportRecording, result: dict[str, np.ndarray], smoothing_s: float
) -> str:
    fps = rec.fps or table_fps(rec.table)
    tracks = point_tracks(rec.table, rec.num_frames)
    speed: list[Series] = []
    depth: list[Series] = []
    proj: dict[str, list[Series]] = {"xy": [], "xz": [], "zy": []}
    for k, tr in enumerate(tracks):
        xyz = prepare(tr, fps, smoothing_s)
        t = np.arange(len(xyz)) / fps
        label = f"instrument {tr.instrument} ({tr.point})"
        speed.append(Series(t, speeds(xyz, fps), colour(k), label))
        depth.append(Series(t, xyz[:, 2], colour(k), label))
        proj["xy"].append(Series(xyz[:, 0], xyz[:, 1], colour(k), label))
        proj["xz"].append(Series(xyz[:, 0], xyz[:, 2], colour(k), label))
        proj["zy"].append(Series(xyz[:, 2], xyz[:, 1], colour(k), label))
    n = len(tracks[0].seen) if tracks else 0
    marks = [(b.time_s(fps), b.text) for b in rec.bookmarks]
    xr = (0.0, max(n / fps, 1e-3))
    legend = "".join(
        f'<span class="legend"><span class="swatch" style="background:{s.colour}"></span>'
        f"{html.escape(s.label)}</span>"
        for s in speed
    )
    plots = ""
    if tracks:
        plots = (
            f'<div class="legendrow">{legend}</div>'
            f"<h3>Speed of the tip over time</h3>"
            + svg_time_plot(
                speed, xlabel="time (s)", ylabel="speed (mm/s)", marks=marks, x_range=xr
            )
            + "<h3>Depth of the tip (distance from the camera plane, z) over time</h3>"
            + svg_time_plot(depth, xlabel="time (s)", ylabel="z (mm)", marks=marks, x_range=xr)
            + "<h3>Tip path in three projections (camera frame, mm; a dot marks the "
            "start)</h3>"
            + '<div class="projs">'
            + svg_projection(proj["xy"], title="front (image): x →, y ↓", flip_y=True)
            + svg_projection(proj["xz"], title="top: x →, depth z ↑")
            + svg_projection(proj["zy"], title="side: depth z →, y ↓", flip_y=True)
            + "</div>"
        )
    return (
        f'<section class="recording"><h2>{html.escape(rec.name)}</h2>'
        f'<p class="note">{n} frames at {fps:g} fps ({n / fps:.1f} s), '
        f"{len(tracks)} instrument(s).</p>"
        f"{_metric_table(result) if tracks else '<p>No instrument with a 3D pose.</p>'}"
        f"<h3>Bookmarks</h3>{_bookmark_list(rec.bookmarks, fps)}{plots}</section>"
    )


_CSS = """
body{font:14px/1.4 system-ui,-apple-system,'Segoe UI',sans-serif;margin:24px auto;
max-width:980px;color:#222;padding:0 16px}
h1{font-size:22px;margin-bottom:4px}h2{font-size:19px;border-bottom:1px solid #ccc;
padding-bottom:3px;margin-top:32px}h3{font-size:14px;margin:18px 0 6px}
table{border-collapse:collapse;margin:6px 0}td,th{border:1px solid #ddd;padding:3px 8px;
text-align:right}th.metric,thead th{text-align:left;background:#f6f6f6}td.dir{color:#666;
text-align:left;font-size:12px}.note{color:#555}.swatch{display:inline-block;width:10px;
height:10px;border-radius:2px;margin-right:5px}.legend{margin-right:16px}
svg text{font:11px sans-serif;fill:#333}.frame{fill:none;stroke:#999}.grid{stroke:#eee}
.line{fill:none;stroke-width:1.5}.thin{stroke-width:1}.mark{stroke:#c33;
stroke-dasharray:3 3}.marklabel{fill:#c33}.scalebar{stroke:#333;stroke-width:2}
.projs{display:flex;gap:10px;flex-wrap:wrap}.bookmarks{margin:4px 0}
"""


def build_report(
    recordings: Sequence[ReportRecording],
    *,
    title: str = "mistool report",
    smoothing_s: float = SMOOTHING_S,
) -> str:
    """The report's HTML text (self-contained: inline CSS and SVG, no script)."""
    results = [
        skill(
            r.table,
            recording=r.name,
            num_frames=r.num_frames,
            fps=r.fps,
            smoothing_s=smoothing_s,
        )
        for r in recordings
    ]
    stamp = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
    names = ", ".join(html.escape(r.name) for r in recordings)
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width, initial-scale=1'>",
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{html.escape(title)}</h1><p class='note'>Recordings: {names}. Made by mistool "
        f"on {stamp}. Metrics from each instrument's tip (the shaft joint when the "
        "clasper has no 3D estimate) in millimetres, camera frame; positions as tracked "
        f"(mistool's Kalman smoothing) then a {smoothing_s:g}-s Gaussian low-pass; "
        "definitions and sources in mistool's docs/teaching.md.</p>",
    ]
    if len(recordings) == 2:
        parts.append(
            "<h2>Comparison</h2><p class='note'>For each metric: which recording is "
            "better in the direction stated (lower or higher is better), and by how much "
            "(in % of the first recording's value, or as a difference for fractions and "
            "ratios). Instruments are paired in name order.</p>"
        )
        parts.append(_comparison(recordings, results))
    for rec, res in zip(recordings, results, strict=True):
        parts.append(_recording_section(rec, res, smoothing_s))
    parts.append("</body></html>\n")
    return "".join(parts)


def write_report(path: str | Path, recordings: Sequence[ReportRecording], **kwargs: object) -> Path:
    """Build the report and write it atomically to ``path``."""
    text = build_report(recordings, **kwargs)  # type: ignore[arg-type]
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(text)
    return Path(path)
