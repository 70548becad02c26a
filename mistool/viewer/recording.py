"""Standalone offline HTML replays (viser's scene serializer + its bundled client).

viser 1.1.1 records every scene message sent while a serializer is active, with sleeps
between frames, and ``StateSerializer.as_html()`` inlines the recording (zstd, base64) into
its prebuilt single-file web client, which then plays the recording back with its own
play/pause and time slider — no server and no network needed. What is recorded: the
cylinders, trails, grid and the endoscope frustum with the overlay (mask and boxes) on its
image plane, frame by frame. The GUI panel (plots, overlay panel, mode switch) is not part
of a recording: the export uses one mode (metric when available).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from mistool.annotations import Bookmark
from mistool.errors import ConfigError
from mistool.export import atomic_write
from mistool.viewer.app import LoadedSequence, quiet_server
from mistool.viewer.html_overlay import decorate_export
from mistool.viewer.overlay import OverlayRenderer
from mistool.viewer.scene import SceneView

#: Longest side (px) of the overlay images stored in an HTML replay.
EXPORT_IMAGE_SIDE = 320


@dataclass(frozen=True)
class ExportSummary:
    """What :func:`export_html` wrote."""

    path: Path
    """The HTML file."""
    frames: int
    """Frames recorded."""
    bytes: int
    """File size."""
    mode: str
    """Display mode recorded."""


def export_html(
    sequence: LoadedSequence,
    out: str | Path,
    *,
    mode: str | None = None,
    stride: int = 1,
    max_frames: int | None = None,
    images: bool = True,
    image_side: int = EXPORT_IMAGE_SIDE,
    opacity: float = 0.6,
    trail_frames: int = 25,
    jpeg_quality: int = 70,
    title: str | None = None,
    autoplay: bool = False,
    bookmarks: Sequence[Bookmark] = (),
) -> ExportSummary:
    """Write a standalone HTML replay of a sequence (opens offline in any browser).

    Args:
        sequence: from :func:`mistool.viewer.load_sequence`.
        out: the HTML file to write (atomically).
        mode: ``"metric"`` or ``"paper"``; default: the viewer's default.
        stride: record every ``stride``-th frame (playback keeps real time).
        max_frames: record at most this many frames.
        images: put the overlay on the frustum's image plane (larger file).
        image_side: longest side (px) of those images.
        opacity: mask opacity of the overlay.
        trail_frames: trail length (frames; 0 = off).
        jpeg_quality: JPEG quality of the overlay images.
        title: the page's title (default: the sequence's name); a frame counter with
            units, the legend and the tips' plots are added (:mod:`.html_overlay`).
        autoplay: start playing on open (default: paused at the first frame).
        bookmarks: marked on the plots.

    Raises:
        ConfigError: an invalid option.
    """
    replay = sequence.replay
    mode = mode or replay.default_mode
    if mode not in replay.modes:
        raise ConfigError(
            f"--mode {mode}: not available for this sequence; choose from {', '.join(replay.modes)}"
        )
    if stride < 1:
        raise ConfigError(f"--stride {stride}: must be an integer >= 1")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames {max_frames}: must be an integer >= 1")
    frames = list(range(0, replay.num_frames, stride))[:max_frames]
    renderer = (
        OverlayRenderer(replay, sequence.frames, max_side=image_side)
        if images and (sequence.frames.has_masks or sequence.frames.has_source)
        else None
    )
    first = renderer.render(frames[0], opacity) if renderer else None
    server = quiet_server("127.0.0.1", 0)
    try:
        server.scene.configure_environment_map(None)
        scene = SceneView(
            server,
            replay,
            mode,
            overlay=first,
            trail_frames=trail_frames,
            jpeg_quality=jpeg_quality,
        )
        position, look_at, up, fov = scene.camera_pose("Reset")
        server.initial_camera.position = tuple(position)
        server.initial_camera.look_at = tuple(look_at)
        server.initial_camera.up = tuple(up)
        server.initial_camera.fov = fov
        scene.show(frames[0])
        serializer = server.get_scene_serializer()
        dt = stride / replay.fps
        for k in frames:
            with server.atomic():
                scene.show(k)
                if renderer is not None:
                    scene.set_overlay(renderer.render(k, opacity))
            serializer.insert_sleep(dt)
        html = serializer.as_html()
        html = decorate_export(
            html,
            sequence,
            title=title,
            start_frame=frames[0],
            mode=mode,
            autoplay=autoplay,
            bookmarks=bookmarks,
        )
    finally:
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints "Server stopped"
            server.stop()
    with atomic_write(out, "w", encoding="utf-8") as f:
        f.write(html)
    path = Path(out)
    return ExportSummary(path=path, frames=len(frames), bytes=path.stat().st_size, mode=mode)
