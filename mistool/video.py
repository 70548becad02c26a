"""The replay as a video for slides (``mistool export-video``), rendered headless.

Each output frame, ``(H, W)`` = ``(panel + bar, 2 * panel width)``:

- left, the **3D view**: every instrument part as a cylinder (shaft, wrist, clasper:
  ``start_*_mm -> end_*_mm`` with the shaft's radius, the head thinner), drawn with OpenCV
  from a fixed oblique viewpoint (:class:`ObliqueView`: 35 deg around the camera's y axis,
  30 deg down; perspective), far parts first; the tips' trails over the last second, a
  floor grid (20 mm) under the scene, and the endoscope as a small frustum at the origin;
- right, the **2D overlay**: the mask, each instrument's pixels in its colour (the pixels
  inside its rotated boxes; the clasper a lighter shade), and the boxes outlined;
- below, the **bar**: frame counter (frame k / N, time in s, fps), the legend (one colour
  per instrument, as in the viewer and the report) and the current bookmark as a caption
  (an event or a comment for :data:`CAPTION_HOLD_S`, a phase until the next bookmark).

Encoding: H.264 (libx264 through PyAV's bundled FFmpeg, yuv420p, CRF 20) where
available, else OpenCV's ``mp4v``; at the sequence's frame rate; written to a temporary
file beside the output and renamed, so a failure leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mistool.annotations import Bookmark, caption_at
from mistool.config import Config
from mistool.errors import ConfigError, InputPathError
from mistool.model import PARTS, TrackTable
from mistool.report import PALETTE_RGB

#: Height of the two panels (px); their width follows the mask's aspect ratio.
PANEL_HEIGHT = 432
#: Height of the bar under the panels (px).
BAR_HEIGHT = 64
#: Events and comments stay on screen this long after their frame (s).
CAPTION_HOLD_S = 2.0
#: Length of the tips' trails in the 3D view (s).
TRAIL_S = 1.0
#: The 3D view's direction: degrees around the camera's y axis, then down.
VIEW_AZIMUTH_DEG, VIEW_ELEVATION_DEG = 35.0, 30.0
#: Floor grid spacing in the 3D view (mm).
GRID_MM = 20.0
#: Clasper (and wrist) radius as a fraction of the shaft's.
HEAD_RADIUS_FRACTION = 0.6
#: H.264 constant rate factor (lower = better quality, larger file).
H264_CRF = 20
_BG3D = (36, 30, 26)  # BGR
_BG2D = (0, 0, 0)
_BAR = (24, 24, 24)
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def instrument_bgr(k: int, part: str = "shaft") -> tuple[int, int, int]:
    """The BGR colour of the ``k``-th instrument's part (heads lighter, as the viewer)."""
    r, g, b = PALETTE_RGB[k % len(PALETTE_RGB)]
    if part != "shaft":
        r, g, b = (int(c + 0.45 * (255 - c)) for c in (r, g, b))
    return (b, g, r)


def h264_available() -> bool:
    """True when PyAV can encode H.264 (libx264)."""
    try:
        import av

        av.codec.Codec("libx264", "w")
    except Exception:  # noqa: BLE001 - any failure means: not available
        return False
    return True


