"""The teacher's report: self-contained offline HTML, checked in real headless chromium."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.annotations import Bookmark, save_annotations
from mistool.cli import main
from mistool.export import write_csv
from mistool.model import TrackTable
from mistool.report import ReportRecording, build_report, nice_floor, verdict, write_report
from mistool.skill import METRICS

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--no-first-run"]
#: Where the test saves its screenshot (a temporary folder unless set).
SCREENSHOT_ENV = "MISTOOL_REPORT_SCREENSHOT"
INFO = {m.name: m for m in METRICS}


def wavy_table(speed: float, n: int = 150, fps: float = 25.0) -> TrackTable:
    """Two instruments moving on smooth curves (clasper tips + shafts), ``speed`` scales
    the motion."""
    t = np.arange(n) / fps
    cols: dict[str, list] = {
        k: [] for k in ("frame", "time_s", "instrument", "part", "end_x_mm", "end_y_mm", "end_z_mm")
    }
    cols.update({"axis_x": [], "axis_y": [], "axis_z": []})
    for k, name in enumerate(("left", "right")):
        x = (-20 + 40 * k) + 10 * np.sin(speed * t + k)
        y = 8 * np.cos(0.7 * speed * t)
        z = 80 + 15 * np.sin(0.3 * speed * t + k)
        for f in range(n):
            for part, off in (("shaft", -15.0), ("clasper", 0.0)):
                cols["frame"].append(f)
                cols["time_s"].append(f / fps)
                cols["instrument"].append(name)
                cols["part"].append(part)
                cols["end_x_mm"].append(x[f] + off)
                cols["end_y_mm"].append(y[f])
                cols["end_z_mm"].append(z[f])
                cols["axis_x"].append(1.0)
                cols["axis_y"].append(0.0)
                cols["axis_z"].append(0.0)
    return TrackTable(cols)


def test_verdict_states_direction_and_size() -> None:
    v = verdict(INFO["path_length_mm"], 100.0, 80.0, ("A", "B"))
    assert v == "<b>B</b> better: B lower by 20%"
    v = verdict(INFO["mean_speed_mm_s"], 10.0, 8.0, ("A", "B"))
    assert v == "<b>A</b> better: B lower by 20%"
    v = verdict(INFO["idle_fraction"], 0.30, 0.10, ("A", "B"))
    assert v == "<b>B</b> better: B lower by 0.2"
    assert verdict(INFO["ldlj"], -9.0, -9.0, ("A", "B")) == "equal"
    assert verdict(INFO["duration_s"], 10.0, 12.0, ("A", "B")).endswith("(no better direction)")
    assert verdict(INFO["ldlj"], float("nan"), 1.0, ("A", "B")) == "–"
    assert [nice_floor(v) for v in (0.7, 1.0, 3.3, 19.9, 20.0, 60.0)] == [0.5, 1, 2, 10, 20, 50]


def test_report_is_self_contained() -> None:
    recs = [ReportRecording("novice", wavy_table(2.0)), ReportRecording("expert", wavy_table(1.0))]
    text = build_report(recs, title="Lab <1>")
    assert "<script" not in text and "http" not in text and "src=" not in text
    assert "Lab &lt;1&gt;" in text  # escaped
    assert text.count("<svg") == 2 * 5  # 2 time plots + 3 projections per recording
    assert text.count("<h3>instrument left of novice vs instrument left of expert") == 1


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is needed for the report test (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield b
        b.close()


def test_report_in_chromium_offline(browser, tmp_path: Path) -> None:
    a, b = tmp_path / "novice.csv", tmp_path / "expert.csv"
    write_csv(wavy_table(2.0), a)
    write_csv(wavy_table(1.0), b)
    marks_a, marks_b = tmp_path / "a.json", tmp_path / "b.json"
    save_annotations(marks_a, [Bookmark(50, "needle grasped", "event")])
    save_annotations(marks_b, [])
    out = tmp_path / "report.html"
    args = ["report", str(a), str(b), "-o", str(out), "-q", "--title", "Skills lab"]
    assert main([*args, "--annotations", str(marks_a), str(marks_b)]) == 0
    page = browser.new_page(viewport={"width": 1000, "height": 1300})
    remote: list[str] = []
    page.on("request", lambda r: remote.append(r.url) if not r.url.startswith("file:") else None)
    try:
        page.goto(out.as_uri())
        assert page.title() == "Skills lab"
        assert page.locator("svg.plot").count() == 4
        assert page.locator("svg.proj").count() == 6
        # the comparison: the slower "expert" has the shorter path, and says so
        row = page.locator("table.compare").first.locator("tr", has_text="path length")
        assert "expert better" in row.inner_text()
        assert "needle grasped" in page.locator("section.recording").first.inner_text()
        assert page.locator("svg.plot text.marklabel", has_text="needle grasped").count() == 2
        # every plot has drawn lines, the projections are in each instrument's colour
        for box in page.locator("svg.plot path.line").all():
            assert len(box.get_attribute("d") or "") > 200
        shot = Path(os.environ.get(SCREENSHOT_ENV) or tmp_path / "report.png")
        page.screenshot(path=str(shot), full_page=True)
        img = cv2.imread(str(shot))
        assert img.shape[0] > 2000 and img.std() > 10
        blue = np.all(np.abs(img.astype(int) - [180, 119, 31]) < 40, axis=2)  # BGR of #1f77b4
        assert blue.sum() > 500
        assert not remote, remote
    finally:
        page.close()


def test_report_bad_input(tmp_path: Path, capsys) -> None:
    a = tmp_path / "a.csv"
    write_csv(wavy_table(1.0, n=20), a)
    out = tmp_path / "r.html"
    assert main(["report", str(a), "-o", str(out), "--annotations", "x.json", "y.json"]) == 1
    assert "one per SOURCE" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    assert main(["report", str(a), "-o", str(out), "--annotations", str(bad)]) == 1
    assert capsys.readouterr().err.startswith(f"mistool: error: {bad}: not valid JSON")
    assert not out.exists()
    write_report(out, [ReportRecording("a", TrackTable())])  # empty-safe
    assert "No instrument with a 3D pose" in out.read_text()
