"""Reading mask sequences, one frame at a time (memory does not grow with their length).

A *sequence* is one of:

- a **folder of label images**: every file with an image extension (``.png``, ``.bmp``,
  ``.tif``/``.tiff``, ``.pgm``/``.ppm``, ``.jpg``/``.jpeg``, ``.webp``) is a frame; frame
  order is the *natural* sort of the names (``frame2.png`` before ``frame10.png``). Other
  files (``mistool.toml``, ``truth.csv``, ``README``), hidden files and sub-folders are
  ignored. A file with an image extension that does not decode is an error.
- a **mask video** (``.avi``, ``.mp4``, ``.mov``, ``.mkv``, ``.m4v``, ``.mpg``/``.mpeg``,
  ``.wmv``), e.g. EndoVis'15 ``Segmentation.avi``, read with OpenCV's FFmpeg backend.
- an **iterable of numpy arrays** (a segmentation network's own loop, in-process).

``mistool.toml`` beside the frames (in the folder, or beside the video) says what the
pixel values mean; see :mod:`mistool.config`.

Pixel formats, each turned into one integer *label image* of shape ``(H, W)``:

- 8-bit or 16-bit single-channel images: the pixel values are the labels (uint8/uint16).
- palette PNGs: the palette **index** is the label (OpenCV expands palettes to colours, so
  the colours are mapped back to indices with the file's ``PLTE`` chunk; palette entries
  that share one colour cannot be told apart and read as the lowest such index).
- 3- or 4-channel images whose colour channels are equal (grey saved as RGB, alpha
  ignored): the shared channel.
- colour masks, when the config gives parts as ``"#rrggbb"`` colours
  (``Config.colour_masks``): each pixel is packed as ``r << 16 | g << 8 | b`` (uint32), the
  same packing as :func:`mistool.config.pack_rgb`; grey pixels pack as ``r = g = b``.
  Numpy arrays given by the caller are taken as **RGB**; files are decoded as BGR and
  packed accordingly.

Mask videos (and folders of JPEG masks, treated the same): the lossy codec smears label
values around each part's edges (the reason the paper masks by *intensity range*). For such
input every part given as a single value ``v`` is widened to ``[v - t, v + t]`` with
``t =`` :data:`VIDEO_TOLERANCE` (15), narrowed where needed so that the ranges of different
values never overlap; parts given as ``[lo, hi]`` ranges are used as given. Colour masks
are packed exactly (no tolerance), so they only work with a lossless codec. Grey videos
are converted to one channel with OpenCV's BGR-to-grey conversion. The smear is not
reported as unknown label values: there a value must cover ``min_area_px`` pixels of a
frame to count, and values up to the tolerance are background.

OpenCV's own log lines about corrupt files are silenced (log level SILENT) while mistool
reads a sequence: mistool reports them itself as one-line :class:`MistoolError` (the
codecs' own stderr lines, e.g. libpng's, are filtered by the command line).

Resource limits: a frame's size is read from its header (PNG, JPEG, BMP, PNM; a video's
stream) and checked against ``Config.max_pixels`` (default
:data:`mistool.config.MAX_PIXELS`, 50 MP) *before* decoding, so a 74-byte PNG claiming
100000 x 100000 pixels is refused at once. A mask video that ends before the frame count
in its header, and a ``source`` that disagrees with the masks in frame count or size, are
reported as :class:`~mistool.errors.InputWarning`.
"""

from __future__ import annotations

import errno
import math
import os
import re
import struct
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mistool.config import CONFIG_NAME, MAX_PIXELS, Config, ValueRange, load_config, preset_hint
from mistool.errors import InputPathError, InputWarning, MaskFormatError
from mistool.lens import fit_camera
from mistool.pngdecode import PngImage, decode_png

