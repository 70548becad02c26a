"""What the standalone HTML replay adds around viser's recording player: a title, a frame
counter with units, the legend, plots of each tip's speed and depth with a cursor, and
no autoplay unless asked.

viser 1.1.1's exported page is its own web client playing the recording (play/pause, a
time box in seconds, a time slider at the bottom). This module injects, before
``</body>``, a fixed panel (static HTML and inline SVG, no network) and a small script
that reads the player's current time (the slider's hidden input, in seconds), shows
``frame k (0..N-1) · t s / T s · fps`` and moves the plots' cursors; when autoplay is off
it pauses the player as soon as it appears and puts it back to 0 s. If a later viser
changes its player's markup, the panel stays (title, legend, plots) and only the counter
and the cursors stop following.
"""

from __future__ import annotations

import html
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from mistool.annotations import Bookmark

if TYPE_CHECKING:  # pragma: no cover
    from mistool.viewer.app import LoadedSequence

#: How often the injected script reads the player's time (ms).
POLL_MS = 100


@dataclass(frozen=True)
class LegendEntry:
    """One instrument of the legend."""

    label: str
    """Text."""
    css_colour: str
    """CSS colour, e.g. ``#1f77b4``."""


_CSS = """
#mistool-panel{position:fixed;top:10px;left:50%;transform:translateX(-50%);z-index:500;
max-width:60vw;text-align:center;
font:13px/1.35 system-ui,sans-serif;color:#222;background:rgba(255,255,255,.88);
border-radius:6px;padding:8px 12px;box-shadow:0 1px 4px rgba(0,0,0,.25)}
#mistool-panel h1{font-size:16px;margin:0 0 4px}
#mistool-counter{font-variant-numeric:tabular-nums;font-weight:600}
#mistool-panel .sw{display:inline-block;width:10px;height:10px;border-radius:2px;
margin:0 4px 0 10px}
#mistool-plots{position:fixed;right:10px;bottom:56px;z-index:500;width:min(460px,44vw);
background:rgba(255,255,255,.9);border-radius:6px;padding:4px 8px;
box-shadow:0 1px 4px rgba(0,0,0,.25);font:12px system-ui,sans-serif}
#mistool-plots svg{width:100%;height:auto}
#mistool-plots svg text{font:11px sans-serif;fill:#333}
#mistool-plots .frame{fill:none;stroke:#999}#mistool-plots .grid{stroke:#eee}
#mistool-plots .line{fill:none;stroke-width:1.5}
#mistool-plots .cursor{stroke:#d00;stroke-width:1.5}
#mistool-plots .mark{stroke:#c33;stroke-dasharray:3 3}#mistool-plots .marklabel{fill:#c33}
"""

_SCRIPT = """
(function () {
  var cfg = %(config)s;
  var num = function (x) { return /^-?[0-9]+(\\.[0-9]+)?$/.test(x.value); };
  var player = function () {
    var hidden = Array.prototype.find.call(
      document.querySelectorAll('input[type=hidden]'), num);
    var box = Array.prototype.find.call(
      document.querySelectorAll('input[type=text]'), num);
    return {hidden: hidden, box: box};
  };
  var paused = cfg.autoplay;
  var pause = function (p) {
    var buttons = Array.prototype.filter.call(document.querySelectorAll('button'),
      function (b) { return b.compareDocumentPosition(p.box) & Node.DOCUMENT_POSITION_FOLLOWING; });
    if (!buttons.length) { return false; }
    buttons[buttons.length - 1].click();
    var set = Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, 'value').set;
    set.call(p.box, '0');
    p.box.dispatchEvent(new Event('input', {bubbles: true}));
    p.box.dispatchEvent(new KeyboardEvent('keydown', {key: 'Enter', bubbles: true}));
    p.box.blur();
    return true;
  };
  var counter = document.getElementById('mistool-counter');
  var cursors = document.querySelectorAll('#mistool-plots svg[data-t1]');
  var tick = function () {
    var p = player();
    if (p.hidden && p.box) {
      if (!paused) { paused = pause(p); }
      var t = parseFloat(p.hidden.value);
      var seconds = cfg.start_s + t;
      var frame = Math.min(cfg.last_frame, Math.round(seconds * cfg.fps));
      counter.textContent = 'frame ' + frame + ' (0\\u2013' + cfg.last_frame + ') \\u00b7 ' +
        seconds.toFixed(2) + ' s / ' + cfg.duration_s.toFixed(2) + ' s \\u00b7 ' + cfg.fps + ' fps';
      counter.setAttribute('data-frame', String(frame));
      Array.prototype.forEach.call(cursors, function (svg) {
        var t0 = +svg.dataset.t0, t1 = +svg.dataset.t1, a = +svg.dataset.px0, b = +svg.dataset.px1;
        var x = a + (Math.max(t0, Math.min(t1, seconds)) - t0) / (t1 - t0) * (b - a);
        var c = svg.querySelector('.cursor');
        if (c) { c.setAttribute('x1', x.toFixed(1)); c.setAttribute('x2', x.toFixed(1)); }
      });
    }
  };
  setInterval(tick, %(poll)d);
})();
"""


