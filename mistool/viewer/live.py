"""The live plug-in: show the instruments while a segmentation network runs.

::

    with mistool.Viewer("mistool.toml") as viewer:       # the server starts at once
        for image in video:
            labels = net(image).argmax(0)                  # (H, W) integer labels
            rows = viewer.add(labels, image)               # tracked, shown, returned
    table = viewer.table()                                 # the whole sequence so far

:meth:`Viewer.add` tracks the frame with :class:`mistool.Tracker` (the same tracker, the
same rows), writes it into the replay and asks the timeline to show it; the drawing and
the messages to browsers happen on the viewer's own threads, so ``add`` never waits for a
browser, however slow. Browsers that connect late get the whole replay so far (the 3D
motion, plots and timeline of every frame). The 2D overlay keeps only the last
:data:`LIVE_IMAGE_FRAMES` frames' images in memory (at display size); older frames show
their 3D motion and boxes over a dark background.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING

import cv2
import numpy as np

from mistool.config import Config
from mistool.model import TrackTable
from mistool.sequence import to_labels
from mistool.viewer.overlay import FrameStore, display_size

if TYPE_CHECKING:
    from mistool.viewer.app import ReplayViewer

#: Frames whose label image and video image are kept for the 2D overlay (10 s at 25 fps).
LIVE_IMAGE_FRAMES = 250
#: JPEG quality of the video images kept for the overlay.
LIVE_JPEG_QUALITY = 85


class LiveFrames(FrameStore):
    """The last frames given to :meth:`Viewer.add`, at display size, for the overlay."""

    def __init__(self, config: Config, keep: int = LIVE_IMAGE_FRAMES) -> None:
        super().__init__(None, config)
        self._keep = keep
        self._labels: OrderedDict[int, np.ndarray] = OrderedDict()
        self._images: OrderedDict[int, bytes] = OrderedDict()
        self._count = 0
        self._size_wh: tuple[int, int] | None = None
        self._live_lock = threading.Lock()

    def put(self, index: int, labels: np.ndarray, image: np.ndarray | None) -> None:
        """Keep frame ``index`` (labels ``(H, W)``; image ``(H, W, 3)`` RGB or None)."""
        h, w = labels.shape[:2]
        size = display_size((w, h))
        small = (
            cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST) if size != (w, h) else labels
        )
        jpeg = None
        if image is not None:
            rgb = np.asarray(image)
            if rgb.ndim == 2:
                rgb = cv2.cvtColor(rgb, cv2.COLOR_GRAY2RGB)
            rgb = cv2.resize(rgb[..., :3], size, interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(
                ".jpg",
                cv2.cvtColor(rgb.astype(np.uint8, copy=False), cv2.COLOR_RGB2BGR),
                [int(cv2.IMWRITE_JPEG_QUALITY), LIVE_JPEG_QUALITY],
            )
            jpeg = buf.tobytes() if ok else None
        with self._live_lock:
            self._size_wh = size
            self._labels[index] = np.ascontiguousarray(small)
            if jpeg is not None:
                self._images[index] = jpeg
            for store in (self._labels, self._images):
                while len(store) > self._keep:
                    store.popitem(last=False)
            self._count = max(self._count, index + 1)

    @property
    def has_masks(self) -> bool:
        return True

    @property
    def has_source(self) -> bool:
        return bool(self._images)

    @property
    def num_mask_frames(self) -> int:
        return self._count

    def labels(self, index: int) -> np.ndarray | None:
        with self._live_lock:
            return self._labels.get(index)

    def source(self, index: int) -> np.ndarray | None:
        with self._live_lock:
            jpeg = self._images.get(index)
        if jpeg is None:
            return None
        bgr = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class Viewer:
    """A replay viewer fed frame by frame from a segmentation network's loop.

    Example::

        viewer = mistool.Viewer("mistool.toml", port=8080)   # returns at once
        print("open", viewer.url)
        for labels in network_outputs:
            rows = viewer.add(labels)                         # this frame's rows
        viewer.close()
    """

    def __init__(
        self,
        config: Config | str | Path | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
    ) -> None:
        """Start the server (returns at once).

        Args:
            config: a :class:`~mistool.Config`, a path to ``mistool.toml``, or None
                (EndoVis'15 defaults).
            host: interface to listen on.
            port: first port to try (the next free one is taken when busy; 0 = any).

        Raises:
            MistoolError: bad config, host or port (one-line message).
        """
        from mistool.api import Tracker
        from mistool.viewer.app import LoadedSequence, ReplayViewer
        from mistool.viewer.replay import Replay, config_parts

        self.tracker = Tracker(config)
        """The tracker (:class:`mistool.Tracker`) every frame goes through."""
        cfg = self.tracker.config
        if cfg.camera is not None:
            guess = (int(round(2 * cfg.camera.cx + 1)), int(round(2 * cfg.camera.cy + 1)))
        else:
            guess = (720, 576)
        replay = Replay(
            cfg,
            num_frames=1,
            image_wh=guess,
            instruments=tuple(s.name for s in cfg.instruments),
            parts=config_parts(cfg),
        )
        self._frames = LiveFrames(cfg)
        self._lock = threading.Lock()
        self._closed = False
        self._viewer = ReplayViewer(
            LoadedSequence(replay, self._frames, "live"), host=host, port=port
        )
        self._viewer.timeline.growing = True
        self._viewer.timeline.follow = True

    @property
    def url(self) -> str:
        """The address to open in a browser."""
        return self._viewer.url

    @property
    def port(self) -> int:
        """The port the server really listens on."""
        return self._viewer.port

    @property
    def replay_viewer(self) -> ReplayViewer:
        """The underlying :class:`~mistool.viewer.ReplayViewer` (tests, benchmarks)."""
        return self._viewer

    @property
    def num_frames(self) -> int:
        """Frames added so far."""
        return self.tracker.num_frames

    def add(self, labels: np.ndarray, image: np.ndarray | None = None) -> TrackTable:
        """Track one frame, show it, and return its rows.

        Args:
            labels: ``(H, W)`` integer label image (``(H, W, 3)`` RGB for colour masks).
            image: the frame's own RGB image ``(H, W, 3)`` uint8, shown under the mask
                (optional).

        Returns:
            This frame's rows, as :meth:`mistool.Tracker.update` returns them.

        Raises:
            MistoolError: a bad label image (wrong dtype or shape, size changed).
            RuntimeError: the viewer is closed.
        """
        with self._lock:
            if self._closed:
                raise RuntimeError("Viewer.add: the viewer is closed")
            rows = self.tracker.update(labels)
            index = self.tracker.num_frames - 1
            arr = np.asarray(labels)
            if index == 0:
                self._first_frame(arr.shape[1], arr.shape[0])
            cfg = self.tracker.config
            packed = to_labels(arr, f"frame {index}", colour=cfg.colour_masks, order="rgb")
            self._frames.put(index, packed, image)
            viewer = self._viewer
            viewer.apply(viewer.replay.compute(rows, index, index + 1))
        return rows

    def _first_frame(self, width: int, height: int) -> None:
        if (width, height) != self._viewer.replay.image_wh:
            self._viewer.set_image_size((width, height))

    def table(self) -> TrackTable:
        """Every frame so far as one table (as :meth:`mistool.Tracker.table`)."""
        with self._lock:
            return self.tracker.table()

    def close(self) -> None:
        """Stop the server (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._viewer.close()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
