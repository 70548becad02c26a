"""The 2D overlay: a frame's mask, colourised per instrument and part, blended over the
procedure's own video frame when there is one, with each part's rotated box drawn.

Frames are read lazily (one at a time, on demand) from the sequence folder or mask video,
and from ``source`` in ``mistool.toml`` (a video file or a folder of RGB frames). Nothing
here imports viser. Images are RGB uint8, shape ``(h, w, 3)``, at a display size no larger
than :data:`MAX_OVERLAY_SIDE` (the JPEG sent to the browser stays small).
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from mistool.config import Config
from mistool.errors import InputPathError, MaskFormatError
from mistool.sequence import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    FastPathGate,
    is_frame_file,
    list_frames,
    read_label_image,
    source_frame_names,
)
from mistool.viewer.replay import PALETTE, Replay


class _KernelsLoaded(FastPathGate):
    """The viewer's reads take the compiled PNG decoder only once it is loaded: its first
    use imports numba (~0.5-1 s of CPU), which the viewer must not wait for (nor its URL,
    nor its first picture). Until then OpenCV decodes (the same pixels:
    ``tests/test_png_decoder_fuzz.py``), and the first read starts loading the decoder in
    a thread."""

    def __init__(self) -> None:
        super().__init__()
        self._loaded = threading.Event()
        self._started = False
        self._start_lock = threading.Lock()

    @property
    def open(self) -> bool:
        if self._loaded.is_set():
            return True
        with self._start_lock:
            if not self._started:
                self._started = True
                threading.Thread(target=self._load, name="mistool-png", daemon=True).start()
        return False

    def _load(self) -> None:
        from mistool import kernels
        from mistool.kernels import png

        kernels.load(png)  # (a kernel is loaded at its first call, not at import)
        self._loaded.set()

    def record(self, decoded: bool) -> None:
        """Nothing to count: the gate follows the loading only."""


#: OpenCV alone: the probe of a sequence's frame size, read before the viewer's URL and
#: before the tracking process is forked (no numba import, no thread before the fork).
_OPENCV_ONLY = FastPathGate(patience=0)

#: Longest side (px) of the overlay image sent to the browser.
MAX_OVERLAY_SIDE = 400
#: Colour (RGB) of mask pixels whose label is a part value but that no box explains.
UNASSIGNED_RGB = (200, 200, 200)
#: Background (RGB) where there is no source video.
BACKGROUND_RGB = (24, 24, 28)


class _VideoReader:
    """Random access to a video's frames (sequential reads are fast, seeks are not)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        if not self._cap.isOpened():
            raise MaskFormatError(f"{path}: cannot open as a video")
        self._next = 0
        self.num_frames = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.seeks = 0
        """Seeks so far (each decodes from the keyframe before the frame asked)."""

    def is_next(self, index: int) -> bool:
        """Whether ``index`` is read without a seek."""
        return index == self._next

    def read(self, index: int) -> np.ndarray | None:
        """The BGR (or grey) frame at ``index``, or None past the end."""
        if index != self._next:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, index)
            self.seeks += 1
        ok, img = self._cap.read()
        self._next = index + 1 if ok else -1
        return img if ok else None

    def close(self) -> None:
        self._cap.release()


#: Source video frames kept at display size (JPEG) around where the user scrubs.
AHEAD_FRAMES = 1500
#: JPEG quality of the frames kept (about 20 KB each at display size).
AHEAD_QUALITY = 90