def decorate_replay_html(
    page: str,
    *,
    title: str,
    fps: float,
    num_frames: int,
    start_frame: int = 0,
    legend: Sequence[LegendEntry] = (),
    plots_html: str = "",
    note: str = "",
    autoplay: bool = False,
) -> str:
    """Inject the title, counter, legend, plots and the playback script into an exported
    viser page (returns the new page text).

    Args:
        page: the HTML of ``StateSerializer.as_html()``.
        title: shown at the top left and as the page title.
        fps: the sequence's frame rate (counter: frame = round(time x fps)).
        num_frames: frames of the sequence (counter shows 0..N-1).
        start_frame: the sequence frame the recording starts at.
        legend: one entry per instrument.
        plots_html: inline SVG plots; an ``<svg data-t0 data-t1 data-px0 data-px1>`` with a
            ``.cursor`` line gets its cursor moved to the current time.
        note: a line under the counter (e.g. units).
        autoplay: keep viser's autoplay; False pauses at 0 s once the player appears.
    """
    items = "".join(
        f'<span class="sw" style="background:{html.escape(e.css_colour)}"></span>'
        f"{html.escape(e.label)}"
        for e in legend
    )
    config = {
        "fps": float(fps),
        "last_frame": max(0, int(num_frames) - 1),
        "start_s": start_frame / fps,
        "duration_s": num_frames / fps,
        "autoplay": bool(autoplay),
    }
    panel = (
        f"<style>{_CSS}</style>"
        f'<div id="mistool-panel"><h1>{html.escape(title)}</h1>'
        f'<div id="mistool-counter" data-frame="0">frame 0 (0–{config["last_frame"]}) · '
        f"0.00 s / {config['duration_s']:.2f} s · {fps:g} fps</div>"
        f'<div class="note">{html.escape(note)}</div>'
        f'<div id="mistool-legend">{items}</div></div>'
    )
    if plots_html:
        # closed at first: the 3D view stays clear; one click opens the plots
        panel += (
            '<details id="mistool-plots"><summary>plots: tip speed and depth</summary>'
            f"{plots_html}</details>"
        )
    script = _SCRIPT % {"config": json.dumps(config), "poll": POLL_MS}
    injected = f"{panel}<script>{script}</script>"
    page = page.replace("<title>", f"<title>{html.escape(title)} – ", 1)
    end = page.rfind("</body>")
    if end < 0:
        return page + injected
    return page[:end] + injected + page[end:]


def decorate_export(
    page: str,
    sequence: LoadedSequence,
    *,
    title: str | None = None,
    start_frame: int = 0,
    mode: str = "metric",
    autoplay: bool = False,
    bookmarks: Sequence[Bookmark] = (),
) -> str:
    """:func:`decorate_replay_html` for a sequence exported by
    :func:`mistool.viewer.export_html`: its instruments' colours as the legend, its tips'
    speed and depth as plots (when the table has a metric pose), bookmarks on the plots."""
    from mistool.report import tip_plots

    replay = sequence.replay
    legend = [
        LegendEntry(f"instrument {name}", "#{:02x}{:02x}{:02x}".format(*map(int, rgb)))
        for name, rgb in zip(replay.instruments, replay.colours, strict=True)
    ]
    plots = ""
    if sequence.table is not None and sequence.table.num_rows:
        _, plots = tip_plots(
            sequence.table,
            num_frames=replay.num_frames,
            fps=replay.fps,
            bookmarks=bookmarks,
            cursor=True,
        )
    units = "millimetres, endoscope frame" if mode == "metric" else "the paper's pixel units"
    return decorate_replay_html(
        page,
        title=title or f"mistool replay: {sequence.name}",
        fps=replay.fps,
        num_frames=replay.num_frames,
        start_frame=start_frame,
        legend=legend,
        plots_html=plots,
        note=f"3D in {units}; shaft darker, clasper lighter",
        autoplay=autoplay,
    )
