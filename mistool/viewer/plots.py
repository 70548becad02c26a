"""Plots of x/y/z and roll/pitch/yaw over time for one instrument part, with a cursor at
the current frame (viser's uPlot charts).

Long sequences are downsampled to at most :data:`MAX_PLOT_POINTS` points per series
(every k-th frame). The cursor is a vertical line: two points at the current time are
inserted into the x data each frame (uPlot's aligned mode cannot draw a vertical segment
otherwise). Y ranges are fixed from the whole series so the axes do not jump.
"""

from __future__ import annotations

import numpy as np
import viser
import viser.uplot as uplot

from mistool.viewer.replay import Replay

#: Most points per plotted series (about one per pixel of the panel; the whole series is
#: sent with each cursor move).
MAX_PLOT_POINTS = 300
#: Placeholder in the instrument menu before any instrument has been seen.
NO_INSTRUMENT = "(none yet)"
_AXIS_COLOURS = ("#d62728", "#2ca02c", "#1f77b4")
_LABELS = {
    "metric/position": (("x (mm)", "y (mm)", "z (mm)"), "Position, camera frame (mm)"),
    "metric/rotation": (("roll", "pitch", "yaw"), "Rotation (deg)"),
    "paper/position": (("x (px)", "y (px)", "z (Eq. 5)"), "Paper position"),
    "paper/rotation": (("e_r", "e_p", "e_y"), "Paper angles (deg)"),
}


def _range(values: np.ndarray) -> tuple[float, float]:
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return -1.0, 1.0
    lo, hi = float(finite.min()), float(finite.max())
    pad = 0.05 * (hi - lo) if hi > lo else max(1.0, abs(hi) * 0.05)
    return lo - pad, hi + pad


