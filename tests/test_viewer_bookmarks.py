"""Bookmarks in the viewer, in real headless chromium: add at the current frame with a
text (written to annotations.json), listed, jumped to, deleted, marked under the slider."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import viser

from mistool.annotations import Bookmark, save_annotations
from mistool.viewer.bookmarks import BookmarkPanel

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run"]


class StubTimeline:
    """The part of the viewer's Timeline the panel uses: a slider, fps, frame, seek."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.fps = 25.0
        self.slider = server.gui.add_slider("Frame", min=0, max=99, step=1, initial_value=0)
        self.sought: list[int] = []

    @property
    def frame(self) -> int:
        return int(self.slider.value)

    def seek(self, frame: int) -> None:
        self.sought.append(frame)
        self.slider.value = frame


@pytest.fixture
def server() -> Iterator[viser.ViserServer]:
    s = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    yield s
    s.stop()


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is needed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield b
        b.close()


def _wait(predicate, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def _saved(path: Path) -> list[tuple[int, str]]:
    if not path.exists():
        return []
    return [(b["frame"], b["text"]) for b in json.loads(path.read_text())["bookmarks"]]


def test_add_list_jump_delete_in_the_browser(server, browser, tmp_path: Path) -> None:
    timeline = StubTimeline(server)
    path = tmp_path / "annotations.json"
    save_annotations(path, [Bookmark(80, "closing", "phase")])
    panel = BookmarkPanel(server, timeline, path)
    timeline.slider.value = 42
    page = browser.new_page(viewport={"width": 1200, "height": 800})
    try:
        page.goto(f"http://127.0.0.1:{server.get_port()}")
        page.get_by_role("slider").first.wait_for(timeout=20000)
        assert page.locator(".mantine-Slider-markLabel", has_text="closing").count() == 1
        page.get_by_text("Bookmarks").first.click()
        label = page.locator("label", has_text="Text").first
        box = label.locator("xpath=ancestor::div[2]//input").first
        box.fill("needle grasped")
        box.evaluate("e => e.blur()")
        time.sleep(0.3)
        page.locator("button", has_text="Add at current frame").click()
        assert _wait(lambda: _saved(path) == [(42, "needle grasped"), (80, "closing")])
        assert _wait(
            lambda: (
                page.locator(".mantine-Slider-markLabel").all_inner_texts()
                == ["needle grasped", "closing"]
            )
        )
        assert "#0 1.7 s (42) event: needle grasped" in str(panel.list.value)
        timeline.slider.value = 10
        page.locator("button", has_text="Jump").click()
        assert _wait(lambda: timeline.sought == [42])
        page.locator("button", has_text="Delete").click()
        assert _wait(lambda: _saved(path) == [(80, "closing")])
        assert _wait(
            lambda: page.locator(".mantine-Slider-markLabel").all_inner_texts() == ["closing"]
        )
    finally:
        page.close()


def test_bad_file_is_reported_and_never_overwritten(server, tmp_path: Path) -> None:
    timeline = StubTimeline(server)
    path = tmp_path / "annotations.json"
    path.write_text("{broken")
    panel = BookmarkPanel(server, timeline, path)
    assert "not valid JSON" in panel.status.content
    panel.add(5, "kept in memory")
    assert path.read_text() == "{broken"
    assert [b.text for b in panel.marks] == ["kept in memory"]
    panel.add(6, "   ")  # an empty text adds nothing
    assert len(panel.marks) == 1 and "Type a text" in panel.status.content


def test_without_a_file_bookmarks_stay_in_memory(server) -> None:
    timeline = StubTimeline(server)
    panel = BookmarkPanel(server, timeline, None)
    panel.add(3, "live note", "comment")
    panel.jump(0)
    assert timeline.sought == [3]
    assert "memory only" in panel.status.content
    panel.delete(0)
    assert panel.marks == [] and timeline.slider._marks is None


def test_the_viewer_has_the_panel_on_its_timeline(tmp_path: Path) -> None:
    import argparse

    from mistool.cli.serve import _annotations_path
    from mistool.synth import synthesize
    from mistool.synth.writer import SceneOptions
    from mistool.viewer import ReplayViewer, load_sequence

    seq = tmp_path / "seq"
    scene = SceneOptions(width=360, height=288, focal_px=300.0)
    synthesize(seq, frames=20, instruments=1, seed=2, fps=10.0, scene=scene)
    assert _annotations_path(argparse.Namespace(annotations=None, sequence=str(seq))) == (
        seq / "annotations.json"
    )
    assert _annotations_path(argparse.Namespace(annotations=None, sequence=None)) is None
    save_annotations(seq / "annotations.json", [Bookmark(15, "end", "phase")])
    viewer = ReplayViewer(
        load_sequence(seq, poses=seq / "truth.csv"), port=0, annotations=seq / "annotations.json"
    )
    try:
        panel = viewer.bookmarks
        assert [b.text for b in panel.marks] == ["end"]
        assert viewer.timeline.slider._marks[0].label == "end"
        viewer.timeline.seek(4)
        assert _wait(lambda: viewer.timeline.frame == 4)
        panel.add(viewer.timeline.frame, "start", "phase")
        assert _saved(seq / "annotations.json") == [(4, "start"), (15, "end")]
        panel.jump(1)
        assert _wait(lambda: viewer.timeline.frame == 15)
    finally:
        viewer.close()
