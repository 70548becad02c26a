"""Long and live sequences in a real browser (Debian chromium through playwright).

- A long generated procedure (20,000 frames) is on screen, instruments drawn, while its
  tracking still runs in the background, and the timeline grows as it proceeds.
- ``mistool.Viewer.add`` fed from a loop: a browser watches the timeline grow and sees the
  newest frame, a browser connecting late gets the whole timeline; after looking through the
  endoscope and pressing Reset, the frustum shows the frame on screen (not the one from
  before).

Under CI (env ``CI`` set) these tests must run: a missing chromium or playwright FAILS.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_viewer_browser import _hue_pixels, _open, _shot, _wait, browser  # noqa: F401

from mistool.sequence import list_frames
from mistool.viewer import ReplayViewer, load_sequence

#: Frames of the long procedure (symlinks to a short synthetic sequence).
LONG_FRAMES = 20_000


@pytest.fixture(scope="module")
def short_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from mistool.synth import synthesize

    out = tmp_path_factory.mktemp("live_browser") / "seq"
    synthesize(out, frames=40, instruments=2, seed=3)
    return out


def _slider_max(page) -> int:
    return int(float(page.get_by_role("slider").first.get_attribute("aria-valuemax") or 0))


def test_long_procedure_renders_before_tracking_finishes(
    browser,  # noqa: F811
    short_seq: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    long = tmp_path / "long"
    long.mkdir()
    (long / "mistool.toml").write_bytes((short_seq / "mistool.toml").read_bytes())
    frames = list_frames(short_seq)
    n = len(frames)
    for k in range(LONG_FRAMES):  # forwards and backwards through the short sequence
        src = frames[k % n] if (k // n) % 2 == 0 else frames[n - 1 - k % n]
        os.symlink(src, long / f"{k:05d}.png")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    sequence = load_sequence(long, background=True)
    # Nothing listed before the server starts: the background job lists the frames.
    assert sequence.replay.tracked == 0 and not sequence.frames.listed
    viewer = ReplayViewer(sequence, port=0)
    page = None
    try:
        page = _open(browser, viewer.url)
        assert viewer.wait_tracked(50, timeout=90), "no tracked frame arrived"
        assert sequence.frames.num_mask_frames == LONG_FRAMES == sequence.feed.total  # type: ignore[union-attr]
        assert _wait(lambda: viewer._fitted, timeout=30), "the view never showed an instrument"
        shown = viewer.timeline.shown
        assert _wait(lambda: viewer.overlay_frame == viewer.timeline.shown, timeout=10)
        time.sleep(1.0)
        img = _shot(page)
        replay = viewer.replay
        assert replay.modes[replay.default_mode].visible[shown].any()
        colours = [replay.part_colour(i, "shaft") for i in range(len(replay.instruments))]
        assert max(_hue_pixels(img, c) for c in colours) > 300, "no instrument on screen"
        assert replay.tracked < LONG_FRAMES, "tracking had already finished"
        assert page.get_by_text("Tracking", exact=False).count() >= 1, "no progress line"
        first_max = _slider_max(page)
        assert first_max >= 49
        assert _wait(lambda: _slider_max(page) > first_max + 20, timeout=60), (
            f"the timeline did not grow past {first_max}"
        )
        assert viewer.replay.tracked < LONG_FRAMES
        assert not page.errors, page.errors  # type: ignore[attr-defined]
        assert not viewer.timeline.draw_errors and not viewer.feed_errors
    finally:
        if page is not None:
            page.close()
        viewer.close()
    job = sequence.feed.job if sequence.feed is not None else None
    assert job is not None and not job.running, "tracking still running"


def test_viewer_add_from_a_loop_while_a_browser_watches(
    browser,  # noqa: F811
    short_seq: Path,
) -> None:
    import mistool

    labels = [cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in list_frames(short_seq)]
    tissue = np.zeros((*labels[0].shape, 3), np.uint8)
    tissue[:] = (150, 60, 50)  # a reddish video frame under the mask
    viewer = mistool.Viewer(short_seq / "mistool.toml", port=0)
    rv = viewer.replay_viewer
    page = None
    try:
        page = _open(browser, viewer.url)
        stop = threading.Event()
        added: list[int] = []

        def network_loop() -> None:
            k = 0
            while not stop.is_set() and k < 400:
                n = len(labels)  # forwards and backwards: continuous motion
                viewer.add(labels[k % n if (k // n) % 2 == 0 else n - 1 - k % n], image=tissue)
                added.append(k)
                k += 1
                time.sleep(0.04)  # a 25 fps network

        thread = threading.Thread(target=network_loop)
        thread.start()
        try:
            assert _wait(lambda: _slider_max(page) >= 10, timeout=60), "timeline did not grow"
            seen = _slider_max(page)
            assert _wait(lambda: _slider_max(page) >= seen + 10, timeout=60)
        finally:
            stop.set()
            thread.join(30)
        total = len(added)
        assert rv.replay.tracked == total and rv.timeline.num_frames == total
        assert _wait(lambda: _slider_max(page) == total - 1, timeout=10)
        assert rv.timeline.wait_shown(total - 1), "the newest frame is not on screen"
        assert _wait(lambda: len(rv.server.get_clients()) == 1)
        client = next(iter(rv.server.get_clients().values()))  # the first page's
        late = _open(browser, viewer.url)  # a browser that connects late sees it all
        try:
            assert _wait(lambda: _slider_max(late) == total - 1, timeout=20)
        finally:
            late.close()

        # A frame with both instruments, looked at through the endoscope, then Reset: the
        # frustum shows that frame's overlay, not the one from before entering the view.
        g = rv.replay.modes[rv.replay.default_mode]
        busy = np.flatnonzero(g.visible[:total, :, 0].all(axis=1))  # every shaft in view
        n = len(labels)
        busy = busy[busy % n != (total - 1) % n]  # not the same picture as the last frame
        assert len(busy) >= 2
        page.get_by_role("button", name="Endoscope").click()
        assert _wait(lambda: client.client_id in rv._endoscope)
        target = int(busy[len(busy) // 2])
        rv.timeline.seek(target)
        assert rv.timeline.wait_shown(target) and rv.wait_overlay(target)
        assert rv.scene.frustum._image_data != rv._overlay_jpeg  # hidden: not updated
        page.get_by_role("button", name="Reset").click()
        assert _wait(lambda: not rv._endoscope)
        assert rv.scene.frustum._image_data == rv._overlay_jpeg, "stale frustum image"
        time.sleep(1.0)
        img = _shot(page)
        colours = [rv.replay.part_colour(i, "shaft") for i in range(len(rv.replay.instruments))]
        assert min(_hue_pixels(img, c) for c in colours) > 100, "an instrument is missing"
        assert not page.errors, page.errors  # type: ignore[attr-defined]
        assert not rv.timeline.draw_errors
    finally:
        if page is not None:
            page.close()
        viewer.close()


def test_a_browser_connecting_while_the_first_data_arrives_is_fitted_to_it(
    browser,  # noqa: F811
    short_seq: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """viser counts a browser as connected only once its first camera message arrives
    (after the page has loaded its WebGL). The first data coming in between must still
    move that browser's camera onto the instruments. The window is made wide on purpose:
    the server holds the page's camera messages until the data is in."""
    import asyncio

    import viser.infra
    from viser import _messages

    import mistool

    release = threading.Event()
    register = viser.infra.WebsockClientConnection.register_handler

    def held_register(self, message_cls, callback):  # type: ignore[no-untyped-def]
        if message_cls is not _messages.ViewerCameraMessage:
            return register(self, message_cls, callback)

        async def held(client_id, message):  # type: ignore[no-untyped-def]
            while not release.is_set():
                await asyncio.sleep(0.02)
            await callback(client_id, message)

        return register(self, message_cls, held)

    monkeypatch.setattr(viser.infra.WebsockClientConnection, "register_handler", held_register)
    labels = [cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in list_frames(short_seq)]
    viewer = mistool.Viewer(short_seq / "mistool.toml", port=0)
    rv = viewer.replay_viewer
    page = None
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.goto(viewer.url)
        page.wait_for_selector("canvas[data-engine]", timeout=20000)
        page.wait_for_timeout(1000)  # the page sends its camera: held
        assert not rv.server.get_clients(), "the page counted as connected"
        for k in range(10):  # the first data: the view is fitted without this browser
            viewer.add(labels[k])
        assert rv._fitted
        release.set()
        assert _wait(lambda: len(rv.server.get_clients()) == 1, timeout=20)
        page.wait_for_timeout(1500)
        img = _shot(page)
        colours = [rv.replay.part_colour(i, "shaft") for i in range(len(rv.replay.instruments))]
        assert max(_hue_pixels(img, c) for c in colours) > 300, "no instrument on screen"
    finally:
        release.set()
        if page is not None:
            page.close()
        viewer.close()
