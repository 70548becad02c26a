"""The replay viewer (the only part of mistool that imports viser).

``mistool serve`` and ``mistool export-html`` are thin layers over this package:
:func:`load_sequence` tracks a sequence (or loads its motion table) and raises every input
problem before a server starts; :class:`ReplayViewer` serves the replay; and
:func:`export_html` writes a standalone offline HTML replay.
"""

from mistool.viewer.app import LoadedSequence, ReplayViewer, load_sequence
from mistool.viewer.recording import export_html
from mistool.viewer.replay import Replay, build_replay

__all__ = ["LoadedSequence", "Replay", "ReplayViewer", "build_replay", "export_html",
           "load_sequence"]
