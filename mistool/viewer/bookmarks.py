"""Bookmarks in the viewer: add one at the current frame with a short text, list them,
jump to one, delete one; shown as marks under the timeline's frame slider.

Stored in the sequence's ``annotations.json`` (or the ``--annotations`` file) through
:mod:`mistool.annotations` (atomic writes, never the masks). All browsers share the list,
as they share the timeline. Without a file (a live session) bookmarks stay in memory.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any, Protocol

import viser

from mistool.annotations import KINDS, Bookmark, load_annotations, save_annotations
from mistool.errors import MistoolError

#: Characters of a bookmark's text shown under the slider.
MARK_LABEL_CHARS = 14
_NONE = "(no bookmarks)"


class TimelineLike(Protocol):
    """What the panel needs of the timeline."""

    slider: Any
    fps: float

    @property
    def frame(self) -> int:
        """The current frame."""
        ...

    def seek(self, frame: int) -> None:
        """Go to a frame."""
        ...


def slider_marks(marks: list[Bookmark]) -> tuple[Any, ...] | None:
    """viser slider marks (value, short label) for the bookmarks; None without any."""
    from viser._gui_api import _build_slider_marks  # viser's own normaliser (1.1.1)

    if not marks:
        return None
    return _build_slider_marks(tuple((float(b.frame), b.text[:MARK_LABEL_CHARS]) for b in marks))


def option_label(k: int, b: Bookmark, fps: float) -> str:
    """One line of the bookmark list."""
    return f"#{k} {b.frame / fps:.1f} s ({b.frame}) {b.kind}: {b.text}"


class BookmarkPanel:
    """The GUI folder "Bookmarks" of the viewer."""

    def __init__(
        self,
        server: viser.ViserServer,
        timeline: TimelineLike,
        path: Path | None,
        *,
        num_frames: int | None = None,
    ) -> None:
        """
        Args:
            server: the viser server.
            timeline: the shared timeline (its slider gets the marks).
            path: the annotations file (read now, written on each change), or None.
            num_frames: frames in the sequence (bookmarks beyond are still listed).
        """
        self.timeline = timeline
        self.path = path
        self.num_frames = num_frames
        self._lock = threading.Lock()
        self.error: str | None = None
        try:
            self.marks = load_annotations(path) if path is not None else []
        except MistoolError as exc:  # a bad file: shown, not fatal, and never overwritten
            self.marks, self.error = [], str(exc)
        gui = server.gui
        with gui.add_folder("Bookmarks", expand_by_default=False):
            self.text = gui.add_text("Text", initial_value="", hint="a short note")
            self.kind = gui.add_dropdown("Kind", KINDS, initial_value="event")
            self.add_button = gui.add_button("Add at current frame", icon=viser.Icon.BOOKMARK)
            self.list = gui.add_dropdown("List", (_NONE,), initial_value=_NONE)
            self.actions = gui.add_button_group("Bookmark", ("Jump", "Delete"))
            self.status = gui.add_markdown("")
        self.add_button.on_click(lambda _: self.add(self.timeline.frame, self.text.value))
        self.actions.on_click(lambda e: self._action(str(e.target.value)))
        self._refresh()

    # actions ----------------------------------------------------------------------
    def add(self, frame: int, text: str, kind: str | None = None) -> None:
        """Add a bookmark at ``frame`` (empty text: nothing happens)."""
        text = text.strip()
        if not text:
            self._say("Type a text first.")
            return
        with self._lock:
            try:
                mark = Bookmark(int(frame), text, kind or str(self.kind.value))
            except MistoolError as exc:
                self._say(str(exc))
                return
            self.marks = sorted([*self.marks, mark], key=lambda b: b.frame)
            self._save()
        self.text.value = ""  # type: ignore[misc]  # viser: assignable at runtime
        self._refresh(select=mark)

    def delete(self, index: int) -> None:
        """Delete the ``index``-th bookmark (frame order)."""
        with self._lock:
            if 0 <= index < len(self.marks):
                del self.marks[index]
                self._save()
        self._refresh()

    def jump(self, index: int) -> None:
        """Move the shared timeline to the ``index``-th bookmark."""
        if 0 <= index < len(self.marks):
            self.timeline.seek(self.marks[index].frame)

    def _selected(self) -> int:
        value = str(self.list.value)
        if not value.startswith("#"):
            return -1
        return int(value[1:].split(" ", 1)[0])

    def _action(self, which: str) -> None:
        k = self._selected()
        if which == "Jump":
            self.jump(k)
        elif which == "Delete":
            self.delete(k)

    # state ------------------------------------------------------------------------
    def _save(self) -> None:
        if self.path is None or self.error is not None:
            return
        try:
            save_annotations(self.path, self.marks)
        except MistoolError as exc:
            self.error = str(exc)

    def _say(self, text: str) -> None:
        self.status.content = text

    def _refresh(self, select: Bookmark | None = None) -> None:
        fps = self.timeline.fps
        options = tuple(option_label(k, b, fps) for k, b in enumerate(self.marks)) or (_NONE,)
        self.list.options = options
        chosen = options[0]
        if select is not None and select in self.marks:
            chosen = options[self.marks.index(select)]
        self.list.value = chosen  # type: ignore[misc]
        self.timeline.slider._marks = slider_marks(self.marks)
        where = f"`{self.path.name}`" if self.path is not None else "memory only (no file)"
        if self.error is not None:
            self._say(f"Bookmarks not saved: {self.error}")
        else:
            self._say(f"{len(self.marks)} bookmark(s), saved to {where}.")
