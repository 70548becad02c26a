"""A whole dataset in one run: every sequence of a folder tracked into its own table.

A dataset is a folder holding sequence folders (label images) and/or mask videos. Each
sequence is tracked exactly as ``mistool track SEQ`` alone would (same config, same
table), into ``OUT/<name>_motion.<csv|npz|parquet>``; ``OUT/summary.csv`` lists every
sequence with its frames, instruments, seconds, status and error.

- Config: a ``mistool.toml`` at the dataset's root gives defaults; a sequence's own
  ``mistool.toml`` (in its folder; for a video at the root, the root's file is its own)
  overrides them key by key at the top level (a table such as ``[camera]`` or the
  ``[[instrument]]`` list replaces the root's as a whole). Relative paths in a merged
  config are relative to the sequence's own file.
- A broken sequence never stops the others: its one-line error is in the summary and is
  reported through ``on_error``; nothing is written for it; the run goes on.
- Resume: a sequence whose output exists and whose inputs (files, sizes, modification
  times, configs) and options are unchanged since it was written is skipped. The record
  of what was written is ``OUT/.mistool-dataset.json``, updated after each output is in
  place, and every file is written atomically, so an interrupted run leaves only
  complete outputs and re-running carries on where it stopped.
"""

from __future__ import annotations

import csv
import json
import os
import time
import traceback
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from mistool import __version__, api, parallel
from mistool.columnar import write_table
from mistool.config import CONFIG_NAME, Config, config_from_dict, load_config, tomllib
from mistool.errors import ConfigError, InputPathError, MistoolError
from mistool.export import atomic_write, format_value
from mistool.model import TrackTable
from mistool.sequence import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, list_frames, natural_key

#: The summary table's file name in the output folder.
SUMMARY_NAME = "summary.csv"
#: The record of the outputs written (for resuming), in the output folder.
STATE_NAME = ".mistool-dataset.json"
#: Suffix of each sequence's table: ``<name>_motion.<format>``.
OUTPUT_SUFFIX = "_motion"

STATUS_OK = "ok"
STATUS_SKIPPED = "up to date"
STATUS_ERROR = "error"


@dataclass(frozen=True)
class Entry:
    """One sequence of a dataset."""

    name: str
    """Its name (the folder's name, or the video's stem): the output is named after it."""
    path: Path
    """The sequence folder or mask video."""


@dataclass
class Outcome:
    """One row of the summary table."""

    sequence: str
    frames: int = 0
    instruments: int = 0
    seconds: float = 0.0
    status: str = STATUS_OK
    error: str = ""


@dataclass
class Options:
    """How every sequence is tracked (the ``mistool track`` options)."""

    metric: bool = True
    smoothing: str = "offline"
    overrides: dict[str, Any] = field(default_factory=dict)
    """Config overrides from the command line (``Config.with_overrides``)."""
    fmt: str = ".csv"
    """Output format: ``.csv``, ``.npz`` or ``.parquet``."""


def is_dataset(path: Path) -> bool:
    """Whether ``path`` is a dataset folder: no label images of its own, but sequence
    folders or mask videos inside."""
    if not path.is_dir():
        return False
    try:
        with os.scandir(path) as entries:  # no sort, no stat: a sequence of 100k frames
            for e in entries:  # answers at its first image
                if Path(e.name).suffix.lower() in IMAGE_EXTENSIONS and not e.is_dir():
                    return False
    except OSError as exc:
        raise InputPathError(f"{path}: cannot list folder: {exc.strerror or exc}") from None
    return bool(discover(path))


def discover(root: Path, exclude: Path | None = None) -> list[Entry]:
    """The dataset's sequences in natural order: every non-hidden sub-folder and every
    mask video directly in ``root`` (``exclude``: a folder to leave out, the output)."""
    skip = exclude.resolve() if exclude is not None else None
    found: list[Entry] = []
    try:
        entries = sorted(os.scandir(root), key=lambda e: natural_key(e.name))
    except OSError as exc:
        raise InputPathError(f"{root}: cannot list folder: {exc.strerror or exc}") from None
    names: set[str] = set()
    for e in entries:
        p = Path(e.path)
        if e.name.startswith(".") or (skip is not None and p.resolve() == skip):
            continue
        if e.is_dir():
            name = e.name
        elif e.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS:
            name = p.stem if p.stem not in names else p.name
        else:
            continue
        names.add(name)
        found.append(Entry(name, p))
    return found


def _toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None


def sequence_config(entry: Entry, root: Path) -> Config:
    """The entry's config: the root's ``mistool.toml`` overridden by its own."""
    root_toml = root / CONFIG_NAME
    own = entry.path / CONFIG_NAME if entry.path.is_dir() else root_toml
    if own == root_toml or not own.is_file():
        return load_config(root_toml) if root_toml.is_file() else Config()
    if not root_toml.is_file():
        return load_config(own)
    return config_from_dict({**_toml(root_toml), **_toml(own)}, own)


def _stamp(entry: Entry, root: Path) -> list[Any]:
    """What the output depends on in the file system: each input file's name, size and
    modification time (ns), and the configs'."""
    files = list_frames(entry.path) if entry.path.is_dir() else [entry.path]
    configs = [root / CONFIG_NAME]
    if entry.path.is_dir():
        configs.append(entry.path / CONFIG_NAME)
    out: list[Any] = []
    for f in [*files, *configs]:
        try:
            st = f.stat()
        except OSError:
            out.append([str(f), None])
            continue
        out.append([str(f), st.st_size, st.st_mtime_ns])
    return out