class ObliqueView:
    """A fixed perspective view of the scene, from above and to the side of the endoscope.

    ``p_view = R (p - centre)`` with ``R = Rx(elevation) Ry(azimuth)`` (camera frame: x
    right, y down, z forward), then a pinhole at distance ``distance`` behind the centre.
    """

    def __init__(self, points: np.ndarray, size_wh: tuple[int, int]) -> None:
        """Frame ``points`` ((N, 3) mm, NaN rows ignored) in a ``size_wh`` panel."""
        p = points[np.all(np.isfinite(points), axis=1)]
        if len(p) == 0:
            p = np.array([[0.0, 0.0, 80.0]])
        lo, hi = np.percentile(p, 1, axis=0), np.percentile(p, 99, axis=0)
        self.centre = (lo + hi) / 2
        self.radius = max(float(np.linalg.norm(hi - lo)) / 2, 20.0)
        a, e = math.radians(VIEW_AZIMUTH_DEG), math.radians(VIEW_ELEVATION_DEG)
        ry = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
        rx = np.array([[1, 0, 0], [0, math.cos(e), -math.sin(e)], [0, math.sin(e), math.cos(e)]])
        self.R = rx @ ry
        self.distance = 3.0 * self.radius
        self.w, self.h = size_wh
        self.f = 0.5 * min(self.w, self.h) * self.distance / self.radius

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(..., 3) mm -> ((..., 2) px, (...,) depth along the view in mm)."""
        q = (np.asarray(p, dtype=np.float64) - self.centre) @ self.R.T
        z = q[..., 2] + self.distance
        zz = np.maximum(z, 1e-3)
        uv = np.stack(
            [self.f * q[..., 0] / zz + self.w / 2, self.f * q[..., 1] / zz + self.h / 2], -1
        )
        return uv, z

    def radius_px(self, r_mm: float, depth: float) -> float:
        """A radius of ``r_mm`` at ``depth`` in px."""
        return self.f * r_mm / max(depth, 1e-3)


@dataclass
class _Rows:
    """The table indexed by frame."""

    table: TrackTable
    order: np.ndarray
    starts: np.ndarray
    frames: np.ndarray

    @staticmethod
    def of(table: TrackTable) -> _Rows:
        frame = np.asarray(table["frame"], dtype=np.int64)
        order = np.argsort(frame, kind="stable")
        uniq, starts = np.unique(frame[order], return_index=True)
        return _Rows(table, order, np.append(starts, len(order)), uniq)

    def at(self, frame: int) -> np.ndarray:
        k = int(np.searchsorted(self.frames, frame))
        if k >= len(self.frames) or self.frames[k] != frame:
            return np.zeros(0, dtype=np.int64)
        return self.order[self.starts[k] : self.starts[k + 1]]


def _xyz(table: TrackTable, prefix: str) -> np.ndarray:
    return np.stack([np.asarray(table[f"{prefix}_{c}_mm"], dtype=np.float64) for c in "xyz"], 1)


class FrameRenderer:
    """Renders one output frame (BGR) from the table, the mask and the bookmarks."""

    def __init__(
        self,
        table: TrackTable,
        config: Config,
        image_wh: tuple[int, int],
        num_frames: int,
        bookmarks: list[Bookmark] | None = None,
        panel_height: int = PANEL_HEIGHT,
    ) -> None:
        self.table, self.config, self.num_frames = table, config, num_frames
        self.fps = float(config.fps)
        self.bookmarks = sorted(bookmarks or [], key=lambda b: b.frame)
        self.names = sorted({str(n) for n in table["instrument"]})
        self.index = {n: k for k, n in enumerate(self.names)}
        iw, ih = image_wh
        self.ph = panel_height - panel_height % 2
        self.pw = int(round(iw * self.ph / ih / 2)) * 2
        self.size_wh = (2 * self.pw, self.ph + BAR_HEIGHT)
        self.scale = self.ph / ih
        self.rows = _Rows.of(table)
        self.start, self.end = _xyz(table, "start"), _xyz(table, "end")
        self.metric = bool(np.isfinite(self.end).all(axis=1).any())
        self.view = ObliqueView(np.concatenate([self.start, self.end]), (self.pw, self.ph))
        self.lut = self._label_lut()
        self.trail = int(round(TRAIL_S * self.fps))
        tip = table["part"] == "clasper"
        self.tips = {n: np.full((num_frames, 3), np.nan) for n in self.names}
        for i in np.flatnonzero(tip):
            f = int(table["frame"][i])
            if 0 <= f < num_frames:
                self.tips[str(table["instrument"][i])][f] = self.end[i]

    def _label_lut(self) -> dict[str, list[tuple[int, int]]]:
        ranges: dict[str, list[tuple[int, int]]] = {p: [] for p in PARTS}
        for part, rng in self.config.parts.items():
            ranges.setdefault(part, []).append(rng)
        for inst in self.config.instruments:
            for part, rng in inst.parts.items():
                ranges.setdefault(part, []).append(rng)
        return ranges

    # 2D ---------------------------------------------------------------------------
    def overlay(self, frame: int, labels: np.ndarray | None) -> np.ndarray:
        """The right panel: mask coloured per instrument, boxes outlined."""
        panel = np.zeros((self.ph, self.pw, 3), np.uint8)
        if labels is None:
            return panel
        lab = cv2.resize(labels, (self.pw, self.ph), interpolation=cv2.INTER_NEAREST)
        part_of = np.zeros(lab.shape, np.uint8)  # 0 none, else 1 + PARTS index
        for k, part in enumerate(PARTS):
            for lo, hi in self.lut.get(part, []):
                part_of[(lab >= lo) & (lab <= hi)] = k + 1
        owner = np.zeros(lab.shape, np.int32)  # 0 none, else 1 + instrument index
        rows = self.rows.at(frame)
        boxes = []
        for part in PARTS:  # distal parts last: they win where boxes overlap
            for i in rows:
                if self.table["part"][i] != part:
                    continue
                pts = np.array([[self.table[f"{a}{j}_px"][i] for a in "xy"] for j in range(1, 5)])
                if not np.isfinite(pts).all():
                    continue
                pts = np.round(pts * self.scale).astype(np.int32)
                k = self.index[str(self.table["instrument"][i])]
                cv2.fillConvexPoly(owner, pts, k + 1)
                boxes.append((pts, k, part))
        panel[part_of > 0] = (110, 110, 110)
        for k in range(len(self.names)):
            for j, part in enumerate(PARTS):
                sel = (owner == k + 1) & (part_of == j + 1)
                panel[sel] = instrument_bgr(k, part)
        for pts, k, part in boxes:
            cv2.polylines(panel, [pts], True, instrument_bgr(k, part), 1, cv2.LINE_AA)
        _label(panel, "masks + boxes", (8, 20))
        return panel

    # 3D ---------------------------------------------------------------------------
    def _floor(self, panel: np.ndarray) -> None:
        p = np.concatenate([self.start, self.end])
        p = p[np.all(np.isfinite(p), axis=1)]
        if not len(p):
            return
        y = float(np.percentile(p[:, 1], 99)) + 10.0
        x0, x1 = np.percentile(p[:, 0], [1, 99]) + [-20, 20]
        z0, z1 = min(0.0, float(np.percentile(p[:, 2], 1))), np.percentile(p[:, 2], 99) + 20
        for x in np.arange(math.floor(x0 / GRID_MM) * GRID_MM, x1 + 1e-9, GRID_MM):
            self._line3d(panel, (x, y, z0), (x, y, z1), (70, 62, 56))
        for z in np.arange(math.floor(z0 / GRID_MM) * GRID_MM, z1 + 1e-9, GRID_MM):
            self._line3d(panel, (x0, y, z), (x1, y, z), (70, 62, 56))

    def _line3d(self, panel: np.ndarray, a: Any, b: Any, colour: tuple[int, int, int]) -> None:
        uv, z = self.view.project(np.array([a, b], dtype=np.float64))
        if (z > 1).all():
            p = np.round(uv).astype(np.int32)
            cv2.line(panel, tuple(p[0]), tuple(p[1]), colour, 1, cv2.LINE_AA)

    def _endoscope(self, panel: np.ndarray) -> None:
        cam = self.config.camera
        d = 15.0
        hx, hy = (0.6, 0.45) if cam is None else (cam.cx / cam.fx, cam.cy / cam.fy)
        corners = [
            (-hx * d, -hy * d, d),
            (hx * d, -hy * d, d),
            (hx * d, hy * d, d),
            (-hx * d, hy * d, d),
        ]
        grey = (170, 170, 170)
        for k, c in enumerate(corners):
            self._line3d(panel, (0, 0, 0), c, grey)
            self._line3d(panel, c, corners[(k + 1) % 4], grey)
        uv, _ = self.view.project(np.zeros(3))
        _label(panel, "endoscope", (int(uv[0]) + 6, int(uv[1]) - 6), scale=0.4)

    def _cylinder(
        self, panel: np.ndarray, a: np.ndarray, b: np.ndarray, r: float, k: int, part: str
    ) -> None:
        uv, z = self.view.project(np.stack([a, b]))
        if not (z > 1).all() or not np.isfinite(uv).all():
            return
        ra, rb = (max(1.0, self.view.radius_px(r, zz)) for zz in z)
        d = uv[1] - uv[0]
        n = np.array([-d[1], d[0]]) / (np.linalg.norm(d) + 1e-9)
        quad = np.array([uv[0] + n * ra, uv[1] + n * rb, uv[1] - n * rb, uv[0] - n * ra])
        colour = instrument_bgr(k, part)
        dark = tuple(int(c * 0.55) for c in colour)
        light = tuple(int(c + 0.5 * (255 - c)) for c in colour)
        s = 4  # fixed-point sub-pixel drawing
        q = np.round(quad * 2**s).astype(np.int32)
        cv2.circle(
            panel,
            tuple(np.round(uv[1] * 2**s).astype(int)),
            int(rb * 2**s),
            colour,
            -1,
            cv2.LINE_AA,
            s,
        )
        cv2.fillConvexPoly(panel, q, colour, cv2.LINE_AA, s)
        cv2.polylines(panel, [q], True, dark, 1, cv2.LINE_AA, s)
        hi = np.round((uv + n * np.array([[ra], [rb]]) * 0.45) * 2**s).astype(np.int32)
        cv2.line(panel, tuple(hi[0]), tuple(hi[1]), light, 1, cv2.LINE_AA, s)

    def scene(self, frame: int) -> np.ndarray:
        """The left panel: the 3D view of this frame."""
        panel = np.full((self.ph, self.pw, 3), _BG3D, np.uint8)
        if not self.metric:
            _label(panel, "no metric 3D (no [camera] in mistool.toml)", (8, self.ph // 2))
            return panel
        self._floor(panel)
        self._endoscope(panel)
        for name, tips in self.tips.items():
            lo = max(0, frame - self.trail)
            uv, z = self.view.project(tips[lo : frame + 1])
            ok = np.isfinite(uv).all(axis=1) & (z > 1)
            pts = np.round(uv[ok]).astype(np.int32)
            if len(pts) > 1:
                colour = instrument_bgr(self.index[name], "clasper")
                cv2.polylines(panel, [pts], False, colour, 1, cv2.LINE_AA)
        parts = []
        for i in self.rows.at(frame):
            a, b = self.start[i], self.end[i]
            if not (np.isfinite(a).all() and np.isfinite(b).all()):
                continue
            name = str(self.table["instrument"][i])
            part = str(self.table["part"][i])
            r = (self.config.shaft_diameter_for(name) or 8.0) / 2
            if part != "shaft":
                r *= HEAD_RADIUS_FRACTION
            _, z = self.view.project((a + b) / 2)
            parts.append((float(z), a, b, r, self.index[name], part))
        for _, a, b, r, k, part in sorted(parts, key=lambda t: -t[0]):
            self._cylinder(panel, a, b, r, k, part)
        _label(panel, "3D (camera frame, mm)", (8, 20))
        return panel

    # bar --------------------------------------------------------------------------
    def bar(self, frame: int) -> np.ndarray:
        """The bar: frame counter, legend, caption."""
        bar = np.full((BAR_HEIGHT, self.size_wh[0], 3), _BAR, np.uint8)
        counter = (
            f"frame {frame} (0-{self.num_frames - 1})   {frame / self.fps:6.2f} s / "
            f"{self.num_frames / self.fps:.2f} s   {self.fps:g} fps"
        )
        _label(bar, counter, (10, 22), scale=0.55)
        x = 10
        for k, name in enumerate(self.names):
            cv2.rectangle(bar, (x, 34), (x + 14, 48), instrument_bgr(k), -1)
            text = f"instrument {name}"
            _label(bar, text, (x + 20, 47), scale=0.5)
            x += 40 + cv2.getTextSize(text, _FONT, 0.5, 1)[0][0]
        mark = caption_at(self.bookmarks, frame, int(round(CAPTION_HOLD_S * self.fps)))
        if mark is not None:
            text = _ascii(f"[{mark.kind}] {mark.text}")
            width = cv2.getTextSize(text, _FONT, 0.6, 2)[0][0]
            x0 = max(x + 10, self.size_wh[0] - width - 14)
            cv2.rectangle(bar, (x0 - 6, 28), (self.size_wh[0] - 6, 56), (0, 190, 255), -1)
            cv2.putText(bar, text, (x0, 49), _FONT, 0.6, (0, 0, 0), 2, cv2.LINE_AA)
        return bar

    def render(self, frame: int, labels: np.ndarray | None) -> np.ndarray:
        """One output frame, ``(H, W, 3)`` uint8 BGR."""
        top = np.concatenate([self.scene(frame), self.overlay(frame, labels)], axis=1)
        return np.concatenate([top, self.bar(frame)], axis=0)


def _ascii(text: str) -> str:
    """OpenCV's Hershey fonts draw ASCII only."""
    return text.encode("ascii", "replace").decode("ascii")


