"""The instruments' part names (nothing imported: the command line reads them while it
builds its parser, before it starts the workers' fork server and imports numpy)."""

from __future__ import annotations

#: Instrument parts, proximal to distal. ``wrist`` exists only where the labels have one.
PARTS: tuple[str, ...] = ("shaft", "wrist", "clasper")