def _fingerprint(entry: Entry, root: Path, options: Options) -> dict[str, Any]:
    return {
        "version": __version__,
        "options": {
            "metric": options.metric,
            "smoothing": options.smoothing,
            "overrides": {k: repr(v) for k, v in sorted(options.overrides.items())},
        },
        "inputs": _stamp(entry, root),
    }


def output_path(out: Path, entry: Entry, fmt: str) -> Path:
    """``OUT/<name>_motion<fmt>``."""
    return out / f"{entry.name}{OUTPUT_SUFFIX}{fmt}"


class _State:
    """``OUT/.mistool-dataset.json``: per output file, the fingerprint it was made from."""

    def __init__(self, out: Path) -> None:
        self.path = out / STATE_NAME
        self.data: dict[str, Any] = {}
        try:
            loaded = json.loads(self.path.read_text(encoding="utf-8"))
            if isinstance(loaded, dict):
                self.data = loaded
        except (OSError, ValueError):
            self.data = {}

    def current(self, output: Path, fingerprint: Mapping[str, Any]) -> dict[str, Any] | None:
        rec = self.data.get(output.name)
        if output.is_file() and isinstance(rec, dict) and rec.get("fingerprint") == fingerprint:
            return rec
        return None

    def record(self, output: Path, fingerprint: Mapping[str, Any], outcome: Outcome) -> None:
        self.data[output.name] = {"fingerprint": fingerprint, "outcome": asdict(outcome)}
        with atomic_write(self.path, "w", encoding="utf-8") as f:
            json.dump(self.data, f)


def _track_one(
    entry: Entry,
    root: Path,
    options: Options,
    pool: parallel.FramePool | None,
    on_frames: Callable[[int], None] | None,
) -> tuple[TrackTable, Outcome]:
    config = sequence_config(entry, root).with_overrides(**options.overrides)
    result = api.run(
        entry.path,
        config,
        metric=options.metric,
        smoothing=options.smoothing,
        pool=pool,
        workers=1 if pool is None else None,
        on_frames=on_frames,
    )
    outcome = Outcome(
        entry.name, result.num_frames, len(result.instruments), round(result.seconds, 3)
    )
    return result.table, outcome


def track_dataset(
    root: str | Path,
    out: str | Path,
    options: Options | None = None,
    *,
    pool: parallel.FramePool | None = None,
    on_error: Callable[[str], None] | None = None,
    on_sequence: Callable[[Entry, int | None], None] | None = None,
    on_frames: Callable[[int], None] | None = None,
) -> list[Outcome]:
    """Track every sequence of a dataset into ``out`` (see the module docstring).

    Args:
        root: the dataset folder.
        out: the output folder (created if missing).
        options: tracking options and output format.
        pool: where the per-frame work runs (None: in this process).
        on_error: called with each broken sequence's one-line error.
        on_sequence: called before each sequence with its entry and frame count (None
            when unknown), for progress.
        on_frames: called with the number of frames just tracked, for progress.

    Returns:
        The summary, one :class:`Outcome` per sequence in order (also written to
        ``out/summary.csv``).

    Raises:
        InputPathError: ``root`` is not a folder with sequences, or ``out`` is not writable.
    """
    opts = options or Options()
    root_p, out_p = Path(root), Path(out)
    entries = discover(root_p, exclude=out_p)
    if not entries:
        raise InputPathError(f"{root_p}: no sequence folders or mask videos in this folder")
    try:
        out_p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputPathError(f"{out_p}: cannot create: {exc.strerror or exc}") from None
    state = _State(out_p)
    outcomes: list[Outcome] = []
    for entry in entries:
        target = output_path(out_p, entry, opts.fmt)
        fp = _fingerprint(entry, root_p, opts)
        rec = state.current(target, fp)
        n_frames = len(list_frames(entry.path)) if entry.path.is_dir() else None
        if on_sequence is not None:
            on_sequence(entry, n_frames)
        if rec is not None:
            outcome = Outcome(**{**rec["outcome"], "status": STATUS_SKIPPED})
            if on_frames is not None and n_frames:
                on_frames(n_frames)
            outcomes.append(outcome)
            continue
        start = time.perf_counter()
        try:
            table, outcome = _track_one(entry, root_p, opts, pool, on_frames)
            write_table(table, target)
        except MistoolError as exc:
            outcome = _failed(entry, start, str(exc), on_error)
        except Exception as exc:  # a bug: keep its traceback, but finish the others
            detail = "".join(traceback.format_exception_only(type(exc), exc)).strip()
            outcome = _failed(entry, start, f"internal error (a bug): {detail}", on_error)
            if on_error is not None:
                on_error(traceback.format_exc().rstrip())
        else:
            state.record(target, fp, outcome)
        outcomes.append(outcome)
    write_summary(outcomes, out_p / SUMMARY_NAME)
    return outcomes


def _failed(
    entry: Entry, start: float, message: str, on_error: Callable[[str], None] | None
) -> Outcome:
    line = " ".join(message.split())  # one line, whatever the message held
    if on_error is not None:
        on_error(line)
    return Outcome(
        entry.name,
        seconds=round(time.perf_counter() - start, 3),
        status=STATUS_ERROR,
        error=line,
    )


def write_summary(outcomes: list[Outcome], path: Path) -> None:
    """The summary table (one row per sequence: sequence, frames, instruments, seconds,
    status, error) as CSV, atomically."""
    names = [f.name for f in fields(Outcome)]
    with atomic_write(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(names)
        for o in outcomes:
            writer.writerow([format_value(getattr(o, n)) for n in names])


def failed(outcomes: list[Outcome]) -> list[Outcome]:
    """The outcomes of broken sequences."""
    return [o for o in outcomes if o.status == STATUS_ERROR]