def _label(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.5) -> None:
    cv2.putText(img, _ascii(text), org, _FONT, scale, (235, 235, 235), 1, cv2.LINE_AA)


@contextlib.contextmanager
def _temporary_beside(out: Path) -> Iterator[Path]:
    """A temporary file path beside ``out``, renamed to ``out`` on success."""
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():
        raise InputPathError(f"{out}: output folder {folder} does not exist")
    if out.is_dir():
        raise InputPathError(f"{out}: is a folder; expected an output file name")
    fd, tmp = tempfile.mkstemp(prefix=f".{out.name}.", suffix=out.suffix or ".mp4", dir=folder)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


class _Encoder:
    """H.264 through PyAV, or OpenCV's mp4v."""

    def __init__(self, path: Path, size_wh: tuple[int, int], fps: float, codec: str) -> None:
        self.codec = codec
        if codec == "h264":
            import av

            self.container = av.open(str(path), mode="w", format="mp4")
            stream = self.container.add_stream(
                "libx264", rate=Fraction(fps).limit_denominator(1001)
            )
            stream.width, stream.height = size_wh
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": str(H264_CRF), "preset": "veryfast"}
            self.stream = stream
        else:
            fourcc = cv2.VideoWriter.fourcc(*"mp4v")
            self.writer = cv2.VideoWriter(str(path), fourcc, float(fps), size_wh)
            if not self.writer.isOpened():
                raise InputPathError(f"{path}: OpenCV cannot open an mp4v writer")

    def write(self, bgr: np.ndarray) -> None:
        if self.codec == "h264":
            import av

            frame = av.VideoFrame.from_ndarray(bgr, format="bgr24")
            for packet in self.stream.encode(frame):
                self.container.mux(packet)
        else:
            self.writer.write(bgr)

    def close(self) -> None:
        if self.codec == "h264":
            for packet in self.stream.encode():
                self.container.mux(packet)
            self.container.close()
        else:
            self.writer.release()


