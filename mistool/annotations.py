"""Bookmarks at key moments of a recording, kept in a small JSON sidecar file.

The file (``annotations.json`` inside a sequence folder, beside ``mistool.toml``;
``<video stem>.annotations.json`` beside a mask video; or any ``.json`` path given with
``--annotations``)::

    {
      "mistool_annotations": 1,
      "bookmarks": [
        {"frame": 120, "text": "needle grasped", "kind": "event"},
        {"frame": 300, "text": "suturing", "kind": "phase"}
      ]
    }

- ``mistool_annotations``: the schema version (1).
- ``bookmarks``: a list, kept sorted by frame; each has ``frame`` (0-based frame index,
  int >= 0), ``text`` (at most :data:`MAX_TEXT` characters, one line) and ``kind``, one of
  :data:`KINDS` (default ``"comment"``). Unknown keys are kept when the file is read and
  written back, so other tools may add their own.

Writing is atomic (a temporary file beside the target, then a rename), only ever to a
``.json`` path that is absent or a regular file: the masks are never touched.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mistool.errors import ConfigError, InputPathError
from mistool.export import atomic_write

#: The schema version written and understood.
SCHEMA_VERSION = 1
#: What a bookmark marks.
KINDS: tuple[str, ...] = ("phase", "event", "comment")
#: Longest bookmark text (characters).
MAX_TEXT = 200
#: The sidecar's name inside a sequence folder.
FILE_NAME = "annotations.json"


@dataclass(frozen=True)
class Bookmark:
    """One moment of a recording."""

    frame: int
    """0-based frame index."""
    text: str
    """A short one-line text."""
    kind: str = "comment"
    """One of :data:`KINDS`."""
    extra: dict[str, Any] = field(default_factory=dict, compare=False)
    """Keys other tools wrote (kept as they are)."""

    def __post_init__(self) -> None:
        check_bookmark(self.frame, self.text, self.kind)

    def time_s(self, fps: float) -> float:
        """The bookmark's time at ``fps`` (s)."""
        return self.frame / fps

    def to_json(self) -> dict[str, Any]:
        """The JSON object of this bookmark."""
        return {**self.extra, "frame": self.frame, "text": self.text, "kind": self.kind}


def check_bookmark(frame: Any, text: Any, kind: Any, where: str = "bookmark") -> None:
    """Raise :class:`ConfigError` naming ``where`` unless the fields are valid."""
    if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
        raise ConfigError(f"{where}: frame must be an integer >= 0, got {frame!r}")
    if not isinstance(text, str) or not text.strip():
        raise ConfigError(f"{where}: text must be a non-empty string, got {text!r}")
    if len(text) > MAX_TEXT or "\n" in text or "\r" in text:
        raise ConfigError(f"{where}: text must be one line of at most {MAX_TEXT} characters")
    if kind not in KINDS:
        raise ConfigError(f"{where}: kind must be one of {', '.join(KINDS)}, got {kind!r}")


def default_path(sequence: str | Path) -> Path:
    """Where a sequence's bookmarks live: ``annotations.json`` in its folder, or
    ``<stem>.annotations.json`` beside a mask video."""
    p = Path(sequence)
    return p / FILE_NAME if p.is_dir() else p.with_name(f"{p.stem}.{FILE_NAME}")


def load_annotations(path: str | Path) -> list[Bookmark]:
    """The bookmarks of a sidecar file, sorted by frame; ``[]`` when it does not exist.

    Raises:
        InputPathError: the path is a folder or unreadable.
        ConfigError: not valid JSON or not the documented schema (says where).
    """
    p = Path(path)
    if not p.exists():
        return []
    if not p.is_file():
        raise InputPathError(f"{p}: not a regular file; expected an annotations .json file")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputPathError(f"{p}: cannot read: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{p}: not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not isinstance(data.get("bookmarks", []), list):
        raise ConfigError(f"{p}: expected an object with a 'bookmarks' list")
    version = data.get("mistool_annotations", SCHEMA_VERSION)
    if version != SCHEMA_VERSION:
        raise ConfigError(
            f"{p}: mistool_annotations version {version!r}; this mistool reads {SCHEMA_VERSION}"
        )
    out = []
    for k, item in enumerate(data.get("bookmarks", [])):
        where = f"{p}: bookmarks[{k}]"
        if not isinstance(item, dict):
            raise ConfigError(f"{where}: expected an object with frame and text")
        frame, text, kind = item.get("frame"), item.get("text"), item.get("kind", "comment")
        check_bookmark(frame, text, kind, where)
        assert isinstance(frame, int) and isinstance(text, str)  # checked just above
        extra = {key: v for key, v in item.items() if key not in ("frame", "text", "kind")}
        out.append(Bookmark(frame, text, kind, extra))
    return sorted(out, key=lambda b: b.frame)


def save_annotations(path: str | Path, bookmarks: Iterable[Bookmark]) -> Path:
    """Write the bookmarks (sorted by frame) atomically to a ``.json`` path.

    Raises:
        InputPathError: the path does not end in ``.json``, or exists and is not a
            regular file (a folder, a device, a link to one), or its folder is missing.
    """
    p = Path(path)
    if p.suffix.lower() != ".json":
        raise InputPathError(f"{p}: annotations are written only to a .json file")
    if p.exists() and (p.is_symlink() or not p.is_file()):
        raise InputPathError(f"{p}: exists and is not a regular file; not replaced")
    items = sorted(bookmarks, key=lambda b: b.frame)
    data = {"mistool_annotations": SCHEMA_VERSION, "bookmarks": [b.to_json() for b in items]}
    with atomic_write(p, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=2, ensure_ascii=False)
        f.write("\n")
    return p


def add_bookmark(path: str | Path, frame: int, text: str, kind: str = "comment") -> list[Bookmark]:
    """Add one bookmark to the sidecar file (created if absent); returns them all."""
    items = load_annotations(path) + [Bookmark(frame, text.strip(), kind)]
    save_annotations(path, items)
    return sorted(items, key=lambda b: b.frame)


def remove_bookmark(path: str | Path, index: int) -> list[Bookmark]:
    """Remove the ``index``-th bookmark (in frame order); returns the rest."""
    items = load_annotations(path)
    if not 0 <= index < len(items):
        raise ConfigError(f"{path}: no bookmark #{index} (there are {len(items)})")
    del items[index]
    save_annotations(path, items)
    return items


def caption_at(bookmarks: list[Bookmark], frame: int, hold_frames: int) -> Bookmark | None:
    """The bookmark to caption ``frame`` with: the latest at or before it, if it is at
    most ``hold_frames`` old (phases hold until the next bookmark)."""
    best = None
    for b in bookmarks:
        if b.frame <= frame:
            best = b
        else:
            break
    if best is None:
        return None
    return best if best.kind == "phase" or frame - best.frame <= hold_frames else None