class PlotPanel:
    """Two uPlot charts (position, rotation) for a chosen instrument and part."""

    def __init__(self, gui: viser.GuiApi, replay: Replay, mode: str) -> None:
        self.replay = replay
        self.mode = mode
        self._frames_sampled = -1
        self._resample()
        self.instrument = gui.add_dropdown(
            "Instrument", self._instrument_options(), initial_value=self._instrument_options()[0]
        )
        self.part = gui.add_dropdown("Part", replay.parts, initial_value=replay.parts[-1])
        self._frame = 0
        self._cache: dict[tuple[object, ...], tuple[np.ndarray, dict[str, tuple]]] = {}
        self.revision = replay.revision
        """The replay revision the charts' ranges were last set from."""
        self.charts: dict[str, viser.GuiUplotHandle] = {}
        for kind in ("position", "rotation"):
            data, ranges = self._data(kind, 0)
            self.charts[kind] = gui.add_uplot(
                data=data,
                series=self._series(kind),
                scales=self._scales(kind, ranges),
                title=_LABELS[f"{mode}/{kind}"][1],
                aspect=1.6,
                axes=self._axes(kind),
                legend={"show": True, "live": False},
            )
        self.instrument.on_update(lambda _: self.refresh())
        self.part.on_update(lambda _: self.refresh())

    def _resample(self) -> None:
        """Frames plotted: every k-th of the timeline, at most MAX_PLOT_POINTS."""
        n = self.replay.num_frames
        if n == self._frames_sampled:
            return
        self._frames_sampled = n
        self._stride = max(1, int(np.ceil(n / MAX_PLOT_POINTS)))
        self._idx = np.arange(0, n, self._stride)
        self._t = self._idx / self.replay.fps

    def _instrument_options(self) -> tuple[str, ...]:
        return self.replay.instruments or (NO_INSTRUMENT,)

    def grow(self) -> None:
        """Follow a replay that has grown: new instruments, longer timeline, new values
        (the charts' ranges are set again)."""
        options = self._instrument_options()
        if tuple(self.instrument.options) != options:
            current = self.instrument.value
            self.instrument.options = options
            if current not in options:
                self.instrument.value = options[0]  # type: ignore[misc]  # viser's stub
        self._resample()
        self.refresh()

    def _series(self, kind: str) -> tuple[uplot.Series, ...]:
        labels = _LABELS[f"{self.mode}/{kind}"][0]
        out: list[uplot.Series] = [{"label": "t (s)"}]
        for j in range(3):
            s: uplot.Series = {"label": labels[j], "stroke": _AXIS_COLOURS[j], "width": 1.5}
            if self.mode == "paper" and kind == "position" and j == 2:
                s["scale"] = "z"
            out.append(s)
        out.append(
            {
                "label": "frame",
                "stroke": "#444444",
                "width": 1.0,
                "dash": (4.0, 3.0),
                "scale": "y",
                "points": {"show": False},
            }
        )
        return tuple(out)

    def _axes(self, kind: str) -> tuple[uplot.Axis, ...]:
        axes: list[uplot.Axis] = [{"scale": "x"}, {"scale": "y"}]
        if self.mode == "paper" and kind == "position":
            axes.append({"scale": "z", "side": 1, "grid": {"show": False}})
        return tuple(axes)

    def _selected(self, kind: str) -> np.ndarray:
        """(F, 3) values of the selected instrument part."""
        replay = self.replay
        series = replay.series[f"{self.mode}/{kind}"]
        if self.instrument.value not in replay.instruments:
            return np.full((series.shape[0], 3), np.nan)
        i = replay.instruments.index(self.instrument.value)
        p = replay.parts.index(self.part.value)
        return series[:, i, p]

    def _values(self, kind: str) -> tuple[np.ndarray, dict[str, tuple]]:
        """Downsampled (M, 3) values of the selection and their y ranges (cached)."""
        key = (self.mode, kind, self.instrument.value, self.part.value, self.replay.revision)
        hit = self._cache.get(key)
        if hit is None:
            values = np.ascontiguousarray(self._selected(kind)[self._idx])
            split = self.mode == "paper" and kind == "position"
            y = _range(values[:, :2] if split else values)
            hit = values, {"y": y, "z": _range(values[:, 2]) if split else y}
            if len(self._cache) > 16:
                self._cache.clear()
            self._cache[key] = hit
        return hit

    def _data(self, kind: str, frame: int) -> tuple[tuple[np.ndarray, ...], dict[str, tuple]]:
        values, ranges = self._values(kind)
        y_lo, y_hi = ranges["y"]
        t_now = frame / self.replay.fps
        j = int(np.searchsorted(self._t, t_now))
        x = np.concatenate([self._t[:j], [t_now, t_now], self._t[j:]])
        selected = self._selected(kind)
        now = selected[min(max(frame, 0), len(selected) - 1)]
        cols = []
        for c in range(3):
            v = values[:, c]
            cols.append(np.concatenate([v[:j], [now[c], now[c]], v[j:]]))
        cursor = np.full(len(x), np.nan)
        cursor[j], cursor[j + 1] = y_lo, y_hi
        return (x, *cols, cursor), ranges

    def _scales(self, kind: str, ranges: dict[str, tuple]) -> dict[str, uplot.Scale]:
        t1 = max(self._t[-1] if len(self._t) else 0.0, 1.0 / self.replay.fps)
        return {
            "x": {"time": False, "auto": False, "range": (0.0, float(t1))},
            "y": {"auto": False, "range": ranges["y"]},
            "z": {"auto": False, "range": ranges["z"]},
        }

    def set_mode(self, mode: str) -> None:
        """Follow the scene's display mode."""
        self.mode = mode
        self.refresh()

    def refresh(self) -> None:
        """Rebuild both charts (instrument, part or mode changed)."""
        self.revision = self.replay.revision
        for kind, chart in self.charts.items():
            data, ranges = self._data(kind, self._frame)
            chart.series = self._series(kind)
            chart.scales = self._scales(kind, ranges)
            chart.axes = self._axes(kind)
            chart.title = _LABELS[f"{self.mode}/{kind}"][1]
            chart.data = data

    def set_frame(self, frame: int) -> None:
        """Move the cursor to ``frame``."""
        self._frame = frame
        for kind, chart in self.charts.items():
            chart.data = self._data(kind, frame)[0]