@dataclass(frozen=True)
class VideoSummary:
    """What :func:`export_video` wrote."""

    path: Path
    """The video file."""
    frames: int
    """Frames written."""
    size_wh: tuple[int, int]
    """Frame size (px)."""
    fps: float
    """Frame rate."""
    codec: str
    """``"h264"`` or ``"mp4v"``."""


def export_video(
    table: TrackTable,
    labels: Callable[[], Iterator[tuple[int, np.ndarray]]],
    config: Config,
    out: str | Path,
    *,
    image_wh: tuple[int, int],
    num_frames: int,
    bookmarks: list[Bookmark] | None = None,
    codec: str = "auto",
    max_frames: int | None = None,
    progress: bool = False,
) -> VideoSummary:
    """Write the replay video.

    Args:
        table: the motion table (metric columns give the 3D view).
        labels: called once, yields ``(frame index, (H, W) label image)`` in order.
        config: the sequence's config (fps, label values, camera, shaft diameter).
        out: the video file (``.mp4``).
        image_wh: the masks' size (px).
        num_frames: frames in the sequence.
        bookmarks: shown as captions.
        codec: ``"auto"`` (H.264 when PyAV has libx264, else mp4v), ``"h264"``, ``"mp4v"``.
        max_frames: write at most this many frames.
        progress: a tqdm progress bar on stderr.

    Raises:
        ConfigError: a bad option; InputPathError: the output cannot be written.
    """
    if codec not in ("auto", "h264", "mp4v"):
        raise ConfigError(f"--codec {codec!r}: choose auto, h264 or mp4v")
    if codec == "h264" and not h264_available():
        raise ConfigError("--codec h264: this PyAV has no libx264 encoder; use --codec mp4v")
    if max_frames is not None and max_frames < 1:
        raise ConfigError(f"--max-frames {max_frames}: must be >= 1")
    chosen = codec if codec != "auto" else ("h264" if h264_available() else "mp4v")
    total = min(num_frames, max_frames or num_frames)
    renderer = FrameRenderer(table, config, image_wh, num_frames, bookmarks)
    path = Path(out)
    written = 0
    with _temporary_beside(path) as tmp:
        encoder = _Encoder(tmp, renderer.size_wh, config.fps, chosen)
        try:
            from tqdm import tqdm

            bar = tqdm(total=total, unit="frame", desc="export-video", disable=not progress)
            for index, lab in labels():
                if written >= total:
                    break
                encoder.write(renderer.render(index, lab))
                written += 1
                bar.update(1)
            bar.close()
        finally:
            encoder.close()
    return VideoSummary(path, written, renderer.size_wh, float(config.fps), chosen)
