"""The fuller HTML replay: title, frame counter with units, legend and plots around
viser's player, paused at 0 s unless autoplay is asked; checked in headless chromium on
a real export."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from mistool.viewer.html_overlay import LegendEntry, decorate_replay_html

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run"]
FRAMES, FPS = 30, 10.0


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict[bool, str]:
    """The same sequence exported by 'mistool export-html', paused and with --autoplay."""
    from mistool.annotations import Bookmark, save_annotations
    from mistool.cli import main
    from mistool.synth import synthesize
    from mistool.synth.writer import SceneOptions

    folder = tmp_path_factory.mktemp("overlay")
    scene = SceneOptions(width=360, height=288, focal_px=300.0)
    synthesize(folder / "seq", frames=FRAMES, instruments=2, seed=3, fps=FPS, scene=scene)
    marks = folder / "marks.json"
    save_annotations(marks, [Bookmark(12, "grasp", "event")])
    pages = {}
    for autoplay in (False, True):
        out = folder / f"replay{int(autoplay)}.html"
        args = ["export-html", str(folder / "seq"), "-o", str(out), "-q", "--no-images"]
        args += ["--poses", str(folder / "seq" / "truth.csv"), "--annotations", str(marks)]
        args += ["--title", "Lab replay"] + (["--autoplay"] if autoplay else [])
        assert main(args) == 0
        pages[autoplay] = out.read_text(encoding="utf-8")
    return pages


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is needed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield b
        b.close()


def _open(browser, tmp_path: Path, text: str):
    out = tmp_path / "page.html"
    out.write_text(text, encoding="utf-8")
    page = browser.new_page(viewport={"width": 1100, "height": 700})
    remote: list[str] = []
    page.on("request", lambda r: remote.append(r.url) if r.url.startswith("http") else None)
    page.goto(out.as_uri())
    page.wait_for_selector("canvas[data-engine]", timeout=30000)
    return page, remote


def _frames_seen(page, seconds: float) -> set[str]:
    seen = set()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        seen.add(page.locator("#mistool-counter").get_attribute("data-frame") or "")
        time.sleep(0.1)
    return seen


def test_paused_at_zero_without_autoplay(browser, exported, tmp_path: Path) -> None:
    page, remote = _open(browser, tmp_path, exported[False])
    try:
        assert page.title().startswith("Lab replay")
        assert page.locator("#mistool-panel h1").inner_text() == "Lab replay"
        assert "instrument 2" in page.locator("#mistool-legend").inner_text()
        assert page.locator("#mistool-plots svg").count() == 2
        page.locator("#mistool-plots summary").click()  # closed at first
        assert page.locator("#mistool-plots svg").first.is_visible()
        assert page.locator("#mistool-plots text.marklabel", has_text="grasp").count() == 2
        time.sleep(1.0)
        assert _frames_seen(page, 1.5) == {"0"}
        assert page.locator("#mistool-counter").inner_text().startswith("frame 0 (0–29) · 0.00 s")
        assert page.locator("#mistool-counter").inner_text().endswith("3.00 s · 10 fps")
        assert not remote, remote
    finally:
        page.close()


def test_autoplay_when_asked_moves_counter_and_cursor(browser, exported, tmp_path) -> None:
    page, _ = _open(browser, tmp_path, exported[True])
    try:
        cursor = page.locator("#mistool-plots line.cursor").first
        xs: set[str | None] = set()
        frames: set[str | None] = set()
        end = time.monotonic() + 20.0  # software WebGL on a loaded machine plays slowly
        while time.monotonic() < end and (len(frames) < 3 or len(xs) < 3):
            frames.add(page.locator("#mistool-counter").get_attribute("data-frame"))
            xs.add(cursor.get_attribute("x1"))
            time.sleep(0.1)
        assert len(frames) >= 3 and len(xs) >= 3, (frames, xs)
    finally:
        page.close()


def test_decorate_escapes_and_keeps_the_page() -> None:
    page = "<html><head><title>Viser</title></head><body><div id=app></div></body></html>"
    out = decorate_replay_html(
        page, title="A <b>", fps=25.0, num_frames=10, legend=[LegendEntry("x<", "#000")]
    )
    assert out.startswith("<html><head><title>A &lt;b&gt; – Viser</title>")
    assert "<div id=app></div>" in out and out.endswith("</body></html>")
    assert "x&lt;" in out and '"autoplay": false' in out
