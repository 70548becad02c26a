"""Two procedures side by side in one viewer (``mistool serve A/ B/``).

The second recording (B) is merged into the first one's (A) replay as more instruments:

- **own colour set**: B's instruments are named ``B:<name>`` after A's ``A:<name>``, so
  they take the next colours of the palette;
- **own scene region**: B's 3D positions (``start_*``, ``end_*``, ``trocar_*``) are
  shifted along the camera's x axis so that B's working region sits beside A's, with a
  gap of :data:`REGION_GAP_MM` (a translation: B's motion itself is unchanged);
- **one timeline, synchronised by time**: B's frame ``k`` is shown at A's frame
  ``round((k / fps_B + offset_s) * fps_A)`` (``--offset``: B starts that many seconds
  after A; negative: before);
- the 2D overlay and the endoscope frustum show A's masks, with both recordings' rotated
  boxes (B's in its colours, at its own pixel positions); the paper mode (pixel units)
  draws both at their own pixel positions, without the shift: compare in metric mode.

The skill metrics of both recordings are shown side by side in the panel
(:func:`add_metrics_panel`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import viser

from mistool.model import TrackTable
from mistool.skill import METRICS, skill

#: Gap between the two recordings' scene regions (mm).
REGION_GAP_MM = 30.0
#: Names given to the two recordings' instruments.
PREFIXES = ("A", "B")
_X_COLUMNS = ("start_x_mm", "end_x_mm", "trocar_x_mm")


def _x_range(table: TrackTable) -> tuple[float, float]:
    xs = np.concatenate([np.asarray(table[c], dtype=np.float64) for c in _X_COLUMNS[:2]])
    xs = xs[np.isfinite(xs)]
    if not len(xs):
        return 0.0, 0.0
    return float(np.percentile(xs, 1)), float(np.percentile(xs, 99))


def region_shift_mm(a: TrackTable, b: TrackTable) -> float:
    """How far B is moved along x so that its region starts :data:`REGION_GAP_MM` to the
    right of A's (1st-99th percentiles of the parts' ends)."""
    _, a_hi = _x_range(a)
    b_lo, _ = _x_range(b)
    return a_hi - b_lo + REGION_GAP_MM


def combine_tables(
    a: TrackTable,
    b: TrackTable,
    *,
    fps_a: float,
    fps_b: float,
    offset_s: float = 0.0,
    num_frames: int | None = None,
) -> tuple[TrackTable, float]:
    """One table holding both recordings on A's timeline (see the module docstring).

    Args:
        a, b: the two motion tables.
        fps_a, fps_b: their frame rates.
        offset_s: B starts this many seconds after A (negative: before).
        num_frames: A's frames; B's rows beyond are dropped (default: keep all).

    Returns:
        ``(table, shift_mm)``: the combined table and B's shift along x.
    """
    shift = region_shift_mm(a, b)
    ta = a.with_columns(instrument=[f"{PREFIXES[0]}:{n}" for n in a["instrument"]])
    frame_b = np.round((np.asarray(b["frame"]) / fps_b + offset_s) * fps_a).astype(np.int64)
    keep = frame_b >= 0
    if num_frames is not None:
        keep &= frame_b < num_frames
    cols: dict[str, object] = {c: b[c][keep] for c in b.columns}
    cols["frame"] = frame_b[keep]
    cols["time_s"] = frame_b[keep] / fps_a
    cols["instrument"] = [f"{PREFIXES[1]}:{n}" for n in b["instrument"][keep]]
    tb = TrackTable(cols)
    tb = tb.with_columns(
        **{c: np.asarray(tb[c], dtype=np.float64) + shift for c in _X_COLUMNS if c in tb}
    )
    return TrackTable.concat([ta, tb]).sorted(), shift


def metrics_markdown(
    recordings: Sequence[tuple[str, TrackTable, float, int | None]],
) -> str:
    """A markdown table of the skill metrics, one column per recording x instrument.

    Args:
        recordings: ``(name, table, fps, num_frames)`` per recording.
    """
    heads: list[str] = []
    cols: list[dict[str, float]] = []
    for name, table, fps, n in recordings:
        r = skill(table, recording=name, fps=fps, num_frames=n)
        for k, inst in enumerate(r["instrument"]):
            heads.append(f"{name}:{inst}")
            cols.append({m.name: float(r[m.name][k]) for m in METRICS})
    if not heads:
        return "_No instrument with a 3D pose._"

    def fmt(v: float) -> str:
        return "–" if not math.isfinite(v) else f"{v:.3g}"

    lines = ["| metric | " + " | ".join(heads) + " |", "|---" * (len(heads) + 1) + "|"]
    for m in METRICS:
        arrow = {"lower": " ↓", "higher": " ↑"}.get(m.better, "")
        unit = f" ({m.unit})" if m.unit else ""
        cells = " | ".join(fmt(c[m.name]) for c in cols)
        lines.append(f"| {m.label}{unit}{arrow} | {cells} |")
    lines.append("")
    lines.append("↓ lower is better, ↑ higher is better (docs/teaching.md).")
    return "\n".join(lines)


def add_metrics_panel(
    server: viser.ViserServer,
    recordings: Sequence[tuple[str, TrackTable, float, int | None]],
    *,
    names: tuple[str, str] = PREFIXES,
    offset_s: float = 0.0,
    shift_mm: float = 0.0,
) -> viser.GuiMarkdownHandle:
    """A "Skill metrics" folder with both recordings' metrics side by side (columns
    named as the instruments in the scene: ``A:<name>``, ``B:<name>``)."""
    with server.gui.add_folder("Skill metrics", expand_by_default=False):
        server.gui.add_markdown(
            f"**{PREFIXES[0]}** = {names[0]}, **{PREFIXES[1]}** = {names[1]} "
            f"(starts {offset_s:+g} s after A; drawn {shift_mm:.0f} mm to the right)."
        )
        return server.gui.add_markdown(metrics_markdown(recordings))