class DecodedAhead:
    """A source video's frames at display size, decoded in order around where the user
    scrubs, so that random access does not seek for every frame.

    A seek decodes every frame from the keyframe before it (H.264 encoders put one every
    few seconds, or only one at the start): scrubbing the bundled sample's video cost
    ~70 ms a frame. When a frame is asked out of order, a worker thread with its own
    decoder seeks once to a little before it and decodes onwards, keeping up to
    ``capacity`` frames (JPEG at display size, least recently asked dropped first); a
    request far from what it is decoding moves it there.
    """

    def __init__(self, path: Path, size_wh: tuple[int, int], capacity: int = AHEAD_FRAMES) -> None:
        self.path = path
        self.size_wh = size_wh
        self.capacity = capacity
        self._items: OrderedDict[int, bytes] = OrderedDict()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._centre: int | None = None
        self._closed = False
        self._thread: threading.Thread | None = None
        self.decoded = 0
        """Frames the worker has decoded (tests, benchmarks)."""

    def get(self, index: int) -> np.ndarray | None:
        """The frame at display size (RGB uint8 ``(h, w, 3)``), if it is kept."""
        with self._lock:
            jpeg = self._items.get(index)
            if jpeg is not None:
                self._items.move_to_end(index)
        if jpeg is None:
            return None
        bgr = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        return None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def around(self, index: int) -> None:
        """Decode the frames around ``index`` (returns at once; the worker starts once)."""
        with self._lock:
            if self._closed:
                return
            self._centre = int(index)
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name="mistool-video-ahead", daemon=True
                )
                self._thread.start()
        self._wake.set()

    def _window(self, centre: int) -> range:
        start = max(0, centre - self.capacity // 4)
        return range(start, start + self.capacity)

    def _run(self) -> None:
        cap = cv2.VideoCapture(str(self.path), cv2.CAP_FFMPEG)
        try:
            while not self._closed:
                self._wake.wait()
                self._wake.clear()
                centre = self._centre
                if centre is not None and cap.isOpened():
                    self._fill(cap, self._window(centre))
        finally:
            cap.release()

    def _fill(self, cap: cv2.VideoCapture, window: range) -> None:
        """Decode ``window`` in order (from its first frame not kept), until it is done or
        a request falls outside it."""
        with self._lock:
            todo = [k for k in window if k not in self._items]
        if not todo:
            return
        cap.set(cv2.CAP_PROP_POS_FRAMES, todo[0])
        for k in range(todo[0], window.stop):
            centre = self._centre
            if self._closed or (centre is not None and centre not in window):
                self._wake.set()  # go there
                return
            ok, bgr = cap.read()
            if not ok:
                return
            self.decoded += 1
            small = cv2.resize(bgr, self.size_wh, interpolation=cv2.INTER_AREA)
            ok, buf = cv2.imencode(".jpg", small, [int(cv2.IMWRITE_JPEG_QUALITY), AHEAD_QUALITY])
            with self._lock:
                self._items[k] = buf.tobytes()
                self._items.move_to_end(k)
                while len(self._items) > self.capacity:
                    self._items.popitem(last=False)

    def close(self) -> None:
        """Stop the worker."""
        with self._lock:
            self._closed = True
            thread = self._thread
        self._wake.set()
        if thread is not None:
            thread.join(timeout=10.0)


def find_frame_file(folder: Path) -> Path | None:
    """One label image of ``folder`` (the first the folder lists, not the first in frame
    order), or None when it has none: a look at a few entries, not a listing of them all.

    Raises:
        InputPathError: the folder cannot be listed, or the frame found is a dangling or
            looping symlink.
    """
    try:
        with os.scandir(folder) as it:
            for entry in it:
                if entry.name.startswith("."):
                    continue
                if os.path.splitext(entry.name)[1].lower() not in IMAGE_EXTENSIONS:
                    continue
                if is_frame_file(entry):
                    return Path(entry.path)
    except OSError as exc:
        raise InputPathError(f"{folder}: cannot list folder: {exc.strerror or exc}") from None
    return None


class FrameStore:
    """Lazy, random-access frames of a sequence: label images and source video frames.

    Thread-safe (one lock); a small LRU cache keeps the most recent decoded frames.

    A folder's frames are listed here, unless ``defer_listing``: then only one of its
    frames is looked for (:attr:`probe_file`: the image size, and a folder without label
    images is reported at once), and the ordered frame names come later, from
    :meth:`set_mask_names` (``mistool serve``: the background job lists the folder, so the
    server starts at once whatever the procedure's length). Until then :meth:`labels`
    returns None and :attr:`listed` is False. A ``source`` folder is then listed by
    :meth:`list_source` (the viewer runs it in a thread once its server is up).
    """

    def __init__(
        self,
        sequence: Path | None,
        config: Config,
        *,
        cache_frames: int = 8,
        defer_listing: bool = False,
    ) -> None:
        """
        Args:
            sequence: the folder of label images or the mask video (None: no masks).
            config: the sequence's config (``source``, colour masks).
            cache_frames: decoded frames kept in memory.
            defer_listing: do not list a folder's frames (see the class docstring).
        """
        self.config = config
        self._gate = _KernelsLoaded()  # the compiled PNG decoder once it is loaded
        self._lock = threading.Lock()
        self._cache: OrderedDict[tuple[str, int], np.ndarray | None] = OrderedDict()
        self._cache_frames = cache_frames
        self._mask_dir: Path | None = None
        # Names, not paths: building 100,000 Path objects costs a second.
        self._mask_names: list[str] = []
        self._listed = True
        self.probe_file: Path | None = None
        """One label image of the folder (the first in frame order when listed here)."""
        self._mask_video: _VideoReader | None = None
        if sequence is not None:
            if sequence.is_dir():
                self._mask_dir = sequence
                if defer_listing:
                    self._listed = False
                    self.probe_file = find_frame_file(sequence)
                else:
                    self._mask_names = [f.name for f in list_frames(sequence)]
                    if self._mask_names:
                        self.probe_file = sequence / self._mask_names[0]
            elif sequence.suffix.lower() in VIDEO_EXTENSIONS:
                self._mask_video = _VideoReader(sequence)
        self._source_dir: Path | None = None
        self._source_names: list[str] = []
        self._source_listed = True
        self._source_video: _VideoReader | None = None
        self._ahead: DecodedAhead | None = None
        src = config.source
        if src is not None:
            if not src.exists():
                raise InputPathError(
                    f"{config.path or 'mistool.toml'}: source {src} does not "
                    "exist; fix 'source' or remove it"
                )
            if src.is_dir():
                self._source_dir = src
                if defer_listing:
                    self._source_listed = False  # by list_source(), once the server is up
                else:
                    self._source_names = source_frame_names(src)
            else:
                self._source_video = _VideoReader(src)

    def list_source(self) -> None:
        """List a source folder whose listing was deferred (``defer_listing``: 0.3 s at
        90,000 frames, which the viewer spends in a thread once its server is up, not
        before); until then :meth:`source` returns None and :attr:`listed` is False."""
        if self._source_listed or self._source_dir is None:
            return
        try:
            names = source_frame_names(self._source_dir)
        except OSError:  # gone or unreadable since the start: shown without it
            names = []
        with self._lock:
            self._source_names = names
            self._source_listed = True
            for key in [k for k in self._cache if k[0] == "source"]:
                del self._cache[key]

    def set_mask_names(self, names: list[str]) -> None:
        """Give the folder's frame file names, in frame order (a deferred listing)."""
        with self._lock:
            self._mask_names = list(names)
            self._listed = True
            for key in [k for k in self._cache if k[0] == "mask"]:
                del self._cache[key]

    @property
    def listed(self) -> bool:
        """Whether the mask and source frames are known (False only until a deferred
        listing is given with :meth:`set_mask_names` or made by :meth:`list_source`)."""
        return self._listed and self._source_listed

    @property
    def mask_files(self) -> list[Path]:
        """The label image files, in frame order (empty for a mask video, or while a
        deferred listing is pending)."""
        if self._mask_dir is None:
            return []
        return [self._mask_dir / name for name in self._mask_names]

    @property
    def has_masks(self) -> bool:
        """Whether label images can be read (a deferred listing: once it is given)."""
        return bool(self._mask_names) or self.probe_file is not None or self._mask_video is not None

    @property
    def has_source(self) -> bool:
        """Whether the procedure's own video frames can be read."""
        listed = self._source_listed
        return bool(self._source_names) or not listed or self._source_video is not None

    def mask_shape(self) -> tuple[int, int] | None:
        """``(H, W)`` of the label images, from one of them (:attr:`probe_file`, or a mask
        video's first frame); None without masks.

        Raises:
            MistoolError: that frame cannot be read as a label image.
        """
        if self._mask_video is not None:
            first = self.labels(0)
        elif self.probe_file is not None:
            first = read_label_image(
                self.probe_file, colour=self.config.colour_masks, gate=_OPENCV_ONLY
            )
        else:
            return None
        return None if first is None else (int(first.shape[0]), int(first.shape[1]))

    @property
    def num_mask_frames(self) -> int:
        """Number of mask frames (0 without masks, or while a deferred listing is pending)."""
        if self._mask_video is not None:
            return self._mask_video.num_frames
        return len(self._mask_names)

    def _cached(self, key: tuple[str, int]) -> tuple[bool, np.ndarray | None]:
        if key in self._cache:
            self._cache.move_to_end(key)
            return True, self._cache[key]
        return False, None

    def _store(self, key: tuple[str, int], value: np.ndarray | None) -> None:
        self._cache[key] = value
        while len(self._cache) > self._cache_frames:
            self._cache.popitem(last=False)

    # Files are decoded outside the lock (two threads can decode two frames at once);
    # videos are read under it (one capture, sequential state).
    def labels(self, index: int) -> np.ndarray | None:
        """The ``(H, W)`` label image of frame ``index`` (None when there is none)."""
        with self._lock:
            hit, value = self._cached(("mask", index))
            if hit:
                return value
            if self._mask_video is not None:
                img = self._mask_video.read(index)
                value = (
                    None
                    if img is None
                    else (cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img)
                )
                self._store(("mask", index), value)
                return value
            if not self._listed:
                return None  # not known yet (and not cached: known later)
            names = self._mask_names
        value = None
        if self._mask_dir is not None and 0 <= index < len(names):
            path = self._mask_dir / names[index]
            value = read_label_image(path, colour=self.config.colour_masks, gate=self._gate)
        with self._lock:
            self._store(("mask", index), value)
        return value

    def source(self, index: int) -> np.ndarray | None:
        """The RGB source frame ``index`` (None when there is none)."""
        with self._lock:
            hit, value = self._cached(("source", index))
            if hit:
                return value
            if not self._source_listed:
                return None  # not known yet (and not cached: known later)
            img = None
            if self._source_video is not None:
                img = self._source_video.read(index)
            names = self._source_names
        if img is None and self._source_dir is not None and 0 <= index < len(names):
            img = cv2.imread(str(self._source_dir / names[index]), cv2.IMREAD_COLOR)
        value = None
        if img is not None:
            value = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB if img.ndim == 2 else cv2.COLOR_BGR2RGB)
        with self._lock:
            self._store(("source", index), value)
        return value

    def source_at(self, index: int, size_wh: tuple[int, int]) -> np.ndarray | None:
        """The RGB source frame ``index`` resized to ``size_wh`` (w, h) (None when there is
        none). A video frame asked out of order comes from :class:`DecodedAhead` when it
        has it, and sets it decoding around that frame otherwise; frames asked in order
        (playback) are read as they come."""
        video = self._source_video
        ahead = None
        if video is not None:
            with self._lock:
                if self._ahead is None or self._ahead.size_wh != size_wh:
                    if self._ahead is not None:
                        self._ahead.close()
                    self._ahead = DecodedAhead(video.path, size_wh)
                ahead = self._ahead
                in_order = video.is_next(index) or ("source", index) in self._cache
            small = ahead.get(index)
            if small is not None:
                return small
            if not in_order:
                ahead.around(index)
        src = self.source(index)
        if src is None:
            return None
        return cv2.resize(src, size_wh, interpolation=cv2.INTER_AREA)

    def close(self) -> None:
        """Release open videos (and stop decoding ahead)."""
        if self._ahead is not None:
            self._ahead.close()
        for v in (self._mask_video, self._source_video):
            if v is not None:
                v.close()


