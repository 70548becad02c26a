#!/usr/bin/env python
"""The browser's own share of the time to first picture: a bare viser server with one red
box (no mistool), timed from navigation to the first screenshot showing the box, in the
headless Debian chromium the other benchmarks use (software WebGL). What mistool's
``scripts/bench_live.py`` first-picture figures cannot go below on this machine.

Usage::

    scripts/bench_page_load.py [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import viser

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_viewer_browser import ARGS, CHROMIUM  # noqa: E402

#: Pixels of the box's red that count as "on screen".
MIN_PIXELS = 300
#: Seconds before a run is given up.
TIMEOUT_S = 60.0


def _red_pixels(png: bytes) -> int:
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return int(((img[..., 2] > 150) & (img[..., 1] < 80) & (img[..., 0] < 80)).sum())


def _one_run(browser) -> float:  # type: ignore[no-untyped-def]
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        server.scene.configure_environment_map(None)
        server.scene.add_box("/box", color=(255, 0, 0), dimensions=(1.0, 1.0, 1.0))
        server.initial_camera.position = (3.0, 3.0, 3.0)
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        try:
            t0 = time.perf_counter()
            page.goto(f"http://127.0.0.1:{server.get_port()}")
            while _red_pixels(page.screenshot()) <= MIN_PIXELS:
                if time.perf_counter() - t0 > TIMEOUT_S:
                    raise RuntimeError("the box never appeared")
            return time.perf_counter() - t0
        finally:
            page.close()
    finally:
        server.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        try:
            browser.new_page().close()  # the browser warmed up, as in bench_live
            times = [_one_run(browser) for _ in range(args.runs)]
        finally:
            browser.close()
    runs = ", ".join(f"{t:.2f}" for t in times)
    print(f"bare viser page, first picture: {statistics.median(times):.2f} s (runs: {runs})")


if __name__ == "__main__":
    main()
