"""The viewer in a real browser: Debian's chromium driven by playwright (software WebGL).

Asserts what a person would see: the page renders, each instrument's shaft and clasper are
on screen in its colour, the frame slider works and changes the picture, a camera preset
moves the camera, keyboard shortcuts step and play, several browsers at once (one closing
mid-playback) leave no error or stuck state, and the exported HTML replays offline.

Under CI (env ``CI`` set) these tests must run: a missing chromium or playwright FAILS.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.viewer import ReplayViewer, export_html, load_sequence
from mistool.viewer.scene import node_name

CHROMIUM = Path("/usr/bin/chromium")
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]
VIEWPORT = {"width": 1280, "height": 800}
#: The 3D view left of the GUI panel and below viser's notification (x, y, w, h).
SCENE_CLIP = {"x": 0, "y": 160, "width": 860, "height": 640}
#: Where the browser test saves its screenshot (a temporary folder unless set).
SCREENSHOT_ENV = "MISTOOL_SCREENSHOT"


def _require_browser() -> None:
    reason = None
    if not CHROMIUM.exists():
        reason = f"{CHROMIUM} not installed (apt-get install chromium)"
    else:
        try:
            import playwright.sync_api  # noqa: F401
        except ImportError:
            reason = "playwright is not installed (pip install playwright)"
    if reason is not None:
        if os.environ.get("CI"):
            pytest.fail(f"browser tests must run under CI: {reason}")
        pytest.skip(reason)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory):
    from mistool.synth import synthesize

    out = tmp_path_factory.mktemp("browser") / "seq"
    synthesize(out, frames=40, instruments=2, seed=3)
    return load_sequence(out, poses=out / "truth.csv")


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    _require_browser()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def viewer(sequence) -> Iterator[ReplayViewer]:
    v = ReplayViewer(sequence, port=0)
    yield v
    v.close()


def _busy_frames(replay) -> np.ndarray:
    g = replay.modes[replay.default_mode]
    return np.flatnonzero(g.visible.reshape(replay.num_frames, -1).all(axis=1))


def _shot(page, clip: dict | None = None) -> np.ndarray:
    png = page.screenshot(clip=clip or SCENE_CLIP)
    return cv2.cvtColor(
        cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
    )


def _hue_pixels(img: np.ndarray, rgb: tuple[int, int, int]) -> int:
    """Pixels with the hue of ``rgb`` (lit or shaded), saturated enough not to be grid."""
    hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV).astype(int)
    target = int(cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0, 0])
    dh = np.abs(hsv[..., 0] - target)
    dh = np.minimum(dh, 180 - dh)
    return int(((dh <= 8) & (hsv[..., 1] > 90) & (hsv[..., 2] > 40)).sum())


def _wait(predicate, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def _open(browser, url: str):
    page = browser.new_page(viewport=VIEWPORT)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url)
    page.wait_for_selector("canvas[data-engine]", timeout=20000)
    page.get_by_role("slider").first.wait_for(timeout=20000)
    close = page.locator(".mantine-Notification-root button")
    if close.count():
        close.first.click()
    page.errors = errors  # type: ignore[attr-defined]
    return page


def _client(viewer: ReplayViewer):
    clients = list(viewer.server.get_clients().values())
    assert clients, "no browser connected"
    return clients[-1]


def test_page_shows_the_replay_and_reacts(browser, viewer: ReplayViewer, tmp_path: Path) -> None:
    replay = viewer.replay
    busy = _busy_frames(replay)
    assert len(busy) >= 2, "the synthetic sequence should show both instruments"
    page = _open(browser, viewer.url)
    try:
        assert _wait(lambda: len(viewer.server.get_clients()) >= 1)
        # The scene holds each instrument's shaft and clasper (viser's own registry).
        names = set(viewer.server.scene._handle_from_node_name)
        for inst in replay.instruments:
            for part in ("shaft", "clasper"):
                assert f"/instruments/{node_name(inst)}/{part}" in names
        # GUI: the frame slider and the play button are there.
        assert page.get_by_role("slider").count() >= 1
        assert page.get_by_role("button", name="Play").count() == 1

        # Look through the endoscope at a frame with both instruments: each one's colour
        # is on screen (the frustum image is hidden in this view, so these are cylinders).
        frame = int(busy[len(busy) // 2])
        viewer.timeline.seek(frame)
        assert viewer.timeline.wait_shown(frame)
        # The panel says each drawn part has its pose (truth.csv has them all, and an
        # empty pose_status column: it said "no pose" beside the cylinders).
        n = len(replay.instruments)
        assert _wait(lambda: page.inner_text("body").count("clasper ✓") == n)
        panel = page.inner_text("body")
        assert panel.count("shaft ✓") == n and "no pose" not in panel, panel
        page.get_by_role("button", name="Endoscope").click()
        time.sleep(1.0)
        endo = _shot(page)
        for i in range(len(replay.instruments)):
            assert _hue_pixels(endo, replay.part_colour(i, "shaft")) > 300, (
                f"instrument {replay.instruments[i]} not visible"
            )
        # Behind the cylinders, this browser's background is the overlay (dark mask
        # image, letterboxed), and the frustum and grid are out of the way.
        assert _client(viewer).client_id in viewer._endoscope
        assert (endo.mean(axis=2) < 60).mean() > 0.4, "no mask behind the cylinders"
        assert not viewer.scene.frustum.visible

        # Back to the overview: the canvas is not blank.
        client = _client(viewer)
        before_cam = np.array(client.camera.position)
        page.get_by_role("button", name="Reset").click()
        assert _wait(lambda: np.linalg.norm(np.array(client.camera.position) - before_cam) > 1.0), (
            "Reset preset did not move the camera"
        )
        time.sleep(1.0)
        overview = _shot(page)
        assert overview.std() > 10.0 and len(np.unique(overview.reshape(-1, 3), axis=0)) > 50
        assert overview.mean() > 150, "the endoscope backdrop stayed after leaving the view"
        assert viewer.scene.frustum.visible and not viewer._endoscope

        # A camera preset moves this browser's camera, and the picture.
        reset_cam = np.array(client.camera.position)
        page.get_by_role("button", name="Top").click()
        assert _wait(lambda: np.linalg.norm(np.array(client.camera.position) - reset_cam) > 1.0), (
            "Top preset did not move the camera"
        )
        time.sleep(1.0)
        top = _shot(page)
        assert np.abs(top.astype(int) - overview.astype(int)).mean() > 2.0
        page.get_by_role("button", name="Reset").click()
        time.sleep(1.0)

        # Moving the slider (keyboard on its thumb) moves the replay, and the picture.
        start = int(busy[0])
        viewer.timeline.seek(start)
        assert viewer.timeline.wait_shown(start)
        time.sleep(0.8)
        first = _shot(page)
        thumb = page.get_by_role("slider").first
        thumb.focus()
        for _ in range(max(1, int(busy[-1]) - start)):
            page.keyboard.press("ArrowRight")
        assert _wait(lambda: viewer.timeline.shown == int(busy[-1])), (
            f"slider moved to {viewer.timeline.shown}, expected {int(busy[-1])}"
        )
        time.sleep(0.8)
        moved = _shot(page)
        assert np.abs(moved.astype(int) - first.astype(int)).mean() > 1.0

        # Keyboard shortcuts: L steps forward, J back, space plays and pauses.
        page.mouse.click(400, 600)  # focus the 3D view, not an input
        k = viewer.timeline.frame
        page.keyboard.press("l")
        assert _wait(lambda: viewer.timeline.frame == (k + 1) % replay.num_frames)
        page.keyboard.press("j")
        assert _wait(lambda: viewer.timeline.frame == k)
        page.keyboard.press(" ")
        assert _wait(lambda: viewer.timeline.playing)
        page.keyboard.press(" ")
        assert _wait(lambda: not viewer.timeline.playing)

        # The screenshot for the README: Reset view of a busy frame.
        viewer.timeline.seek(frame)
        viewer.timeline.wait_shown(frame)
        time.sleep(1.0)
        page.screenshot(path=os.environ.get(SCREENSHOT_ENV, str(tmp_path / "viewer.png")))
        assert not page.errors, page.errors  # type: ignore[attr-defined]
        assert not viewer.timeline.draw_errors
    finally:
        page.close()


def test_the_overview_is_beside_the_panel_and_shows_every_instrument(
    browser, viewer: ReplayViewer
) -> None:
    """The GUI panel is docked beside the 3D view, not floating over it: the Reset view of
    a busy frame shows every instrument's shaft on the canvas, none of it under the panel
    (with a floating panel the fitted view put the tools under it)."""
    replay = viewer.replay
    busy = _busy_frames(replay)
    frame = int(busy[len(busy) // 2])
    page = _open(browser, viewer.url)
    try:
        viewer.timeline.seek(frame)
        assert viewer.timeline.wait_shown(frame)
        page.get_by_role("button", name="Reset").click()
        time.sleep(1.0)
        canvas = page.locator("canvas").first.bounding_box()
        play = page.get_by_role("button", name="Play").bounding_box()
        assert canvas is not None and play is not None
        assert canvas["x"] + canvas["width"] <= play["x"], (canvas, play)
        assert canvas["width"] > 0.5 * VIEWPORT["width"], canvas
        clip = {k: round(canvas[k]) for k in ("x", "y", "width", "height")}
        shot = _shot(page, clip)
        for i, name in enumerate(replay.instruments):
            assert _hue_pixels(shot, replay.part_colour(i, "shaft")) > 100, name
        assert not page.errors, page.errors  # type: ignore[attr-defined]
    finally:
        page.close()


def _shaft_pixels(img: np.ndarray, rgb: tuple[int, int, int]) -> np.ndarray:
    """Boolean map of pixels with the hue of a shaft colour ``rgb`` and its strong
    saturation (lit or shaded cylinder, or the overlay's blend on the dark background;
    the lighter clasper colours and the grey background stay out)."""
    hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV).astype(int)
    target = int(cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0, 0])
    dh = np.abs(hsv[..., 0] - target)
    dh = np.minimum(dh, 180 - dh)
    return (dh <= 8) & (hsv[..., 1] > 150) & (hsv[..., 2] > 40)


def _camera_aspect(client) -> float:
    """The aspect (w / h) of the browser's 3D view as it last told the server. Its size
    is the canvas's drawing buffer: the CSS size times a pixel ratio that viser lowers
    (to 0.875 or 0.75) when frames come slowly, e.g. on a loaded machine."""
    w, h = client.camera.image_width, client.camera.image_height
    return w / h if h else 0.0


def _laid_out(viewer: ReplayViewer, client) -> bool:
    """Whether the viewer has sent ``client`` its endoscope layout for the window's
    aspect as the browser last told it (what :meth:`ReplayViewer._camera_moved` does)."""
    if abs(viewer._backdrop_aspect.get(client.client_id, 0.0) - _camera_aspect(client)) > 1e-3:
        return False
    with viewer._lock:  # the handler that sends it holds the lock until it has
        return True


def _canvas_clip(page, client, size: dict, timeout: float = 60.0) -> dict:
    """The 3D canvas's box (integer px) once it has followed a new viewport ``size`` and
    the browser has told the server (its camera's aspect is the canvas's, to its pixel
    rounding): a box read at a fixed delay could still be the old or a half-resized
    one. The last box at the deadline (the caller's asserts then say what is wrong)."""
    canvas = page.locator("canvas").first
    end = time.monotonic() + timeout
    while True:
        box = canvas.bounding_box() or {"x": 0, "y": 0, "width": 0, "height": 1}
        clip = {k: round(box[k]) for k in ("x", "y", "width", "height")}
        wide = clip["width"] > 0.9 * size["width"]
        if (wide and _same_aspect(client, clip)) or time.monotonic() > end:
            return clip
        time.sleep(0.1)


def _same_aspect(client, clip: dict) -> bool:
    return abs(_camera_aspect(client) / (clip["width"] / max(clip["height"], 1)) - 1) < 0.01


def _no_background(img: np.ndarray) -> bool:
    """The endoscope's backdrop is gone: mostly the page's white."""
    return bool((img.min(axis=2) > 250).mean() > 0.5)


def _settled_shot(
    page,
    clip: dict,
    *,
    changed_from: np.ndarray | None = None,
    until=None,
    timeout: float = 60.0,
) -> np.ndarray:
    """A screenshot once the picture has settled: three in a row alike, 0.2 s apart (the
    browser has drawn what it was sent, images decoded), unlike ``changed_from`` (the
    change sent has arrived) and with ``until(shot)`` true. The last one at the
    deadline: the caller's asserts then say what is wrong. (A fixed sleep was too short
    for a loaded machine's browser: a shot still showed what was just hidden.)"""
    end = time.monotonic() + timeout
    last, alike = _shot(page, clip), 0
    while time.monotonic() < end:
        time.sleep(0.2)
        shot = _shot(page, clip)
        alike = alike + 1 if np.array_equal(shot, last) else 0
        moved = changed_from is None or not np.array_equal(shot, changed_from)
        if alike >= 2 and moved and (until is None or until(shot)):
            return shot
        last = shot
    return last


def test_endoscope_view_lines_up_with_the_mask(browser, viewer: ReplayViewer) -> None:
    """Through the endoscope each instrument's shaft cylinder covers its shaft in the mask
    behind it, in a tall window and after resizing it to a wide one. Two screenshots per
    window: the background alone (cylinders hidden) and the cylinders alone (background
    removed); their shaft pixels must coincide."""
    replay = viewer.replay
    busy = _busy_frames(replay)
    frame = int(busy[len(busy) // 2])
    trail, boxes = viewer.trail.value, viewer.boxes.value
    page = browser.new_page(viewport={"width": 620, "height": 900})
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(viewer.url)
        page.wait_for_selector("canvas[data-engine]", timeout=20000)
        page.get_by_role("button", name="Endoscope").wait_for(timeout=20000)
        close = page.locator(".mantine-Notification-root button")  # an orange bar
        if close.count():
            close.first.click()
        viewer.trail.value = 0  # trails and box outlines share the instruments' hues
        viewer.boxes.value = False
        viewer.timeline.seek(frame)
        assert viewer.timeline.wait_shown(frame) and viewer.wait_overlay(frame)
        page.get_by_role("button", name="Endoscope").click()
        page.get_by_label("Collapse panel area").click()  # the docked panel narrows the view
        assert _wait(lambda: len(viewer._endoscope) == 1)
        client = next(c for c, _ in viewer._endoscope.values())
        for size in ({"width": 620, "height": 900}, {"width": 1280, "height": 640}):
            page.set_viewport_size(size)
            clip = _canvas_clip(page, client, size)  # beside the collapsed panel
            w, h = clip["width"], clip["height"]
            assert w > 0.9 * size["width"], (clip, size)
            told = (client.camera.image_width, client.camera.image_height)
            assert _same_aspect(client, clip), (told, clip)
            # The server lays the view out again for the new window (its backdrop and
            # field of view, sent from the camera message's handler, under the lock).
            assert _wait(lambda: _laid_out(viewer, client), timeout=60.0), "no new layout"
            both = _settled_shot(page, clip)  # the backdrop and the cylinders on it
            with viewer.server.atomic():
                for nodes in viewer.scene.parts.values():
                    nodes.hide()
            backdrop = _settled_shot(page, clip, changed_from=both)
            with viewer.server.atomic():
                client.scene.set_background_image(None)
                viewer.scene.show(frame)
            cylinders = _settled_shot(page, clip, until=_no_background)
            assert _no_background(cylinders)
            # Within the image (the padding is black; cylinders run on over it), below
            # the collapsed panel's handle.
            keep = (
                cv2.erode((backdrop.max(axis=2) > 10).astype(np.uint8), np.ones((7, 7), np.uint8))
                > 0
            )
            keep[:70] = False
            for i, name in enumerate(replay.instruments):
                colour = replay.part_colour(i, "shaft")
                mask = _shaft_pixels(backdrop, colour) & keep
                drawn = _shaft_pixels(cylinders, colour) & keep
                assert mask.sum() > 1500 and drawn.sum() > 1500, (
                    size,
                    name,
                    mask.sum(),
                    drawn.sum(),
                )
                iou = (mask & drawn).sum() / (mask | drawn).sum()
                ym, xm = np.nonzero(mask)
                yd, xd = np.nonzero(drawn)
                shift = np.hypot(xd.mean() - xm.mean(), yd.mean() - ym.mean())
                assert iou > 0.85 and shift < 4.0, (
                    f"{w}x{h}, instrument {name}: IoU {iou:.2f}, centroids {shift:.1f} px apart"
                )
            viewer._send_backdrops(viewer._overlay_rgb, only=client)  # what a frame does
        assert not errors, errors
    finally:
        page.close()
        viewer.trail.value, viewer.boxes.value = trail, boxes


class _SocketClient:
    """A bare viser websocket client (what a browser tab is to the server): it receives
    every message the server sends, as fast as it can, until closed."""

    def __init__(self, url: str) -> None:
        import threading

        import msgspec
        import viser
        from viser._messages import ViewerCameraMessage
        from websockets.sync.client import connect

        self.ws = connect(
            url.replace("http://", "ws://"),
            subprotocols=[f"viser-v{viser.__version__}"],
            max_size=None,
        )
        # viser registers a client when its first camera message arrives.
        camera = ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0),
            position=(3.0, 3.0, 3.0),
            fov=1.0,
            near=0.01,
            far=1000.0,
            image_height=600,
            image_width=800,
            look_at=(0.0, 0.0, 0.0),
            up_direction=(0.0, 0.0, 1.0),
        )
        self.ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        self.received = 0
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            for _ in self.ws:
                self.received += 1
        except Exception:  # closed
            pass

    def close(self) -> None:
        self.ws.close()


def test_ten_viewers_playback_and_some_closing(browser, viewer: ReplayViewer) -> None:
    """Two real browsers plus eight bare websocket clients (software WebGL makes ten
    rendering tabs too slow for a test on two cores); five leave mid-playback."""
    pages = [_open(browser, viewer.url) for _ in range(2)]
    sockets = [_SocketClient(viewer.url) for _ in range(8)]
    try:
        assert _wait(lambda: len(viewer.server.get_clients()) >= 10, 20.0)
        viewer.timeline.speed.value = "4x"
        viewer.timeline.set_playing(True)
        time.sleep(0.8)
        pages[1].close()  # a browser closing mid-playback
        for s in sockets[4:]:
            s.close()
        drawn = viewer.timeline.frames_drawn
        time.sleep(0.8)
        assert viewer.timeline.frames_drawn > drawn, "playback stopped after clients left"
        viewer.timeline.set_playing(False)
        before = [s.received for s in sockets[:4]]
        # Rapid scrubbing from the remaining browser: the last position wins.
        thumb = pages[0].get_by_role("slider").first
        thumb.focus()
        pages[0].keyboard.press("Home")
        for _ in range(12):
            pages[0].keyboard.press("ArrowRight")
        assert _wait(lambda: viewer.timeline.shown == 12), viewer.timeline.shown
        assert _wait(lambda: len(viewer.server.get_clients()) == 5, 10.0)
        # The remaining bare clients are still being served (viser batches messages, so
        # count websocket messages, not frames).
        assert _wait(
            lambda: all(s.received > b for s, b in zip(sockets[:4], before, strict=True))
        ), [(s.received, b) for s, b in zip(sockets[:4], before, strict=True)]
        assert not viewer.timeline.draw_errors
        assert not pages[0].errors  # type: ignore[attr-defined]
    finally:
        for page in pages:
            if not page.is_closed():
                page.close()
        for s in sockets:
            s.close()


def test_exported_html_replays_offline(browser, sequence, tmp_path: Path) -> None:
    out = tmp_path / "replay.html"
    export_html(sequence, out, max_frames=30, autoplay=True)  # paused by default (issue 11)
    page = browser.new_page(viewport={"width": 1000, "height": 700})
    remote: list[str] = []
    page.on(
        "request",
        lambda r: (
            remote.append(r.url) if r.url.split(":", 1)[0] not in ("file", "data", "blob") else None
        ),
    )
    # The page's frame counter follows the player's time. The recording is loaded and
    # decoded after the canvas appears (seconds on a loaded machine: a fixed wait once
    # took both pictures before it played), so the pictures wait for the counter.
    frame_at_least = "n => +(document.getElementById('mistool-counter').dataset.frame || -1) >= n"
    clip = {"x": 0, "y": 160, "width": 1000, "height": 480}
    try:
        page.goto(out.as_uri())
        page.wait_for_selector("canvas[data-engine]", timeout=20000)
        page.wait_for_function(frame_at_least, arg=12, timeout=60000)  # tools in view
        shots = [_shot(page, clip)]
        page.wait_for_function(
            "n => { const f = +document.getElementById('mistool-counter').dataset.frame;"
            " return f >= n || f < 5; }",
            arg=int(page.get_attribute("#mistool-counter", "data-frame") or 0) + 12,
            timeout=60000,
        )
        shots.append(_shot(page, clip))
        assert shots[0].std() > 10.0
        assert np.abs(shots[1].astype(int) - shots[0].astype(int)).mean() > 0.2, (
            "the recording does not play"
        )
        assert not remote, remote
    finally:
        page.close()
