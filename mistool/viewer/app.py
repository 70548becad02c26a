"""The replay viewer: a viser server showing one sequence's replay.

Shared or per-browser? The **timeline and display options are shared** by every browser
connected to one server (slider, play/pause, speed, mode, trails, opacity, plot
selection): a teacher scrubs and the class follows, and the server's work per frame does
not grow with the number of browsers. **Cameras are per browser**: orbiting or a camera
preset moves only the browser that asked. In the "Endoscope" view the overlay is that
browser's own background (one extra JPEG per frame per such browser); the frustum and the
grid, being shared, are hidden while any browser looks through the endoscope.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import io
import math
import socket
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import viser

from mistool.cache import CacheEntry
from mistool.config import Config
from mistool.errors import ConfigError, InputPathError, MistoolError
from mistool.lens import undistort_view
from mistool.model import TrackTable
from mistool.viewer import meshes
from mistool.viewer.bookmarks import BookmarkPanel
from mistool.viewer.feed import CacheFeed
from mistool.viewer.guard import AccessPolicy, guarded, with_token
from mistool.viewer.overlay import FrameStore, OverlayCache, OverlayRenderer
from mistool.viewer.plots import PlotPanel
from mistool.viewer.replay import (
    NOT_VISIBLE,
    Replay,
    ReplayPatch,
    build_replay,
    config_parts,
    mode_constants,
)
from mistool.viewer.scene import PRESETS, SceneView
from mistool.viewer.timeline import Timeline


@dataclass(frozen=True)
class LoadedSequence:
    """What the viewer needs about a sequence: its replay and its frames on disk."""

    replay: Replay
    """The replay (complete, or growing while ``feed`` brings more frames)."""
    frames: FrameStore
    """Lazy access to its mask (and source video) frames."""
    name: str
    """A short name for titles."""
    feed: CacheFeed | None = None
    """Where more frames come from while the replay is shown (None: complete)."""
    table: TrackTable | None = None
    """The motion table shown, when complete (None while ``feed`` grows it)."""
    path: Path | None = None
    """The sequence folder or mask video (None for arrays)."""


#: Tracking options of ``mistool serve`` (part of the cache key).
SERVE_TRACKING = {"metric": True, "smoothing": "offline"}


def _entry_for(seq_path: Path, config: Config, files: list[Path] | None = None) -> CacheEntry:
    """The cache entry of a sequence tracked with :data:`SERVE_TRACKING` (``files``: its
    frame files when already listed)."""
    from mistool.cache import cache_key, enforce_limit, open_entry
    from mistool.sequence import list_frames

    if files is None:
        files = list_frames(seq_path) if seq_path.is_dir() else [seq_path]
    elif not files:
        files = [seq_path]
    entry = open_entry(cache_key(seq_path, config, files, **SERVE_TRACKING))
    with contextlib.suppress(OSError):
        entry.touch()
        enforce_limit(keep=entry)
    return entry


def load_sequence(
    path: str | Path | None,
    *,
    poses: str | Path | None = None,
    progress: bool = False,
    table: TrackTable | None = None,
    cache: bool = False,
    background: bool = False,
    fresh: bool = False,
    calibration: str | Path | None = None,
) -> LoadedSequence:
    """Open a sequence for the viewer: track it (or load its motion table) and index its
    frames. Every problem with the input is raised here, before any server starts; in the
    ``background``, what only a listing of every frame can find (a dangling symlink, a
    frame of another size, an unreadable frame) stops the tracking job instead, which
    says so (:attr:`LoadedSequence.feed`'s status).

    Args:
        path: the sequence folder or mask video; None for the bundled sample.
        poses: a motion table CSV to show instead of tracking the sequence.
        progress: show a tracking progress bar on stderr (tracking here, not in the
            background).
        table: an in-memory motion table to show instead of tracking.
        cache: reuse the table tracked by an earlier call for the same, unchanged
            sequence (:mod:`mistool.cache`), and store it after tracking; a partly
            tracked entry is resumed. The sequence's folder is never written to.
        background: do not track here: return at once with an empty replay and a
            :attr:`LoadedSequence.feed` whose background process lists the frames, finds
            the cache entry, and tracks what is not stored yet while the viewer shows it
            (``mistool serve``); the work done here does not grow with the number of
            frames (one frame is read). Implies ``cache``.
        fresh: forget what the cache holds for this sequence and track it again.
        calibration: a camera calibration file overriding the config's camera
            (``--calibration``; :func:`mistool.calibration.with_calibration`).

    Raises:
        MistoolError: bad path, masks, ``mistool.toml`` or table (one-line message).
    """
    from mistool.calibration import with_calibration
    from mistool.export import check_table_limits, read_csv
    from mistool.resources import sample_masks_dir
    from mistool.sequence import check_source, resolve, widen_for_video

    seq_path, config = resolve(sample_masks_dir() if path is None else path)
    config = with_calibration(config, calibration)
    if seq_path.is_file():  # a mask video: its codec smears label values (as tracking does)
        config = widen_for_video(config)
    # In the background, the job lists the frames (and keys the cache on them): the
    # server starts at once however long the sequence (FrameStore's deferred listing).
    deferred = background and table is None and poses is None
    frames = FrameStore(seq_path, config, defer_listing=deferred)
    num_frames: int | None = frames.num_mask_frames or None
    shape = frames.mask_shape()
    if config.camera is not None and shape is not None:  # a calibration of another size
        config = _fit_camera(config, shape)
    if table is None and poses is not None:
        table = read_csv(poses)
    if table is not None:
        check_table_limits(table, str(poses) if poses is not None else "motion table")
        check_source(config, num_frames, shape)  # warns when source and masks disagree
        image_wh = (shape[1], shape[0]) if shape is not None else None
        replay = build_replay(table, config, num_frames=num_frames, image_wh=image_wh)
        return LoadedSequence(
            replay=replay, frames=frames, name=seq_path.name, table=table, path=seq_path
        )
    if seq_path.is_dir() and not frames.has_masks:
        raise InputPathError(
            f"{seq_path}: no label images in this folder; pass a folder "
            "of masks, a mask video, or --poses with a motion table"
        )
    check_source(config, num_frames, shape)  # warns when source and masks disagree
    if background:
        return _background(seq_path, config, frames, num_frames, shape, fresh)
    if fresh:
        _entry_for(seq_path, config, frames.mask_files).remove()
    table, num_frames, config, shape = _track_now(
        seq_path,
        config,
        cache=cache,
        progress=progress,
        num_frames=num_frames,
        shape=shape,
        files=frames.mask_files,
    )
    image_wh = (shape[1], shape[0]) if shape is not None else None
    replay = build_replay(table, config, num_frames=num_frames, image_wh=image_wh)
    return LoadedSequence(
        replay=replay, frames=frames, name=seq_path.name, table=table, path=seq_path
    )


def _track_now(
    seq_path: Path,
    config: Config,
    *,
    cache: bool,
    progress: bool,
    num_frames: int | None,
    shape: tuple[int, int] | None,
    files: list[Path],
) -> tuple[TrackTable, int | None, Config, tuple[int, int] | None]:
    """Track in this process (through the cache when ``cache``)."""
    from mistool import api

    if cache:
        from mistool.background import JobSpec, track_into
        from mistool.cache import frames_digest

        entry = _entry_for(seq_path, config, files)
        with contextlib.suppress(OSError, MistoolError):  # a damaged entry: track again
            same = entry.frames_digest() == frames_digest(files or [seq_path])
            if same and entry.progress().complete:
                return entry.read_final(), num_frames, config, shape
        with contextlib.suppress(OSError):
            spec = JobSpec(seq_path, config, entry, files=files, **SERVE_TRACKING)  # type: ignore[arg-type]
            track_into(spec)
            return entry.read_final(), num_frames, config, shape
    result = api.run(seq_path, config, progress=progress)
    if result.shape is not None:
        shape = result.shape
    return result.table, result.num_frames, result.config, shape


def _fit_camera(config: Config, shape: tuple[int, int]) -> Config:
    """The config with its camera fitted to masks of ``shape`` (H, W): a calibration of
    another size is scaled when uniform (an :class:`InputWarning` says so), else an error
    (:func:`mistool.lens.fit_camera`)."""
    import warnings

    from mistool.errors import InputWarning
    from mistool.lens import fit_camera

    assert config.camera is not None
    where = str(config.calibration) if config.calibration is not None else "camera"
    camera, note = fit_camera(config.camera, (shape[1], shape[0]), where)
    if note is not None:
        warnings.warn(note, InputWarning, stacklevel=3)
    return replace(config, camera=camera)


def _background(
    seq_path: Path,
    config: Config,
    frames: FrameStore,
    num_frames: int | None,
    shape: tuple[int, int] | None,
    fresh: bool,
) -> LoadedSequence:
    """A growing replay fed by a background tracking job through the cache. The job
    lists the frames, finds the cache entry (``fresh``: empties it) and gives the frame
    names to ``frames``; nothing here grows with the sequence's length."""
    from mistool.background import JobSpec
    from mistool.viewer.feed import CacheFeed

    if shape is not None:
        image_wh = (shape[1], shape[0])
    elif config.camera is not None:
        image_wh = (int(round(2 * config.camera.cx + 1)), int(round(2 * config.camera.cy + 1)))
    else:
        image_wh = (720, 576)
    replay = Replay(
        config,
        num_frames=num_frames or 1,
        image_wh=image_wh,
        instruments=tuple(s.name for s in config.instruments),
        parts=config_parts(config),
    )
    spec = JobSpec(seq_path, config, None, fresh=fresh, **SERVE_TRACKING)  # type: ignore[arg-type]
    feed = CacheFeed(None, spec, num_frames, on_names=frames.set_mask_names)
    return LoadedSequence(
        replay=replay, frames=frames, name=seq_path.name, feed=feed, path=seq_path
    )


def check_host(host: str) -> None:
    """Raise :class:`ConfigError` unless a server can listen on ``host`` (viser would
    otherwise try port after port forever)."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)
        family, _, _, _, address = infos[0]
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((address[0], 0))
    except (OSError, IndexError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc) or "cannot bind"
        raise ConfigError(f"--host {host}: cannot listen on this address: {reason}") from None


def make_server(host: str, port: int, access: AccessPolicy | None = None) -> viser.ViserServer:
    """The viser server every viewer runs on (the one place a server is created)."""
    return quiet_server(host, port, access)


def quiet_server(host: str, port: int, access: AccessPolicy | None = None) -> viser.ViserServer:
    """A viser server that prints nothing (viser 1.1.1 prints a banner even when not
    verbose; library code never prints, the command line prints the URL itself), and
    that answers its own page only (``access``, default :meth:`AccessPolicy.for_host`;
    see :mod:`mistool.viewer.guard`)."""
    check_host(host)
    if not 0 <= int(port) <= 65535:
        raise ConfigError(f"--port {port}: must be in 0..65535")
    policy = access if access is not None else AccessPolicy.for_host(host)
    with contextlib.redirect_stdout(io.StringIO()):
        return guarded(
            lambda: viser.ViserServer(host=host, port=port, verbose=False, label="mistool"),
            policy,
        )


def endoscope_layout(
    size_wh: tuple[int, int],
    intrinsics: tuple[float, float, float, float],
    image_wh: tuple[int, int],
    aspect: float,
) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int], float]:
    """How an image is laid out as the background of a window looking through the
    endoscope, so that the 3D scene drawn by viser's camera lines up with it.

    viser's camera is a centred pinhole with square pixels whose vertical field of view
    spans the window's height, and the background image is stretched over the whole
    window. So the image is resampled to square pixels (when fx != fy), padded with black
    so that the principal point is at its centre and its aspect is the window's, and the
    camera gets the vertical field of view of the padded image's height.

    Args:
        size_wh: (w, h) px of the image to lay out (e.g. the overlay, at display size).
        intrinsics: (fx, fy, cx, cy) px, OpenCV convention, of an image of ``image_wh``
            covering the same view.
        image_wh: (w, h) px of the image the intrinsics refer to.
        aspect: the window's width / height (<= 0: unknown, no padding beyond centring).

    Returns:
        ``(resampled (w, h), padded (W, H), offset (x0, y0) of the image in the padded
        one, vertical field of view in radians)``.
    """
    w, h = size_wh
    fx, fy, cx, cy = intrinsics
    sx, sy = w / image_wh[0], h / image_wh[1]
    # In the image's own pixels, with its edges at 0 and w (resp. h).
    fx, cx = fx * sx, (cx + 0.5) * sx
    fy, cy = fy * sy, (cy + 0.5) * sy
    if abs(fx - fy) > 1e-6 * fx:  # stretch vertically to square pixels
        k = max(1, int(round(h * fx / fy))) / h
        h, fy, cy = int(round(h * k)), fy * k, cy * k
    half_w = max(cx, w - cx)  # around the principal point
    half_h = max(cy, h - cy)
    if aspect > 0:
        if half_w / half_h < aspect:
            half_w = half_h * aspect
        else:
            half_h = half_w / aspect
    big_w, big_h = max(w, int(round(2 * half_w))), max(h, int(round(2 * half_h)))
    x0 = min(max(int(round(big_w / 2 - cx)), 0), big_w - w)
    y0 = min(max(int(round(big_h / 2 - cy)), 0), big_h - h)
    return (w, h), (big_w, big_h), (x0, y0), 2.0 * math.atan2(big_h / 2.0, fy)


def endoscope_backdrop(
    rgb: np.ndarray,
    aspect: float,
    intrinsics: tuple[float, float, float, float],
    image_wh: tuple[int, int],
) -> tuple[np.ndarray, float]:
    """An image (RGB uint8, (h, w, 3)) laid out by :func:`endoscope_layout` as the
    background of a window of ``aspect`` (width / height) looking through the endoscope.

    Returns:
        The (H, W, 3) background (``rgb`` itself when nothing changes) and the vertical
        field of view (radians) the window's camera needs.
    """
    h, w = rgb.shape[:2]
    (w2, h2), (big_w, big_h), (x0, y0), fov = endoscope_layout((w, h), intrinsics, image_wh, aspect)
    if h2 != h:
        rgb = cv2.resize(rgb, (w2, h2), interpolation=cv2.INTER_LINEAR)
    if (big_w, big_h) == (w2, h2):
        return rgb, fov
    out = np.zeros((big_h, big_w, 3), dtype=rgb.dtype)
    out[y0 : y0 + h2, x0 : x0 + w2] = rgb
    return out, fov


#: Seconds between two polls of a feed for new frames.
FEED_POLL_S = 0.2
#: The same until the first instrument is on screen (the first picture waits for it).
FEED_POLL_FIRST_S = 0.05
#: Seconds between two refreshes of the plots while the replay grows.
PLOT_REFRESH_S = 2.0


def parts_markdown(replay: Replay, frame: int) -> str:
    """The "Parts in this frame" panel at ``frame`` (markdown): per instrument, each part
    whose metric pose is shown (✓, with its quality) and, for the others, why not (the
    table's ``pose_status``, :meth:`Replay.frame_status`)."""
    rows: dict[str, list[str]] = {}
    for inst, part, status, quality in replay.frame_status(frame):
        if status == "ok":
            text = f"{part} ✓" + (f" ({quality:.2f})" if np.isfinite(quality) else "")
        else:
            text = f"{part}: _{status}_"
        rows.setdefault(inst, []).append(text)
    if not rows:
        return "_Not tracked yet._" if frame >= replay.tracked else "_No instrument._"
    lines = []
    for i, (inst, texts) in enumerate(rows.items()):
        r, g, b = (int(c) for c in replay.colours[i])
        swatch = f"<span style='color:rgb({r},{g},{b})'>■</span> **{inst}**"
        if all(t.endswith(f"_{NOT_VISIBLE}_") for t in texts):
            lines.append(f"{swatch}: _{NOT_VISIBLE}_")
        else:
            lines.append(f"{swatch}: " + " · ".join(texts))
    return "  \n".join(lines) + "  \n<small>✓ 3D pose shown (quality: mask IoU)</small>"


class ReplayViewer:
    """A running viewer: server, scene, overlay, timeline, plots."""

    def __init__(
        self,
        sequence: LoadedSequence,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        environment_map: bool = False,
        trail_frames: int = 25,
        opacity: float = 0.6,
        access: AccessPolicy | None = None,
        annotations: str | Path | None = None,
    ) -> None:
        """
        Args:
            sequence: from :func:`load_sequence`.
            host: interface to listen on.
            port: first port to try (viser moves to the next free one); 0 = any free port.
            environment_map: light the scene with viser's HDR environment map (costly in
                software rendering; see ``scripts/bench_viewer.py``); default lights
                otherwise.
            trail_frames: initial trail length (frames; 0 = off).
            opacity: initial mask opacity of the overlay, [0, 1].
            access: who may connect (default: this page only, a token beyond loopback;
                :mod:`mistool.viewer.guard`).
            annotations: the bookmarks file (``annotations.json``; :mod:`mistool.annotations`)
                the Bookmarks panel reads and writes; None keeps bookmarks in memory.
        """
        self.sequence = sequence
        self.annotations = Path(annotations) if annotations is not None else None
        self.replay = sequence.replay
        self.update_seconds: collections.deque[float] = collections.deque(maxlen=2000)
        """Seconds of each frame update (scene, trails, plot cursor, ready overlay)."""
        self.overlay_latency: collections.deque[float] = collections.deque(maxlen=2000)
        """Seconds from a frame update to its overlay being sent, when not prepared ahead."""
        self.overlay_frame = -1
        """The frame whose overlay is on screen."""
        self._current = -1
        self._overlay_rgb: np.ndarray | None = None
        # Browsers looking through the endoscope: client id -> (client, time it entered).
        self._endoscope: dict[int, tuple[viser.ClientHandle, float]] = {}
        # Client id -> window aspect its Endoscope view was last laid out for.
        self._backdrop_aspect: dict[int, float] = {}
        self._closing = False
        self._lock = threading.RLock()
        self._overlay_jpeg: bytes | None = None
        self._fitted = False  # grid and cameras fitted to some data
        self._source_listing = False  # a deferred source folder is being listed
        self._user_moved = False  # the user has chosen a frame: no automatic jumps
        self._parts_text = ""
        self._plots_refreshed = 0.0
        self._feed_stop = threading.Event()
        self._feed_thread: threading.Thread | None = None
        self.feed_errors: list[BaseException] = []
        """Errors raised while growing the replay (a bug, not bad input)."""
        self.server = make_server(host, port, access)
        try:
            self._build(environment_map, trail_frames, opacity)
        except BaseException:
            with contextlib.redirect_stdout(io.StringIO()):
                self.server.stop()
            raise

    def _build(self, environment_map: bool, trail_frames: int, opacity: float) -> None:
        server, replay, sequence = self.server, self.replay, self.sequence
        server.gui.configure_theme(control_width="large", show_logo=False, titlebar_content=None)
        server.gui.main_panel.dock_right()
        if not environment_map:
            server.scene.configure_environment_map(None)
        # Shadow maps cost extra render passes and shader variants in software WebGL.
        server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        self.renderer = (
            OverlayRenderer(replay, sequence.frames)
            if sequence.frames.has_masks or sequence.frames.has_source
            else None
        )
        self.overlays = OverlayCache(self.renderer) if self.renderer else None
        first = self.overlays.get(0, opacity, True)[0] if self.overlays else None
        mode = replay.default_mode
        if not replay.instruments:  # they come later: the meshes are ready by then
            meshes.warm_up()
        self.scene = SceneView(server, replay, mode, overlay=first, trail_frames=trail_frames)
        gui = server.gui
        self.title = gui.add_markdown(self._title())
        feed = sequence.feed
        with gui.add_folder("Playback"):
            available = replay.tracked if feed is not None else replay.num_frames
            self.timeline = Timeline(server, max(available, 1), replay.fps, self._draw)
            self.timeline.growing = feed is not None
            self.progress = gui.add_markdown(
                feed.status().text() if feed is not None else "", visible=feed is not None
            )
        with gui.add_folder("Parts in this frame"):
            self.parts_info = gui.add_markdown("")
        with gui.add_folder("View"):
            labels = {"metric": "Metric (mm)", "paper": "Paper (px)"}
            self.mode = gui.add_dropdown(
                "3D mode", tuple(labels[m] for m in replay.modes), initial_value=labels[mode]
            )
            if "metric" not in replay.modes:
                gui.add_markdown(
                    "_Metric mode needs `[camera]` in mistool.toml and a metric pose._"
                )
            self.camera_buttons = gui.add_button_group("Camera", PRESETS)
            self.trail = gui.add_slider(
                "Trail (frames)", min=0, max=200, step=1, initial_value=trail_frames
            )
            self.opacity = gui.add_slider(
                "Mask opacity", min=0.0, max=1.0, step=0.05, initial_value=opacity
            )
            self.boxes = gui.add_checkbox("Rotated boxes", initial_value=True)
            self.legend = gui.add_markdown(self._legend())
        with gui.add_folder("2D overlay"):
            self.image = gui.add_image(
                first if first is not None else np.zeros((4, 4, 3), np.uint8),
                format="jpeg",
                jpeg_quality=80,
            )
        with gui.add_folder("Plots", expand_by_default=False):
            self.plots = PlotPanel(gui, replay, mode)
        self.bookmarks = BookmarkPanel(server, self.timeline, self.annotations)
        self.mode.on_update(
            lambda _: self._set_mode(next(m for m in replay.modes if labels[m] == self.mode.value))
        )
        self.camera_buttons.on_click(lambda e: self._camera(e.client, str(e.target.value)))
        server.on_client_connect(self._watch_camera)
        server.on_client_disconnect(lambda c: self._leave_endoscope(c, reset=False))
        self.trail.on_update(lambda _: self._redraw(trails=True))
        self.opacity.on_update(lambda _: self._redraw())
        self.boxes.on_update(lambda _: self._redraw())
        position, look_at, up, fov = self.scene.camera_pose("Reset")
        server.initial_camera.position = tuple(position)
        server.initial_camera.look_at = tuple(look_at)
        server.initial_camera.up = tuple(up)
        server.initial_camera.fov = fov
        self.timeline.slider.on_update(self._slider_moved)
        self.timeline.start()
        busy = replay.first_busy_frame()
        self._fitted = busy is not None
        self.timeline.seek(busy or 0)
        if self._fitted or feed is None:
            self._list_source()
        if feed is not None:
            self._feed_thread = threading.Thread(
                target=self._feed_loop, name="mistool-feed", daemon=True
            )
            self._feed_thread.start()

    # -- public -------------------------------------------------------------------------
    @property
    def port(self) -> int:
        """The port the server really listens on."""
        return self.server.get_port()

    @property
    def url(self) -> str:
        """The address to open in a browser."""
        host = self.server.get_host()
        shown = "localhost" if host in ("0.0.0.0", "::", "") else host
        return with_token(self.server, f"http://{shown}:{self.port}")

    def draw_now(self, frame: int) -> float:
        """Draw ``frame`` synchronously (benchmarks); returns the seconds it took."""
        return self._draw(frame)

    def apply(self, patch: ReplayPatch) -> None:
        """Store new or replaced frames of the replay (thread-safe) and update what
        depends on them: timeline range, new instruments, the frame on screen."""
        replay = self.replay
        with self._lock:
            grew = len(patch.instruments) > len(replay.instruments)
            replay.apply(patch)
            if grew:
                self.scene.add_instruments()
                self.legend.content = self._legend()
                self.title.content = self._title()
            if self.overlays is not None:
                self.overlays.invalidate(patch.lo, patch.hi)
            now = time.monotonic()
            if grew or now - self._plots_refreshed > PLOT_REFRESH_S:
                self._plots_refreshed = now
                self.plots.grow()
        if self.sequence.feed is not None or self.timeline.growing:
            self.timeline.set_num_frames(replay.tracked)
        if not self._fitted:
            busy = replay.first_busy_frame()
            if busy is not None:
                self._fit(busy)
        if patch.lo <= self.timeline.frame < patch.hi:
            self.timeline.redraw()

    def set_image_size(self, image_wh: tuple[int, int]) -> None:
        """Change the image size (live use: known at the first frame): the overlay and
        the frustum follow."""
        with self._lock:
            self.replay.image_wh = (int(image_wh[0]), int(image_wh[1]))
            if self.overlays is not None:
                self.overlays.close()
            self.renderer = OverlayRenderer(self.replay, self.sequence.frames)
            self.overlays = OverlayCache(self.renderer)
            fov, aspect = self.replay.fov_aspect()
            self.scene.frustum.fov, self.scene.frustum.aspect = fov, aspect
            self.scene._canonical_depth = self.scene.frustum.compute_canonical_frustum_size()[2]
            for name, g in self.replay.modes.items():  # paper mode's image plane distance
                distance, _ = mode_constants(name, self.replay.config, self.replay.image_wh)
                self.replay.modes[name] = dataclasses.replace(g, image_distance=distance)
            self.scene.set_mode(self.scene.mode)

    def _list_source(self) -> None:
        """List a deferred ``source`` folder in a thread (once): after the first picture
        when tracking in the background, so that its 0.15-0.3 s of CPU at 90,000 images
        does not compete with the browser loading the page."""
        frames = self.sequence.frames
        if frames.listed or self._source_listing:
            return
        self._source_listing = True
        threading.Thread(target=frames.list_source, name="mistool-list-source", daemon=True).start()

    def _fit(self, busy: int) -> None:
        """The first data has come: fit the grid and cameras to it and show it."""
        self._fitted = True
        self._list_source()
        with self._lock:
            self.scene.set_mode(self.scene.mode)
            position, look_at, up, fov = self.scene.camera_pose("Reset")
            initial = self.server.initial_camera
            initial.position, initial.look_at = tuple(position), tuple(look_at)
            initial.up, initial.fov = tuple(up), fov
        for client in self.server.get_clients().values():
            if client.client_id not in self._endoscope:
                with contextlib.suppress(Exception):  # the browser may have just left
                    self.scene.apply_camera(client, "Reset")
        if not self._user_moved and not self.timeline.follow:
            self.timeline.seek(busy)

    def _slider_moved(self, event: viser.GuiEvent) -> None:
        if event.client is not None:
            self._user_moved = True

    def _feed_loop(self) -> None:
        """Background thread: grow the replay from the feed until it is finished."""
        feed = self.sequence.feed
        assert feed is not None
        try:
            feed.start()
            while not self._feed_stop.is_set():
                for patch in feed.poll(self.replay):
                    if self._feed_stop.is_set():
                        return
                    self.apply(patch)
                self.progress.content = feed.status().text()
                if feed.finished:
                    break
                self._feed_stop.wait(FEED_POLL_S if self._fitted else FEED_POLL_FIRST_S)
        except Exception as exc:  # a bug: keep serving what is there, and say so
            self.feed_errors.append(exc)
            self.progress.content = f"**Tracking failed**: {type(exc).__name__}: {exc}"
        finally:
            self.timeline.growing = False
            if not self._feed_stop.is_set():
                self._list_source()  # (when no frame was ever drawn in 3D)
            self.replay.complete = feed.status().phase == "done"
            if not self._closing:
                with self._lock:
                    self.plots.grow()

    def wait_tracked(self, frames: int, timeout: float = 30.0) -> bool:
        """Block until ``frames`` frames are shown on the timeline (tests, benchmarks)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.replay.tracked >= frames:
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        """Stop tracking, playback and the server."""
        with self._lock:  # a draw in progress finishes first; later ones see _closing
            self._closing = True
        self._feed_stop.set()
        # The feed thread first: it may be starting the job, or asking whether it runs,
        # while the job is stopped and its process closed (then a closed process object
        # stayed in multiprocessing's list, and its exit handler printed a traceback).
        if self._feed_thread is not None:
            self._feed_thread.join(timeout=10.0)
        if self.sequence.feed is not None:
            self.sequence.feed.stop()
        self.timeline.stop()
        if self.overlays is not None:
            self.overlays.close()
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints "Server stopped"
            self.server.stop()
        self.sequence.frames.close()

    # -- internals ----------------------------------------------------------------------
    def _title(self) -> str:
        replay, name = self.replay, self.sequence.name
        # A growing replay's length is on its progress line (learnt after the start).
        length = f"{replay.num_frames:,} frames at " if self.sequence.feed is None else ""
        return (
            f"**mistool replay** · {name} · {length}{replay.fps:g} fps · "
            f"{len(replay.instruments)} instrument(s)"
        )

    def _parts_markdown(self, frame: int) -> str:
        return parts_markdown(self.replay, frame)

    def _legend(self) -> str:
        rows = []
        for i, name in enumerate(self.replay.instruments):
            r, g, b = (int(c) for c in self.replay.colours[i])
            rows.append(f"<span style='color:rgb({r},{g},{b})'>■</span> {name}")
        return "Instruments: " + " &nbsp; ".join(rows)

    def _draw(self, frame: int) -> float:
        """Show ``frame`` everywhere; returns the seconds it took (also recorded).

        The scene, trails and plot cursor are updated at once. The overlay goes with them
        when it is ready (prepared ahead during playback); otherwise (scrubbing) it is
        rendered by the overlay worker and sent right after, unless the frame has changed
        again by then (rapid scrubbing never queues stale overlays).
        """
        t0 = time.perf_counter()
        with self._lock:
            self._current = frame
            opacity, boxes = float(self.opacity.value), bool(self.boxes.value)
            overlay = self.overlays.peek(frame, opacity, boxes) if self.overlays else None
            with self.server.atomic():
                self.scene.show(frame)
                if overlay is not None:
                    self._set_jpeg(*overlay)
                    self.overlay_frame = frame
                self.plots.set_frame(frame)
                text = self._parts_markdown(frame)
                if text != self._parts_text:
                    self._parts_text = text
                    self.parts_info.content = text
            if overlay is not None:
                self._send_backdrops(overlay[0])
        dt = time.perf_counter() - t0
        self.update_seconds.append(dt)
        if self.overlays is not None:
            if overlay is None:
                self.overlays.submit(self._overlay_job, frame, opacity, boxes, t0)
            if self.timeline.playing:
                n = self.replay.num_frames
                ahead = [frame + d for d in (1, 2, 3)]
                ahead = (
                    [k % n for k in ahead]
                    if self.timeline.loop.value
                    else [k for k in ahead if k < n]
                )
                self.overlays.prefetch(ahead, opacity, boxes)
        return dt

    def _overlay_job(self, frame: int, opacity: float, boxes: bool, t0: float) -> None:
        """Worker: render ``frame``'s overlay and send it if it is still the one shown."""
        if frame != self._current or self.overlays is None:
            return  # scrubbed past it
        rgb, jpeg = self.overlays.get(frame, opacity, boxes)
        with self._lock:
            if frame == self._current:
                with self.server.atomic():
                    self._set_jpeg(rgb, jpeg)
                self.overlay_frame = frame
                self.overlay_latency.append(time.perf_counter() - t0)
                self._send_backdrops(rgb)

    def wait_overlay(self, frame: int, timeout: float = 5.0) -> bool:
        """Block until ``frame``'s overlay is on screen (tests and benchmarks)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.overlay_frame == frame:
                return True
            time.sleep(0.002)
        return False

    def _set_jpeg(self, rgb: np.ndarray, jpeg: bytes) -> None:
        """Send one encoded JPEG to both the GUI image and the frustum's image plane."""
        self._overlay_rgb, self._overlay_jpeg = rgb, jpeg
        # Public setters would encode the same image twice; viser 1.1.1 (pinned) keeps
        # the encoded bytes in these props, so the one encoding is shared.
        self.image._image = rgb
        self.image._format = "jpeg"
        self.image._data = jpeg
        if self.scene.show_frustum_image:
            self._set_frustum_jpeg(rgb, jpeg)

    def _set_frustum_jpeg(self, rgb: np.ndarray, jpeg: bytes) -> None:
        view = self._endoscope_view(rgb)
        if view is not rgb:  # a distorted lens: the frustum shows the undistorted frame
            jpeg = cv2.imencode(".jpg", cv2.cvtColor(view, cv2.COLOR_RGB2BGR))[1].tobytes()
        self.scene.frustum._image = view
        self.scene.frustum._format = "jpeg"
        self.scene.frustum._image_data = jpeg

    def _endoscope_view(self, rgb: np.ndarray) -> np.ndarray:
        """The frame as the endoscope's ideal pinhole camera sees it: on a distorted lens,
        undistorted (:func:`mistool.lens.undistort_view`: OpenCV remap, maps computed once),
        so the 3D model drawn with the pinhole intrinsics lines up with the tools in the
        frustum and the endoscope view; the 2D overlay panel keeps the original frame."""
        return undistort_view(rgb, self.replay.config.camera, self.replay.image_wh)

    def _redraw(self, trails: bool = False) -> None:
        if trails:
            with self._lock:
                self.scene.set_trail_frames(int(self.trail.value))
        self.timeline.redraw()

    def _set_mode(self, mode: str) -> None:
        with self._lock:
            self.scene.set_mode(mode)
            self.plots.set_mode(mode)
            if self._overlay_rgb is not None:  # the modes see the image differently
                self._send_backdrops(self._overlay_rgb)

    def _camera(self, client: viser.ClientHandle | None, preset: str) -> None:
        if client is None:
            return
        if preset == "Endoscope":
            with self._lock:
                self._endoscope[client.client_id] = (client, time.monotonic())
                self.scene.set_frustum_image_visible(False)
            self.scene.apply_camera(client, preset, fov=self._endoscope_fov(client))
            with self._lock:
                if self._overlay_rgb is not None:
                    self._send_backdrops(self._overlay_rgb, only=client)
        else:
            self._leave_endoscope(client)
            self.scene.apply_camera(client, preset)

    # -- looking through the endoscope ----------------------------------------------------
    # A browser in the Endoscope view gets the overlay as its own background image (client
    # scoped), padded to its window's aspect around the principal point, and the vertical
    # field of view of that padded image (endoscope_layout), so that the cylinders sit on
    # the mask whatever the window's shape; both follow the window when it is resized.
    # The frustum is hidden while any browser looks through it (the scene is shared) and
    # shown again when none does. Orbiting away from the endoscope leaves the view.
    def _leave_endoscope(self, client: viser.ClientHandle, reset: bool = True) -> None:
        with self._lock:
            was = self._endoscope.pop(client.client_id, None) is not None
            self._backdrop_aspect.pop(client.client_id, None)
            if was and not self._endoscope and not self._closing:
                self.scene.set_frustum_image_visible(True)
                if self._overlay_rgb is not None and self._overlay_jpeg is not None:
                    # The frustum missed the frames drawn while it was hidden.
                    with self.server.atomic():
                        self._set_frustum_jpeg(self._overlay_rgb, self._overlay_jpeg)
        if was and reset:
            with contextlib.suppress(Exception):  # the browser may be gone
                client.scene.set_background_image(None)

    def _watch_camera(self, client: viser.ClientHandle) -> None:
        """A new browser: follow its camera (the endoscope view's background), and put
        it on the data if the view was fitted while it was still loading. viser counts a
        browser as connected only at its first camera message, seconds after its page
        got the initial camera, so :meth:`_fit` can miss it (it then looked at the empty
        scene's default place)."""
        client.camera.on_update(self._camera_moved)
        with self._lock:
            if self._fitted and not self._closing:
                with contextlib.suppress(Exception):  # the browser may have just left
                    self.scene.apply_camera(client, "Reset")

    def _camera_moved(self, camera: viser.CameraHandle) -> None:
        client = camera.client
        entry = self._endoscope.get(client.client_id)
        if entry is None:
            return  # not in the view
        if abs(_aspect(camera) - self._backdrop_aspect.get(client.client_id, 0.0)) > 1e-3:
            with self._lock:  # the window was resized: lay the view out again
                if client.client_id in self._endoscope:
                    with contextlib.suppress(Exception):  # the browser may have just left
                        camera.fov = self._endoscope_fov(client)
                    if self._overlay_rgb is not None:
                        self._send_backdrops(self._overlay_rgb, only=client)
        if time.monotonic() - entry[1] < 1.0:
            return  # still flying there
        if np.linalg.norm(np.asarray(camera.position)) > 0.05:
            self._leave_endoscope(client)

    def _endoscope_fov(self, client: viser.ClientHandle) -> float:
        """The vertical field of view (rad) of ``client``'s window looking through the
        endoscope (see :func:`endoscope_layout`)."""
        replay = self.replay
        self._backdrop_aspect[client.client_id] = aspect = _aspect(client.camera)
        return endoscope_layout(
            replay.image_wh, replay.view_intrinsics(self.scene.mode), replay.image_wh, aspect
        )[3]

    def _send_backdrops(self, rgb: np.ndarray, only: viser.ClientHandle | None = None) -> None:
        """Send the overlay ``rgb`` as the background of the browsers looking through the
        endoscope (or of ``only``), laid out for each one's window, with the matching field
        of view (call holding ``self._lock``)."""
        if self._closing:  # the server is stopping: nothing can be delivered
            return
        clients = [only] if only is not None else [c for c, _ in self._endoscope.values()]
        rgb = self._endoscope_view(rgb)
        intrinsics = self.replay.view_intrinsics(self.scene.mode)
        connected = self.server.get_clients()
        for client in clients:
            if client.client_id not in connected:  # left: viser would only warn
                continue
            cam = client.camera
            aspect = _aspect(cam)
            image, fov = endoscope_backdrop(rgb, aspect, intrinsics, self.replay.image_wh)
            with contextlib.suppress(Exception):  # the browser may have just left
                client.scene.set_background_image(image, format="jpeg", jpeg_quality=80)
                cam.fov = fov  # no message unless it changed
                self._backdrop_aspect[client.client_id] = aspect


def _aspect(camera: viser.CameraHandle) -> float:
    """Width / height of a browser's 3D view (0 when not known yet)."""
    return camera.image_width / camera.image_height if camera.image_height else 0.0
