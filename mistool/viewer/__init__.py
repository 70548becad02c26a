"""The replay viewer (the only part of mistool that imports viser, pinned to 1.1.1).

``mistool serve`` and ``mistool export-html`` are thin layers over this package:
:func:`load_sequence` tracks a sequence (or loads its motion table) and raises every input
problem before a server starts; :class:`ReplayViewer` serves the replay; and
:func:`export_html` writes a standalone offline HTML replay.

What the browser shows:

- **Scene** (:mod:`~mistool.viewer.scene`): per instrument, one cylinder per part
  (``/instruments/<name>/<part>``), linked (each part's base on the previous part's end);
  the endoscope as a frustum with the current overlay on its image plane; a ground grid;
  trails of each tip and joint over the last N frames. World frame z-up, endoscope at the
  origin looking along +y (:mod:`~mistool.viewer.replay` states the conventions).
- **Modes**: *metric* (millimetres from the metric pose; default when the camera is known)
  and *paper* (the paper's vpython scene in pixel units: length = box length, radius =
  half the box width, base at Algorithm 2's (x, y, z), axis turned by its roll, pitch and
  yaw, the clasper's base on the shaft's end).
- **Timeline** (:mod:`~mistool.viewer.timeline`): slider, play/pause, speed 0.25x-4x,
  step, loop, frame and time; keyboard: space or K play/pause, J / L step, Home first
  frame (viser command hotkeys; also in its command palette).
- **2D overlay** (:mod:`~mistool.viewer.overlay`): the mask coloured per instrument and
  part, blended over ``source`` (video file or RGB frame folder) when mistool.toml has one,
  rotated boxes drawn, opacity adjustable; JPEG; frames read lazily, overlays of the next
  frames prepared ahead by a worker during playback.
- **Cameras**: presets Endoscope (look through the endoscope: the overlay becomes that
  browser's background, padded to its window around the principal point with the
  matching field of view, so the cylinders sit on the mask whatever the window's shape
  and as it is resized; frustum and grid hidden while any browser looks through it),
  Side, Top, Reset; orbit controls otherwise (orbiting away leaves the Endoscope view).
- **Plots** (:mod:`~mistool.viewer.plots`): x/y/z and roll/pitch/yaw of a chosen part over
  time, downsampled, with a cursor at the current frame.
- One colour per instrument everywhere (:data:`~mistool.viewer.replay.PALETTE`; claspers
  and wrists lighter shades of it).

Several browsers share one timeline and the display options; each has its own camera
(see :mod:`~mistool.viewer.app`). viser's HDR environment map is off by default: in
software WebGL it delays the first render by about a second (``scripts/bench_viewer.py``);
``mistool serve --environment-map`` turns it on.
"""

from mistool.viewer.app import LoadedSequence, ReplayViewer, load_sequence
from mistool.viewer.live import Viewer
from mistool.viewer.recording import export_html
from mistool.viewer.replay import Replay, build_replay

__all__ = [
    "LoadedSequence",
    "Replay",
    "ReplayViewer",
    "Viewer",
    "build_replay",
    "export_html",
    "load_sequence",
]