def display_size(image_wh: tuple[int, int], max_side: int = MAX_OVERLAY_SIDE) -> tuple[int, int]:
    """(w, h) of the overlay for an image of size ``image_wh``, longest side <= max_side."""
    w, h = image_wh
    s = min(1.0, max_side / max(w, h))
    return max(1, int(round(w * s))), max(1, int(round(h * s)))


class OverlayRenderer:
    """Draws a frame's overlay: colourised mask, source blend, rotated boxes."""

    def __init__(
        self, replay: Replay, frames: FrameStore, max_side: int = MAX_OVERLAY_SIDE
    ) -> None:
        self.replay = replay
        self.frames = frames
        self.size_wh = display_size(replay.image_wh, max_side)
        self._scale = self.size_wh[0] / replay.image_wh[0]
        self._build_tables()

    def _build_tables(self) -> None:
        """Lookup tables for the replay's instruments (built again when it gains some)."""
        replay = self.replay
        self._tables_for = len(replay.instruments)
        cfg = replay.config
        parts = replay.parts
        # Part lookup for label values: 0 = background, p + 1 = parts[p].
        self._own_values = bool(cfg.instruments)
        self._lut_part = np.zeros(65536, dtype=np.uint8)
        self._lut_inst = np.full(65536, 255, dtype=np.uint8)  # 255 = decided by the boxes
        if not cfg.colour_masks:
            for part, (lo, hi) in cfg.parts.items():
                if part in parts:
                    self._lut_part[lo : hi + 1] = parts.index(part) + 1
            for spec in cfg.instruments:
                if spec.name not in replay.instruments:
                    continue
                i = replay.instruments.index(spec.name)
                for part, (lo, hi) in spec.parts.items():
                    if part in parts:
                        self._lut_part[lo : hi + 1] = parts.index(part) + 1
                        self._lut_inst[lo : hi + 1] = i
        # Colour table: [colour class, part] -> RGB. Instruments cycle through the palette
        # (as in 3D), so there are at most len(PALETTE) classes, plus one for unassigned.
        n_i, n_p = len(replay.instruments), len(parts)
        n_c = min(n_i, len(PALETTE))
        self._colours = np.zeros((n_c + 1, n_p + 1, 3), dtype=np.uint8)
        for c in range(n_c):
            for p, part in enumerate(parts):
                self._colours[c, p + 1] = replay.part_colour(c, part)
        self._colours[n_c, 1:] = UNASSIGNED_RGB
        # Instrument index (uint8; >= n_i means unassigned) -> colour class * (n_p + 1).
        classes = np.full(256, n_c, dtype=np.int64)
        classes[: min(n_i, 255)] = np.arange(min(n_i, 255)) % max(n_c, 1)
        self._lut_class = (classes * (n_p + 1)).astype(np.uint8)
        self._background = np.empty((self.size_wh[1], self.size_wh[0], 3), dtype=np.uint8)
        self._background[:] = BACKGROUND_RGB
        self._lut_rgb = np.zeros((1, 256, 3), dtype=np.uint8)
        self._lut_rgb[0, : (n_c + 1) * (n_p + 1)] = self._colours.reshape(-1, 3)

    def _part_image(self, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Per display pixel: part index (0 = none) and, for own-value configs, instrument."""
        w, h = self.size_wh
        small = cv2.resize(labels, (w, h), interpolation=cv2.INTER_NEAREST)
        if self.replay.config.colour_masks:
            part: np.ndarray = np.zeros((h, w), dtype=np.uint8)
            inst = np.full((h, w), 255, dtype=np.uint8)
            cfg = self.replay.config
            specs = [(None, cfg.parts)] + [(s.name, s.parts) for s in cfg.instruments]
            for name, table in specs:
                for pname, (lo, hi) in table.items():
                    if pname not in self.replay.parts:
                        continue
                    m = (small >= lo) & (small <= hi)
                    part[m] = self.replay.parts.index(pname) + 1
                    if name in self.replay.instruments:
                        inst[m] = self.replay.instruments.index(name)
            return part, inst if cfg.instruments else None
        if small.dtype == np.uint8:  # the common case: OpenCV's table lookup
            part = cv2.LUT(small, self._lut_part[:256])
            return part, (cv2.LUT(small, self._lut_inst[:256]) if self._own_values else None)
        idx = small.astype(np.intp, copy=False)
        part = self._lut_part[idx]
        return part, (self._lut_inst[idx] if self._own_values else None)

    def render(self, frame: int, opacity: float = 0.6, boxes: bool = True) -> np.ndarray:
        """The overlay of ``frame``: RGB uint8 ``(h, w, 3)`` at :attr:`size_wh`.

        Args:
            frame: frame index.
            opacity: mask opacity over the source frame (or the dark background), [0, 1].
            boxes: draw each part's rotated box.
        """
        replay = self.replay
        if len(replay.instruments) != self._tables_for:
            self._build_tables()
        base = self.backdrop(frame)
        labels = self.frames.labels(frame)
        corners = replay.corners[frame] * self._scale if 0 <= frame < replay.num_frames else None
        if labels is not None:
            part, inst = self._part_image(labels)
            if inst is None:
                inst = self._instances_from_boxes(part, corners)
            # One code per pixel, (instrument, part) -> colour through a 256-entry LUT.
            code = cv2.LUT(inst, self._lut_class)
            code += part
            colour = cv2.LUT(cv2.merge([code, code, code]), self._lut_rgb)
            mask = (part > 0).view(np.uint8)
            a = float(np.clip(opacity, 0.0, 1.0))
            if a > 0 and cv2.countNonZero(mask):
                blended = cv2.addWeighted(base, 1.0 - a, colour, a, 0.0)
                cv2.copyTo(blended, mask, base)
        if boxes and corners is not None:
            self._draw_boxes(base, corners)
        return base

    def backdrop(self, frame: int) -> np.ndarray:
        """The image the mask is blended over: the source video frame at display size
        (RGB uint8, a new array), or a dark background without one. Every image shown
        under the overlay (GUI panel, frustum, Endoscope view) comes from here."""
        src = self.frames.source_at(frame, self.size_wh)
        return src if src is not None else self._background.copy()

    def _instances_from_boxes(self, part: np.ndarray, corners: np.ndarray | None) -> np.ndarray:
        """Instrument index per pixel for merged masks: the instrument whose box of that
        part covers the pixel (later instruments win overlaps); unassigned elsewhere."""
        n_i = len(self.replay.instruments)
        inst = np.full(part.shape, n_i, dtype=np.uint8)
        if corners is None:
            return inst
        raster = np.full(part.shape, 255, dtype=np.uint8)
        for p in range(corners.shape[1]):
            raster[:] = 255
            for i in range(n_i):
                c = corners[i, p]
                if np.isfinite(c).all():
                    cv2.fillPoly(raster, [np.round(c).astype(np.int32)], i)
            m = (part == p + 1) & (raster != 255)
            inst[m] = raster[m]
        return inst

    def _draw_boxes(self, img: np.ndarray, corners: np.ndarray) -> None:
        for i in range(corners.shape[0]):
            for p, pname in enumerate(self.replay.parts):
                c = corners[i, p]
                if not np.isfinite(c).all():
                    continue
                colour = self.replay.part_colour(i, pname)
                pts = np.round(c * 4).astype(np.int32)  # 2 fractional bits
                cv2.polylines(
                    img, [pts], True, colour, 2 if pname == "shaft" else 1, cv2.LINE_AA, shift=2
                )


def encode_jpeg(rgb: np.ndarray, quality: int = 80) -> bytes:
    """JPEG bytes of an RGB uint8 image."""
    ok, buf = cv2.imencode(
        ".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [int(cv2.IMWRITE_JPEG_QUALITY), int(quality)]
    )
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 RGB
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


class OverlayCache:
    """Rendered and JPEG-encoded overlays of recent and upcoming frames.

    During playback the viewer asks for the next frames ahead of time; one worker thread
    renders them while the current frame is on screen (OpenCV releases the GIL), so the
    frame update itself only sends bytes. Bounded: at most ``max_items`` frames.
    """

    def __init__(self, renderer: OverlayRenderer, max_items: int = 16, quality: int = 80) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.renderer = renderer
        self.quality = quality
        self._max = max_items
        self._lock = threading.Lock()
        self._items: OrderedDict[tuple[int, float, bool], tuple[np.ndarray, bytes]] = OrderedDict()
        self._pending: set[tuple[int, float, bool]] = set()
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mistool-overlay")
        self.hits = 0
        self.misses = 0

    def _make(self, key: tuple[int, float, bool]) -> tuple[np.ndarray, bytes]:
        rgb = self.renderer.render(key[0], key[1], key[2])
        return rgb, encode_jpeg(rgb, self.quality)

    def get(self, frame: int, opacity: float, boxes: bool) -> tuple[np.ndarray, bytes]:
        """The overlay (RGB) and its JPEG bytes, from the cache or rendered now."""
        key = (int(frame), round(float(opacity), 3), bool(boxes))
        with self._lock:
            item = self._items.get(key)
            if item is not None:
                self._items.move_to_end(key)
                self.hits += 1
                return item
        self.misses += 1
        known = self.renderer.frames.listed  # a render without the masks is not kept
        item = self._make(key)
        if known:
            self._put(key, item)
        return item

    def invalidate(self, lo: int, hi: int) -> None:
        """Forget the overlays of frames ``[lo, hi)`` (their boxes changed)."""
        with self._lock:
            for key in [k for k in self._items if lo <= k[0] < hi]:
                del self._items[key]

    def peek(self, frame: int, opacity: float, boxes: bool) -> tuple[np.ndarray, bytes] | None:
        """The cached overlay, or None (never renders)."""
        key = (int(frame), round(float(opacity), 3), bool(boxes))
        with self._lock:
            item = self._items.get(key)
            if item is not None:
                self._items.move_to_end(key)
                self.hits += 1
        return item

    def submit(self, fn: Callable[..., None], *args: object) -> None:
        """Run ``fn(*args)`` on the overlay worker (after the jobs already queued)."""
        self._pool.submit(fn, *args)

    def _put(self, key: tuple[int, float, bool], item: tuple[np.ndarray, bytes]) -> None:
        with self._lock:
            self._items[key] = item
            self._items.move_to_end(key)
            while len(self._items) > self._max:
                self._items.popitem(last=False)

    def prefetch(self, frames: list[int], opacity: float, boxes: bool) -> None:
        """Render these frames in the background (skipping cached or pending ones)."""
        for frame in frames:
            key = (int(frame), round(float(opacity), 3), bool(boxes))
            with self._lock:
                if key in self._items or key in self._pending:
                    continue
                self._pending.add(key)
            self._pool.submit(self._background, key)

    def _background(self, key: tuple[int, float, bool]) -> None:
        try:
            known = self.renderer.frames.listed
            item = self._make(key)
            if known:
                self._put(key, item)
        except Exception:  # noqa: BLE001 - the frame is rendered again on demand
            pass
        finally:
            with self._lock:
                self._pending.discard(key)

    def close(self) -> None:
        """Stop the worker."""
        self._pool.shutdown(wait=True, cancel_futures=True)
