"""Two procedures side by side: 'mistool serve A/ B/' (own colours and scene region, one
timeline with an offset, metrics side by side), in real headless chromium."""

from __future__ import annotations

import contextlib
import io
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from mistool.cli import build_parser
from mistool.export import read_csv
from mistool.viewer.compare import REGION_GAP_MM, combine_tables, metrics_markdown

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run"]


@pytest.fixture(scope="module")
def two(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from mistool.synth import synthesize
    from mistool.synth.writer import SceneOptions

    folder = tmp_path_factory.mktemp("compare")
    scene = SceneOptions(width=360, height=288, focal_px=300.0)
    synthesize(folder / "a", frames=30, instruments=2, seed=1, fps=10.0, scene=scene)
    synthesize(folder / "b", frames=20, instruments=1, seed=2, fps=5.0, scene=scene)
    return folder / "a", folder / "b"


def test_combine_puts_b_beside_a_on_a_shared_clock(two) -> None:
    a, b = (read_csv(p / "truth.csv") for p in two)
    table, shift = combine_tables(a, b, fps_a=10.0, fps_b=5.0, offset_s=1.0, num_frames=30)
    names = sorted(set(table["instrument"]))
    assert names == ["A:1", "A:2", "B:1"]
    tb = table[table["instrument"] == "B:1"]
    # B's frame k (5 fps) is at A's frame (k / 5 + 1) * 10; nothing past A's 30 frames
    src = b[np.isin(b["frame"], (np.asarray(tb["frame"]) - 10) // 2)]
    assert set(np.asarray(tb["frame"]).tolist()) <= set(range(10, 30, 2))
    assert tb.num_rows == src.num_rows > 0
    assert np.allclose(np.sort(tb["end_x_mm"]), np.sort(src["end_x_mm"] + shift), equal_nan=True)
    assert np.allclose(np.sort(tb["end_y_mm"]), np.sort(src["end_y_mm"]), equal_nan=True)
    # the shift puts B's region (1st percentile of its x) 30 mm right of A's (99th)
    a_hi = np.nanpercentile(np.concatenate([a["end_x_mm"], a["start_x_mm"]]), 99)
    b_lo = np.nanpercentile(np.concatenate([b["end_x_mm"], b["start_x_mm"]]), 1)
    assert b_lo + shift == pytest.approx(a_hi + REGION_GAP_MM)
    text = metrics_markdown([("A", a, 10.0, 30), ("B", b, 5.0, 20)])
    assert text.splitlines()[0] == "| metric | A:1 | A:2 | B:1 |"
    assert "path length (mm) ↓" in text


def test_serve_two_recordings_in_the_browser(two, tmp_path: Path, monkeypatch) -> None:
    from mistool.cli.serve import run

    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is needed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    a, b = two
    args = build_parser().parse_args(["serve", str(a), str(b), "--port", "0", "--offset", "1"])
    ready, stop = threading.Event(), threading.Event()
    out, result = io.StringIO(), []

    def serve() -> None:
        with contextlib.redirect_stdout(out):
            result.append(run(args, ready=ready, stop=stop))

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        assert ready.wait(120), out.getvalue()
        url = re.search(r"open (\S+)", out.getvalue()).group(1)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.goto(url)
            page.get_by_role("slider").first.wait_for(timeout=30000)
            legend = page.get_by_text("Instruments:").first
            legend.wait_for(timeout=20000)
            text = legend.inner_text()
            assert "A:1" in text and "A:2" in text and "B:1" in text
            page.get_by_text("Skill metrics").first.click()
            time.sleep(0.5)
            panel = page.get_by_text("starts +1 s after A").first
            assert panel.is_visible()
            assert page.locator("th", has_text="B:1").count() >= 1
            browser.close()
    finally:
        stop.set()
        thread.join(60)
    assert result == [0]