IMAGE_EXTENSIONS: frozenset[str] = frozenset(
    {".png", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm", ".jpg", ".jpeg", ".webp"}
)
VIDEO_EXTENSIONS: frozenset[str] = frozenset(
    {".avi", ".mp4", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".wmv"}
)
#: Half-width (label units) of the range a single label value is widened to in mask videos.
VIDEO_TOLERANCE: int = 15
_LOSSY_EXTENSIONS = frozenset({".jpg", ".jpeg"})

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple[Any, ...]:
    """Sort key that orders the numbers inside names numerically (``a2`` < ``a10``)."""
    chunks = _DIGITS.split(name)
    return tuple(int(c) if i % 2 else c.lower() for i, c in enumerate(chunks)) + (name,)


#: Every ASCII digit to "0": names equal under it have their digit runs at the same places.
_DIGIT_SHAPE = str.maketrans("123456789", "000000000")


def natural_order(names: list[str]) -> list[int]:
    """Indices that sort ``names`` as :func:`natural_key` does.

    Frame names usually differ only in equally wide numbers (``000123.png``): their
    natural order is then their plain string order, found without building a key per
    name (a fifth of a second at 100,000 frames).
    """
    if names:
        shape = names[0].translate(_DIGIT_SHAPE)
        if all(n.translate(_DIGIT_SHAPE) == shape for n in names):
            return sorted(range(len(names)), key=names.__getitem__)
    keys = [natural_key(n) for n in names]
    return sorted(range(len(names)), key=keys.__getitem__)


def _quiet_opencv() -> None:
    """Silence OpenCV's/FFmpeg's own stderr warnings; mistool reports problems itself."""
    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # pragma: no cover - very old OpenCV
        pass
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


# --- pixel formats ---------------------------------------------------------------------


def _png_palette(data: bytes) -> np.ndarray | None:
    """The PLTE of a palette PNG as packed ``r<<16|g<<8|b`` (uint32, one per index), or
    None when ``data`` is not a palette PNG."""
    if len(data) < 33 or not data.startswith(_PNG_SIGNATURE) or data[25] != 3:
        return None
    pos = 8
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        if kind == b"PLTE":
            rgb = np.frombuffer(data[pos + 8 : pos + 8 + length], dtype=np.uint8)
            rgb = rgb[: len(rgb) // 3 * 3].reshape(-1, 3).astype(np.uint32)
            return (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]
        if kind in (b"IDAT", b"IEND"):
            return None
        pos += 12 + length
    return None


def _pack_bgr(img: np.ndarray) -> np.ndarray:
    """(H, W, >=3) uint8 BGR -> (H, W) uint32 ``r<<16|g<<8|b``."""
    b, g, r = (img[..., i].astype(np.uint32) for i in range(3))
    return (r << 16) | (g << 8) | b


def _palette_indices(img: np.ndarray, palette: np.ndarray, where: str) -> np.ndarray:
    """Map a palette PNG decoded to BGR back to its palette indices, (H, W) uint8."""
    packed = _pack_bgr(img)
    keys, first = np.unique(palette, return_index=True)  # lowest index per colour
    pos = np.searchsorted(keys, packed).clip(0, len(keys) - 1)
    if not np.array_equal(keys[pos], packed):
        raise MaskFormatError(f"{where}: palette PNG has colours outside its palette")
    return first[pos].astype(np.uint8)


def to_labels(
    img: np.ndarray,
    where: str,
    *,
    colour: bool,
    order: str = "bgr",
    palette: np.ndarray | None = None,
) -> np.ndarray:
    """Turn a decoded image or a caller's array into an ``(H, W)`` integer label image.

    Args:
        img: ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, 4)`` array.
        where: file or frame name used in error messages.
        colour: pack colours as ``r<<16|g<<8|b`` (uint32) instead of requiring grey.
        order: channel order of ``img``: ``"bgr"`` (OpenCV-decoded) or ``"rgb"`` (caller).
        palette: packed PLTE colours when ``img`` was a palette PNG (then, unless
            ``colour``, the label is the palette index).

    Returns:
        uint8/uint16 labels, or uint32 packed colours when ``colour``.
    """
    arr = np.asarray(img)
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.ndim == 2:
        arr = _integer_labels(arr, where)
        if colour:
            if arr.dtype != np.uint8:
                raise MaskFormatError(
                    f'{where}: colour masks ("#rrggbb" in mistool.toml) '
                    f"need 8-bit images, got {arr.dtype}"
                )
            v = arr.astype(np.uint32)
            return (v << 16) | (v << 8) | v
        return arr
    if arr.ndim != 3 or arr.shape[2] not in (3, 4) or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise MaskFormatError(
            f"{where}: expected a label image of shape (H, W) or (H, W, 3), got shape {arr.shape}"
        )
    arr = arr[..., :3]
    if order == "rgb":
        arr = arr[..., ::-1]
    if colour:
        if arr.dtype != np.uint8:
            raise MaskFormatError(f"{where}: colour masks need 8-bit images, got {arr.dtype}")
        return _pack_bgr(arr)
    if palette is not None:
        return _palette_indices(arr, palette, where)
    c0 = arr[..., 0]
    if not (np.array_equal(c0, arr[..., 1]) and np.array_equal(c0, arr[..., 2])):
        hint = ""
        if arr.dtype == np.uint8:
            hint = preset_hint(np.unique(_pack_bgr(arr)).tolist(), colour=True)
        raise MaskFormatError(
            f"{where}: colour pixels (channels differ) but mistool.toml gives grey label "
            'values; give the parts as "#rrggbb" colours in [parts] or [[instrument]]' + hint
        )
    return _integer_labels(np.ascontiguousarray(c0), where)


def _integer_labels(arr: np.ndarray, where: str) -> np.ndarray:
    """Single-channel array -> uint8/uint16 labels (caller arrays may be int64, bool...)."""
    if arr.dtype in (np.uint8, np.uint16):
        return arr
    if arr.dtype == np.bool_:
        return arr.astype(np.uint8)
    if arr.dtype.kind == "f":
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise MaskFormatError(
                f"{where}: expected integer label values, got non-integer {arr.dtype} pixels"
            )
    elif arr.dtype.kind not in "iu":
        raise MaskFormatError(f"{where}: expected an integer label image, got dtype {arr.dtype}")
    if arr.size == 0:
        raise MaskFormatError(f"{where}: empty image, shape {arr.shape}")
    lo, hi = arr.min(), arr.max()
    if lo < 0 or hi > 65535:
        raise MaskFormatError(f"{where}: label values must be in 0..65535, found {lo}..{hi}")
    return arr.astype(np.uint8 if hi <= 255 else np.uint16)


def _png_labels(png: PngImage, where: str, colour: bool) -> np.ndarray:
    """Labels of a PNG :func:`~mistool.pngdecode.decode_png` decoded, exactly as
    :func:`to_labels` gives them from OpenCV's decoding of the same file (a palette
    image: the lowest index of each pixel's colour, or the packed colour)."""
    if png.palette is None:
        return to_labels(png.pixels, where, colour=colour)
    if colour:
        return png.palette[png.pixels]
    keys, first = np.unique(png.palette, return_index=True)  # lowest index per colour
    lut = first[np.searchsorted(keys, png.palette)].astype(np.uint8)
    return lut[png.pixels]


class FastPathGate:
    """Stops trying :func:`~mistool.pngdecode.decode_png` on a sequence whose files it
    keeps declining (e.g. every frame has a chunk it leaves to OpenCV), so they cost no
    wasted inflate. Counters
    are updated from worker threads; a lost update only delays the decision."""

    def __init__(self, patience: int = 8) -> None:
        self.tried = 0
        self.declined = 0
        self.patience = patience

    @property
    def open(self) -> bool:
        """Whether the fast path is still worth trying."""
        return self.declined < self.patience or 4 * self.declined < self.tried

    def record(self, decoded: bool) -> None:
        """Count one attempt (``decoded``: the fast path took the file)."""
        self.tried += 1
        self.declined += not decoded


def header_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` from an image file's header (PNG, JPEG, BMP, PNM), without
    decoding; None when the format is another or the header is not recognised."""
    if data.startswith(_PNG_SIGNATURE) and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    if data.startswith(b"BM") and len(data) >= 26:
        w, h = struct.unpack("<ii", data[18:26])
        return abs(int(w)), abs(int(h))
    if data[:2] == b"\xff\xd8":
        return _jpeg_size(data)
    m = re.match(rb"P[1-6]\s+(?:#[^\n]*\s+)*(\d+)\s+(?:#[^\n]*\s+)*(\d+)", data[:512])
    if m:
        return int(m.group(1)), int(m.group(2))
    return None


#: JPEG start-of-frame markers (baseline, progressive, lossless...): they carry the size.
_JPEG_SOF = frozenset(
    {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
)


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    pos = 2
    while pos + 9 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        length = struct.unpack(">H", data[pos + 2 : pos + 4])[0]
        if marker in _JPEG_SOF:
            h, w = struct.unpack(">HH", data[pos + 5 : pos + 9])
            return int(w), int(h)
        pos += 2 + length
    return None


def check_pixels(size: tuple[int, int] | None, where: str, max_pixels: int) -> None:
    """Raise :class:`MaskFormatError` when a frame of ``size`` = ``(w, h)`` is empty or
    has more than ``max_pixels`` pixels (``max_pixels`` in mistool.toml raises the limit)."""
    if size is None:
        return
    w, h = size
    if w <= 0 or h <= 0:
        raise MaskFormatError(f"{where}: the image header says {w}x{h} pixels (an empty image)")
    if w * h > max_pixels:
        raise MaskFormatError(
            f"{where}: the image header says {w}x{h} = {w * h} pixels, more than the limit "
            f"of {max_pixels} (max_pixels in mistool.toml raises it)"
        )


def read_label_image(
    path: Path,
    *,
    colour: bool = False,
    gate: FastPathGate | None = None,
    max_pixels: int = MAX_PIXELS,
) -> np.ndarray:
    """Decode one label image file into an ``(H, W)`` label image (see module docs).

    Args:
        path: the image file.
        colour: pack colours (``Config.colour_masks``).
        gate: the sequence's fast-path gate, if any.
        max_pixels: largest ``width x height`` decoded, checked from the header first.

    Raises:
        MaskFormatError: the file does not decode, is too large, or its pixels are not
            labels.
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputPathError(f"{path}: cannot read: {exc.strerror or exc}") from None
    check_pixels(header_size(data), str(path), max_pixels)
    if gate is None or gate.open:
        png = decode_png(data, max_pixels)
        if gate is not None:
            gate.record(png is not None)
        if png is not None:
            return _png_labels(png, str(path), colour)
    try:
        img = (
            cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
            if data
            else None
        )
    except cv2.error:  # OpenCV's own limits (e.g. pixels of another format's header)
        img = None
    if img is None:
        raise MaskFormatError(
            f"{path}: cannot decode as an image (corrupt, truncated or not an image file)"
        )
    check_pixels((img.shape[1], img.shape[0]), str(path), max_pixels)
    palette = _png_palette(data) if img.ndim == 3 else None
    return to_labels(img, str(path), colour=colour, palette=palette)


# --- sequences -------------------------------------------------------------------------


@dataclass(frozen=True)
class Frame:
    """One frame of a sequence, not decoded yet (``load`` is thread-safe)."""

    index: int
    """0-based position in the sequence."""
    name: str
    """File name (folders), ``"<video>#<index>"`` (videos) or ``"frame <index>"`` (arrays)."""
    load: Callable[[], np.ndarray]
    """Decode the frame: returns the ``(H, W)`` integer label image."""


class MaskSequence:
    """A streaming sequence of label images.

    Iterating yields ``(index, name, labels)`` one frame at a time, decoding on the way;
    :meth:`frames` yields undecoded :class:`Frame` handles so a caller can decode in
    worker threads (then it must call :meth:`check_shape` in frame order).
    """

    def __init__(
        self,
        kind: str,
        name: str,
        config: Config,
        frames: Callable[[], Iterator[Frame]],
        num_frames: int | None,
        path: Path | None = None,
        lossy: bool = False,
    ) -> None:
        self.kind = kind
        """``"folder"``, ``"video"`` or ``"arrays"``."""
        self.name = name
        """A short name for the sequence (folder or video stem; ``"arrays"``)."""
        self.config = config
        """The effective config (for videos, single label values widened; module docs)."""
        self.num_frames = num_frames
        """Number of frames, or None when unknown (iterables; videos are approximate)."""
        self.path = path
        """The folder or video file, or None for arrays."""
        self.lossy = lossy
        """Frames from a lossy codec (videos, JPEG folders): label values are smeared."""
        self.shape: tuple[int, int] | None = None
        """``(H, W)`` of the frames, once the first frame was checked."""
        self.video: VideoSource | None = None
        """For a mask video: what a worker process needs to decode spans of its frames
        itself (:class:`VideoReader`); None otherwise."""
        self._frames = frames

    def frames(self) -> Iterator[Frame]:
        """Undecoded frames in order."""
        return self._frames()

    def check_shape(self, frame: Frame | str, shape: tuple[int, ...]) -> None:
        """Record the first frame's ``(H, W)``; raise if a later frame's size differs.

        Args:
            frame: the frame (or its name, for the message).
            shape: the frame's label image shape, ``(H, W)`` first.
        """
        shape = (int(shape[0]), int(shape[1]))
        if self.shape is None:
            self.shape = shape
        elif shape != self.shape:
            name = frame.name if isinstance(frame, Frame) else frame
            raise MaskFormatError(
                f"{name}: frame size changed mid-sequence: {shape[1]}x{shape[0]} px, "
                f"earlier frames are {self.shape[1]}x{self.shape[0]} px"
            )

    def __iter__(self) -> Iterator[tuple[int, str, np.ndarray]]:
        for frame in self.frames():
            labels = frame.load()
            self.check_shape(frame, labels.shape)
            yield frame.index, frame.name, labels

    def __repr__(self) -> str:
        return f"MaskSequence({self.kind} {self.name!r}, {self.num_frames} frames)"


def list_frames(folder: Path) -> list[Path]:
    """The label image files of a folder in natural order (other files ignored)."""
    return [folder / e.name for e in scan_frames(folder)]


def scan_frames(folder: Path, *, check_links: bool = True) -> list[os.DirEntry[str]]:
    """:func:`list_frames` as directory entries (their ``stat()`` is fetched once).

    Args:
        folder: the folder.
        check_links: check that every symlink names a file (one ``stat`` each; a dangling
            or looping one is an error here). False: symlinks are taken as frames, and one
            that is not is an error when it is read.
    """
    try:
        with os.scandir(folder) as it:
            entries = list(it)
    except OSError as exc:
        raise InputPathError(f"{folder}: cannot list folder: {exc.strerror or exc}") from None
    # Filtered and sorted on plain strings: an hour-long procedure has ~100,000 frames,
    # and this listing is on the way to the viewer's first picture.
    frames = [
        e
        for e in entries
        if not e.name.startswith(".")
        and os.path.splitext(e.name)[1].lower() in IMAGE_EXTENSIONS
        and (is_frame_file(e) if check_links or not e.is_symlink() else True)
    ]
    return [frames[i] for i in natural_order([e.name for e in frames])]


def is_frame_file(entry: os.DirEntry[str]) -> bool:
    """Whether a folder entry with an image extension is a frame file; a symlink that
    loops or dangles is an error (it names a frame that cannot be read)."""
    try:
        if entry.is_file():
            return True
    except OSError as exc:
        reason = "symlink loop" if exc.errno == errno.ELOOP else (exc.strerror or str(exc))
        raise InputPathError(f"{entry.path}: cannot read this frame: {reason}") from None
    if entry.is_symlink():
        raise InputPathError(
            f"{entry.path}: cannot read this frame: dangling symlink to {os.readlink(entry.path)}"
        )
    return False


def resolve(path: str | Path) -> tuple[Path, Config]:
    """A sequence path (folder or mask video) and its ``mistool.toml`` (or defaults).

    The config is read from the folder itself, or from the folder holding the video.

    Raises:
        InputPathError: the path does not exist or is neither a folder nor a mask video.
        ConfigError: ``mistool.toml`` is invalid.
    """
    p = Path(path).expanduser()
    if not p.exists():
        raise InputPathError(
            f"{p}: no such file or folder; expected a folder of label images or a mask video"
        )
    if p.is_dir():
        return p, load_config(p)
    if p.suffix.lower() in VIDEO_EXTENSIONS:
        return p, load_config(p.parent)
    if p.name == CONFIG_NAME:
        return p.parent, load_config(p)
    raise InputPathError(
        f"{p}: not a folder of label images or a mask video ({', '.join(sorted(VIDEO_EXTENSIONS))})"
    )


def open_sequence(
    source: str | Path | Iterable[np.ndarray],
    config: Config | None = None,
    *,
    files: Sequence[Path] | None = None,
) -> MaskSequence:
    """Open a sequence for streaming (nothing is decoded yet, except a video's header).

    Args:
        source: a folder of label images, a mask video file, or an iterable of ``(H, W)``
            (or ``(H, W, 3)`` RGB) integer arrays.
        config: what the pixels mean; None reads ``mistool.toml`` beside the frames
            (defaults for arrays).
        files: a folder's frame files as :func:`list_frames` gives them, when the caller
            has listed it already (a long folder is not listed twice).

    Raises:
        InputPathError: missing path, or a folder without label images.
        MaskFormatError: a video that cannot be opened or read.
        ConfigError: an invalid ``mistool.toml``.
    """
    _quiet_opencv()
    if isinstance(source, (str, os.PathLike)):
        path, found = resolve(source)
        config = config if config is not None else found
        if path.is_dir():
            return fit_lens(_open_folder(path, config, files))
        return fit_lens(_open_video(path, config))
    if isinstance(source, np.ndarray) and (
        source.ndim == 2 or (source.ndim == 3 and source.shape[2] in (3, 4))
    ):
        raise MaskFormatError(
            f"source: got one array of shape {source.shape}; pass a list "
            "of frames, e.g. [labels], or an (N, H, W) stack"
        )
    return fit_lens(_open_arrays(source, config if config is not None else Config()))


def fit_lens(seq: MaskSequence) -> MaskSequence:
    """Fit a calibration's camera to the masks' size (:func:`mistool.lens.fit_camera`).

    Only for a camera that knows its image size (from a calibration file): the first
    frame's size is read (one decode; a generator of arrays is not consumed: its first
    frame is kept). Masks that are a uniform scaling of the calibration get scaled
    intrinsics and an :class:`~mistool.errors.InputWarning` saying so (the command line
    prints it); any other size is
    a :class:`~mistool.errors.ConfigError`.
    """
    cam = seq.config.camera
    if cam is None or cam.image_wh is None:
        return seq
    frames = seq.frames()
    try:
        first = next(frames)
    except StopIteration:
        return seq
    shape = first.load().shape
    fitted, note = fit_camera(cam, (int(shape[1]), int(shape[0])), _calibration_name(seq.config))
    if note is not None:
        warnings.warn(note, InputWarning, stacklevel=3)
    seq.config = replace(seq.config, camera=fitted)
    if seq.kind == "arrays":  # do not lose the frame taken from a one-shot iterator
        make = seq._frames
        pending: list[tuple[Frame, Iterator[Frame]]] = [(first, frames)]

        def again() -> Iterator[Frame]:
            if pending:
                head, rest = pending.pop()
                yield head
                yield from rest
            else:
                yield from make()

        seq._frames = again
    return seq


def _calibration_name(config: Config) -> str:
    return str(config.calibration) if config.calibration is not None else "camera"


def _open_folder(folder: Path, config: Config, files: Sequence[Path] | None = None) -> MaskSequence:
    files = list_frames(folder) if files is None else files
    if not files:
        videos = sorted(p.name for p in folder.iterdir() if p.suffix.lower() in VIDEO_EXTENSIONS)
        hint = (
            f"; to read a mask video pass the file itself, e.g. {folder / videos[0]}"
            if videos
            else ""
        )
        raise InputPathError(
            f"{folder}: no label images "
            f"({', '.join(sorted(IMAGE_EXTENSIONS))}) in this folder{hint}"
        )
    colour = config.colour_masks
    gate = FastPathGate()
    limit = config.max_pixels

    def frames() -> Iterator[Frame]:
        for i, f in enumerate(files):
            yield Frame(i, f.name, _loader(f, colour, gate, limit))

    lossy = all(f.suffix.lower() in _LOSSY_EXTENSIONS for f in files)
    return MaskSequence(
        "folder",
        folder.resolve().name or str(folder),
        widen_for_video(config) if lossy else config,
        frames,
        len(files),
        folder,
        lossy=lossy,
    )


def _loader(
    path: Path, colour: bool, gate: FastPathGate, max_pixels: int
) -> Callable[[], np.ndarray]:
    return lambda: read_label_image(path, colour=colour, gate=gate, max_pixels=max_pixels)


def widen_for_video(config: Config, tolerance: int = VIDEO_TOLERANCE) -> Config:
    """The config with every single label value ``v`` widened to ``[v-t, v+t]`` (ranges
    kept), ``t`` narrowed so that ranges of different values never overlap."""
    if config.colour_masks or tolerance <= 0:
        return config
    others = sorted(set(_all_ranges(config)))

    def widen(r: ValueRange) -> ValueRange:
        lo, hi = r
        if lo != hi:
            return r
        t = tolerance
        for olo, ohi in others:
            if (olo, ohi) == r:
                continue
            if ohi < lo:
                t = min(t, (lo - ohi - 1) // 2)
            elif olo > hi:
                t = min(t, (olo - hi - 1) // 2)
        t = max(t, 0)
        return max(lo - t, 1 if lo > 0 else 0), hi + t

    parts = {p: widen(r) for p, r in config.parts.items()}
    instruments = tuple(
        replace(inst, parts={p: widen(r) for p, r in inst.parts.items()})
        for inst in config.instruments
    )
    return replace(config, parts=parts, instruments=instruments)


def _all_ranges(config: Config) -> list[ValueRange]:
    ranges = list(config.parts.values())
    for inst in config.instruments:
        ranges += list(inst.parts.values())
    return ranges


def _open_video(path: Path, config: Config) -> MaskSequence:
    cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    ok = cap.isOpened()
    count = _video_count(cap) if ok else 0
    if ok:
        size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        try:
            check_pixels(size, str(path), config.max_pixels)
        finally:
            cap.release()
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    ok = ok and cap.read()[0]
    cap.release()
    if not ok:
        raise MaskFormatError(
            f"{path}: cannot read as a video (corrupt, unsupported codec or not a video file)"
        )
    colour = config.colour_masks
    stem = path.stem
    widened = widen_for_video(config)

    def frames() -> Iterator[Frame]:
        vc = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
        check = _VideoCheck(path, widened, count)
        try:
            index = 0
            while True:
                ok, img = vc.read()
                if not ok:
                    break
                labels = _video_labels(img, f"{path}#{index}", colour)
                check.see(index, labels)
                yield Frame(index, f"{path.name}#{index}", _constant(labels))
                index += 1
            if index == 0:
                raise MaskFormatError(f"{path}: the video has no readable frame")
            check.finish(index)
        finally:
            vc.release()

    seq = MaskSequence(
        "video",
        stem,
        widened,
        frames,
        count if count > 0 else None,
        path,
        lossy=True,
    )
    seq.video = VideoSource(path.resolve(), widened, count)
    return seq


def _video_labels(img: np.ndarray, where: str, colour: bool) -> np.ndarray:
    """A decoded mask video frame (BGR or grey) -> its label image."""
    if colour:
        return _pack_bgr(img) if img.ndim == 3 else to_labels(img, where, colour=True)
    if img.ndim == 3:
        return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return to_labels(img, where, colour=False)


@dataclass(frozen=True)
class VideoSource:
    """A mask video as a worker process opens it (picklable; :class:`VideoReader`)."""

    path: Path
    """The video file (absolute)."""
    config: Config
    """The sequence's config (label values widened for the codec)."""
    count: int
    """Frames its header announces (0: unknown)."""


class VideoReader:
    """Decodes spans of a mask video's frames in frame order, as
    :meth:`MaskSequence.frames` does, for a worker process.

    No seeking (not frame-exact for every codec): the reader decodes from the first frame
    on, and a span after the previous one skips the frames in between with ``grab()``
    (decoded, not converted: about a quarter of a frame's cost); a span before its
    position reopens the video. The frames are therefore those of a sequential read.
    """

    def __init__(self, source: VideoSource) -> None:
        self.source = source
        self._cap: Any = None
        self._next = 0
        self._lut = _VideoCheck(source.path, source.config, source.count).lut

    def read(self, start: int, stop: int) -> list[tuple[np.ndarray, bool]]:
        """Frames ``start .. stop - 1`` (fewer at the end of the video) as ``(labels,
        looks corrupt)`` pairs (:data:`GARBAGE_FRACTION`)."""
        src = self.source
        if self._cap is None or self._next > start:
            self.close()
            self._cap, self._next = cv2.VideoCapture(str(src.path), cv2.CAP_FFMPEG), 0
        while self._next < start:
            if not self._cap.grab():
                return []
            self._next += 1
        out = []
        colour = src.config.colour_masks
        while self._next < stop:
            ok, img = self._cap.read()
            if not ok:
                break
            labels = _video_labels(img, f"{src.path}#{self._next}", colour)
            out.append((labels, _looks_corrupt(labels, self._lut)))
            self._next += 1
        return out

    def close(self) -> None:
        """Release the video."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def finish_video(source: VideoSource, frames: int, corrupt: Sequence[int]) -> None:
    """After the last frame of a video decoded by :class:`VideoReader` spans: the error
    and the warnings that :meth:`MaskSequence.frames` gives at its end (no readable
    frame; fewer frames than the header announces; frames that look corrupt)."""
    if frames == 0:
        raise MaskFormatError(f"{source.path}: the video has no readable frame")
    check = _VideoCheck(source.path, source.config, source.count)
    check.garbage = list(corrupt)
    check.finish(frames)


#: A mask video frame with more than this fraction of its pixels neither background nor
#: in a (widened) part range looks like decoded garbage (real smear is a thin edge).
GARBAGE_FRACTION: float = 0.2


class _VideoCheck:
    """Says what is odd about a mask video once it has been read: fewer frames than its
    header announces, frames that look like decoded garbage."""

    def __init__(self, path: Path, config: Config, count: int) -> None:
        self.path, self.count = path, count
        self.garbage: list[int] = []
        self.lut: np.ndarray | None = None
        if not config.colour_masks:
            known = np.zeros(256, np.uint8)
            known[: VIDEO_TOLERANCE + 1] = 1  # background and its smear
            for lo, hi in _all_ranges(config):
                known[max(lo, 0) : min(hi, 255) + 1] = 1
            self.lut = known

    def see(self, index: int, labels: np.ndarray) -> None:
        """Check one decoded 8-bit grey frame."""
        if _looks_corrupt(labels, self.lut):
            self.garbage.append(index)

    def finish(self, frames: int) -> None:
        """Warn (:class:`InputWarning`) about what was seen, after the last frame."""
        if self.count > frames:
            warnings.warn(
                f"{self.path}: the video ended after {frames} of the {self.count} frames its "
                "header announces (truncated or corrupt file); the rest is not tracked",
                InputWarning,
                stacklevel=3,
            )
        if self.garbage:
            shown = ", ".join(f"#{i}" for i in self.garbage[:5])
            more = ", ..." if len(self.garbage) > 5 else ""
            warnings.warn(
                f"{self.path}: {len(self.garbage)} frame(s) look corrupt ({shown}{more}: more "
                f"than {GARBAGE_FRACTION:.0%} of their pixels are no label value of "
                "mistool.toml); their instruments may be spurious",
                InputWarning,
                stacklevel=3,
            )


def _looks_corrupt(labels: np.ndarray, lut: np.ndarray | None) -> bool:
    """Whether a decoded 8-bit grey video frame has more than :data:`GARBAGE_FRACTION` of
    its pixels neither background nor a label value (``lut``: 1 for the known values;
    None: colour masks, not checked)."""
    if lut is None or labels.dtype != np.uint8 or labels.ndim != 2:
        return False
    unknown = labels.size - cv2.countNonZero(cv2.LUT(labels, lut))
    return unknown > GARBAGE_FRACTION * labels.size


def _video_count(cap: Any) -> int:
    """A video's frame count from its header (0 when unknown or absurd)."""
    value = cap.get(cv2.CAP_PROP_FRAME_COUNT)
    return int(value) if math.isfinite(value) and 0 < value < 2**31 else 0


def _constant(labels: np.ndarray) -> Callable[[], np.ndarray]:
    return lambda: labels


def _open_arrays(source: Iterable[np.ndarray], config: Config) -> MaskSequence:
    try:
        iterator_source = iter(source)
    except TypeError:
        raise MaskFormatError(
            f"source: expected a path or an iterable of label arrays, got {type(source).__name__}"
        ) from None
    try:
        count: int | None = len(source)  # type: ignore[arg-type]
    except TypeError:
        count = None
    colour = config.colour_masks
    used = False

    def frames() -> Iterator[Frame]:
        nonlocal used
        it = iterator_source if not used else iter(source)
        used = True
        for i, arr in enumerate(it):
            yield Frame(i, f"frame {i}", _array_loader(arr, f"frame {i}", colour))

    return MaskSequence("arrays", "arrays", config, frames, count)


def _array_loader(arr: Any, where: str, colour: bool) -> Callable[[], np.ndarray]:
    return lambda: to_labels(np.asarray(arr), where, colour=colour, order="rgb")


# --- what a command reads, and whether the source agrees with the masks ---------------


def input_files(path: Path, config: Config, frames: Sequence[Path] | None = None) -> list[Path]:
    """Every file a command reads for the sequence at ``path``: its frames (or the mask
    video), ``mistool.toml``, the ``source`` video or its frames, and any other file the
    config names (e.g. a calibration file). Outputs are checked against these
    (:func:`mistool.export.check_output`).

    ``frames``: the folder's frame files as :func:`list_frames` gives them, when the
    caller has listed it already (the listing is then passed to :func:`open_sequence`
    too: a long folder is listed once). The frames come first, in their order."""
    if frames is None:
        frames = list_frames(path) if path.is_dir() else [path]
    named = [config.path, config.source]
    named += [getattr(config.camera, f, None) for f in _field_names(config.camera)]
    named += [getattr(config, f, None) for f in _field_names(config)]
    added: list[Path] = []
    for item in named:
        if not isinstance(item, Path) or item in added:
            continue
        # (only a file with an image's extension can be one of the frames)
        if item.suffix.lower() in IMAGE_EXTENSIONS and item in frames:
            continue
        added.append(item)
        if item.is_dir() and item == config.source:
            added += [p for p in item.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS]
    return [*frames, *added]


def _field_names(obj: object) -> list[str]:
    import dataclasses

    return [f.name for f in dataclasses.fields(obj)] if dataclasses.is_dataclass(obj) else []


def source_info(source: Path, count: bool = True) -> tuple[int | None, tuple[int, int] | None]:
    """``(frame count, (width, height))`` of a ``source`` video or RGB frame folder, read
    from the video's header or the folder's first frame (None where unknown).

    Args:
        source: the video or the folder.
        count: count a folder's frames (a listing of all of them: 0.3 s at 90,000);
            without, the count is None and the size is read from the first image the
            folder lists (not the first in frame order).

    Raises:
        MaskFormatError: the video cannot be opened, or the folder's first frame does
            not decode (e.g. a folder of undecodable JPEGs).
    """
    _quiet_opencv()
    if source.is_dir():
        if count:
            files = [source / name for name in source_frame_names(source)]
        else:
            files = _first_image_listed(source)
        if not files:
            return (0 if count else None), None
        try:
            data = files[0].read_bytes()
            img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
        except (OSError, cv2.error):
            img = None
        if img is None:
            raise MaskFormatError(
                f"{files[0]}: the source frame does not decode (corrupt or not an image); "
                "fix 'source' in mistool.toml or remove it"
            )
        return (len(files) if count else None), (int(img.shape[1]), int(img.shape[0]))
    cap = cv2.VideoCapture(str(source), cv2.CAP_FFMPEG)
    try:
        if not cap.isOpened() or not cap.read()[0]:
            raise MaskFormatError(
                f"{source}: the source video cannot be read (corrupt, unsupported codec or "
                "not a video); fix 'source' in mistool.toml or remove it"
            )
        size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        return _video_count(cap) or None, size
    finally:
        cap.release()


def source_frame_names(folder: Path) -> list[str]:
    """The image files of a ``source`` folder, in frame order (names: 100,000 ``Path``
    objects would cost a second)."""
    with os.scandir(folder) as entries:
        names = [e.name for e in entries if os.path.splitext(e.name)[1].lower() in IMAGE_EXTENSIONS]
    names.sort(key=natural_key)
    return names


def _first_image_listed(folder: Path) -> list[Path]:
    """The first image file ``folder`` lists (not the first in frame order; empty: none),
    without listing them all."""
    with os.scandir(folder) as entries:
        for e in entries:
            if os.path.splitext(e.name)[1].lower() in IMAGE_EXTENSIONS:
                return [Path(e.path)]
    return []


def check_source(
    config: Config, num_frames: int | None, shape: tuple[int, int] | None
) -> list[str]:
    """Compare the config's ``source`` with the masks: warn (:class:`InputWarning`) when
    it has fewer frames than the masks or another size; returns the warning texts.

    Args:
        config: the sequence's config (nothing to check without ``source``).
        num_frames: number of mask frames, if known.
        shape: ``(H, W)`` of the masks, if known.

    Raises:
        MaskFormatError: the source cannot be read at all.
    """
    if config.source is None or not config.source.exists():
        return []
    # Without the masks' count (mistool serve before the tracking job lists them), a
    # source folder is not counted either: the server starts at once whatever its length.
    count, size = source_info(config.source, count=num_frames is not None)
    said = []
    if count is not None and num_frames is not None and count < num_frames:
        said.append(
            f"{config.source}: the source has {count} frame(s), the masks {num_frames}; "
            "later frames are shown without the source under the overlay"
        )
    if size is not None and shape is not None and size != (shape[1], shape[0]):
        said.append(
            f"{config.source}: the source is {size[0]}x{size[1]} px, the masks "
            f"{shape[1]}x{shape[0]} px; the overlay is stretched to fit"
        )
    for text in said:
        warnings.warn(text, InputWarning, stacklevel=2)
    return said


def unknown_values(labels: np.ndarray, config: Config) -> np.ndarray:
    """Label values present that are neither 0 nor any configured part value.

    Args:
        labels: (H, W) integer label image.
        config: the part value ranges (the instruments' own when it has
            ``[[instrument]]`` tables, else the shared ones).

    Returns:
        Sorted 1-D array of the unknown values (int64); empty when all are known.
    """
    arr = np.asarray(labels)
    if arr.dtype == np.uint8 or arr.dtype == np.uint16:
        hist = np.bincount(arr.ravel(), minlength=1)
        values = np.flatnonzero(hist)
    else:
        values = np.unique(arr)
    values = values.astype(np.int64)
    known = values == 0
    if config.instruments:
        ranges = [r for spec in config.instruments for r in spec.parts.values()]
    else:
        ranges = list(config.parts.values())
    for lo, hi in ranges:
        known |= (values >= lo) & (values <= hi)
    return values[~known]


def inputs_of(source: str | Path) -> list[Path]:
    """The files a command reads for one SOURCE argument: a sequence (folder, mask video,
    ``mistool.toml``) gives :func:`input_files`; anything else (a motion table) is itself."""
    p = Path(source).expanduser()
    if p.is_dir() or p.suffix.lower() in VIDEO_EXTENSIONS or p.name == CONFIG_NAME:
        try:
            return input_files(*resolve(p))
        except (InputPathError, MaskFormatError):
            return [p]
    return [p]
