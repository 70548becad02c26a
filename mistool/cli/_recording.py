"""Opening a SOURCE for the teaching commands (skill, report, export-video): a motion
table (CSV) or a mask sequence (folder or mask video), tracked when it is a sequence."""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

from mistool.config import Config
from mistool.errors import InputPathError
from mistool.model import TrackTable


@dataclass
class Recording:
    """One recording: its motion table and where it came from."""

    name: str
    """A short name (the CSV's stem or the sequence folder's name)."""
    table: TrackTable
    """The motion table."""
    num_frames: int | None
    """Frames in the sequence (None when only a table was given)."""
    fps: float | None
    """Frame rate from mistool.toml (None for a table: taken from its time_s)."""
    sequence: Path | None
    """The mask sequence (folder or video), when there is one."""
    config: Config | None
    """The sequence's config."""


def is_table(source: str | Path) -> bool:
    """A SOURCE naming a CSV file is a motion table; anything else a sequence."""
    p = Path(source)
    return p.suffix.lower() == ".csv" and not p.is_dir()


def open_recording(
    source: str | Path, *, poses: str | Path | None = None, progress: bool = False
) -> Recording:
    """Read a motion table, or open a sequence and track it (``poses``: its table).

    Raises:
        MistoolError: bad path, masks, config or table (one line).
    """
    from mistool.export import read_csv

    if is_table(source):
        p = Path(source)
        if not p.is_file():
            raise InputPathError(f"{p}: no such file")
        return Recording(p.stem, read_csv(p), None, None, None, None)
    from mistool import api, sequence

    path, config = sequence.resolve(source)
    name = path.name if path.is_dir() else f"{path.parent.name}_{path.stem}"
    if poses is not None:
        table = read_csv(poses)
        seq = sequence.open_sequence(path, config)
        return Recording(name, table, seq.num_frames, config.fps, path, config)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", api.MistoolWarning)
        result = api.run(path, config, progress=progress and sys.stderr.isatty())
    return Recording(name, result.table, result.num_frames, result.config.fps, path, config)


def unique_names(recordings: list[Recording]) -> None:
    """Make the recordings' names distinct (a suffix #2, #3 ... on repeats)."""
    seen: dict[str, int] = {}
    for r in recordings:
        k = seen.get(r.name, 0) + 1
        seen[r.name] = k
        if k > 1:
            r.name = f"{r.name}#{k}"
