"""Everything the viewer shows, precomputed once from a track table (no viser here).

The viewer's scene is a z-up *world* frame. The endoscope sits at the world origin and
looks along world +y; its image x axis is world +x and its image y axis (down) is world -z.
So a point ``p_cam`` of the OpenCV camera frame (x right, y down, z forward) is at
``R_WORLD_CAMERA @ p_cam`` in the world (times the display scale of the mode).

Two modes place the instruments' cylinders:

- **metric**: the metric pose columns (``start_*_mm``, ``end_*_mm``, ``axis_*``), in
  millimetres, shown at :data:`METRIC_UNITS_PER_MM` world units per mm. Each part is a
  cylinder from its proximal to its distal end; the clasper's base is the shaft's end
  (the joint J). Radii come from the instrument's shaft diameter.
- **paper**: the paper's vpython scene, in pixel units (:data:`PAPER_UNITS_PER_PX` world
  units per px): each part is a cylinder whose base is the paper's (x, y, z) of
  Algorithm 2 (box centroid in px, and Eq. 5's z), whose length is the box length and
  whose radius is half the box width; its axis is +x rotated by the paper's roll about x,
  then pitch about y, then yaw about z (the cumulative sum of Algorithm 2's deltas); the
  clasper's base is attached to the shaft's end, as in the paper. The pixel plane sits at
  the distance of the focal length in front of the endoscope, so the cylinders line up
  with the mask drawn on the frustum's image plane (drawn a little further away, behind
  them). Eq. 5's z is undefined on a part's first frame and is drawn as 0 there.

Every array is dense over ``(frame, instrument, part)`` so that showing a frame is a
lookup, whatever the sequence length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mistool.config import Config
from mistool.errors import TableError
from mistool.model import PARTS, TrackTable
from mistool.report import PALETTE_RGB

#: Rotation of the camera frame into the z-up world frame (columns: camera x, y, z).
R_WORLD_CAMERA = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
#: World units per millimetre in metric mode (1 unit = 1 cm).
METRIC_UNITS_PER_MM = 0.1
#: World units per pixel in paper mode (1 unit = 100 px).
PAPER_UNITS_PER_PX = 0.01
#: The paper mode's image plane is drawn this many focal lengths away, behind the pixel
#: plane holding the cylinders (seen through the endoscope, the two still line up).
PAPER_IMAGE_BEHIND = 1.25
#: Length (mm) drawn for a shaft whose proximal end is unknown.
DEFAULT_SHAFT_LENGTH_MM = 60.0
#: Radius of the clasper and wrist relative to the shaft's, in metric mode.
PART_RADIUS_RATIO = {"shaft": 1.0, "wrist": 0.9, "clasper": 0.7}

#: One colour per instrument (RGB), in instrument order; cycled beyond ten. The same
#: colours as the report and the video (one definition: :data:`mistool.report.PALETTE_RGB`).
PALETTE = np.array(PALETTE_RGB, dtype=np.uint8)
#: How much of white is mixed into an instrument's colour for each part.
PART_LIGHTEN = {"shaft": 0.0, "wrist": 0.3, "clasper": 0.55}

MODES = ("metric", "paper")


def part_colour(instrument_colour: np.ndarray, part: str) -> tuple[int, int, int]:
    """The RGB colour of one part of an instrument: its colour lightened per part."""
    t = PART_LIGHTEN.get(part, 0.0)
    c = (1.0 - t) * instrument_colour.astype(np.float64) + t * 255.0
    return (int(round(c[0])), int(round(c[1])), int(round(c[2])))


def quat_z_to(direction: np.ndarray) -> np.ndarray:
    """Quaternions (wxyz) rotating +z onto each unit direction.

    Args:
        direction: (..., 3) unit vectors (NaN rows give NaN).

    Returns:
        (..., 4) unit quaternions, wxyz.
    """
    d = np.asarray(direction, dtype=np.float64)
    q = np.stack([1.0 + d[..., 2], -d[..., 1], d[..., 0], np.zeros(d.shape[:-1])], axis=-1)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    flip = (norm[..., 0] < 1e-9) & np.isfinite(norm[..., 0])  # d == -z: half turn about x
    q[flip] = (0.0, 1.0, 0.0, 0.0)
    norm[flip] = 1.0
    return q / norm


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """Roll (about x), pitch (about y), yaw (about z), degrees, of wxyz quaternions
    (intrinsic z-y'-x'' convention, R = Rz(yaw) Ry(pitch) Rx(roll)).

    Args:
        q: (..., 4) wxyz.

    Returns:
        (..., 3) degrees.
    """
    w, x, y, z = (q[..., i] for i in range(4))
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.degrees(np.stack([roll, pitch, yaw], axis=-1))


def _rpy_axis(roll_deg: np.ndarray, pitch_deg: np.ndarray, yaw_deg: np.ndarray) -> np.ndarray:
    """+x rotated by Rz(yaw) Ry(pitch) Rx(roll): (..., 3). Rx leaves +x unchanged."""
    p, y = np.radians(pitch_deg), np.radians(yaw_deg)
    del roll_deg  # a rotation about +x does not move the cylinder's axis
    return np.stack([np.cos(y) * np.cos(p), np.sin(y) * np.cos(p), -np.sin(p)], axis=-1)


@dataclass(frozen=True)
class ModeGeometry:
    """Cylinders of one display mode, world frame, dense over (frame, instrument, part)."""

    centre: np.ndarray
    """(F, I, P, 3) float64: cylinder centres (world units)."""
    wxyz: np.ndarray
    """(F, I, P, 4) float64: orientation taking the cylinder's +z to its axis."""
    length: np.ndarray
    """(F, I, P) float64: cylinder lengths (world units)."""
    radius: np.ndarray
    """(F, I, P) float64: cylinder radii (world units)."""
    visible: np.ndarray
    """(F, I, P) bool: the part has a drawable estimate in that frame."""
    joint: np.ndarray
    """(F, I, 3) float64: the shaft's distal end (joint), NaN where unknown."""
    tip: np.ndarray
    """(F, I, 3) float64: the most distal part's end (tip), NaN where unknown."""
    image_distance: float
    """Distance (world units) from the endoscope to the image plane drawn on the frustum."""
    units: str
    """What one world unit is, for the GUI (e.g. ``"1 cm"``)."""


#: Reason shown for a part with no row in a frame (the mask has none of it).
NOT_VISIBLE = "not visible"
#: Reason shown for a part with a row whose metric pose is empty, when the table does not
#: say why (no ``pose_status`` column, or an empty cell).
NO_POSE = "no pose"
#: Frames per window when a whole table is written into a replay.
WRITE_WINDOW = 4096


def mode_constants(mode: str, config: Config, image_wh: tuple[int, int]) -> tuple[float, str]:
    """(image distance in world units, what one world unit is) of a display mode."""
    if mode == "metric":
        return 20.0 * METRIC_UNITS_PER_MM, "1 cm"
    w, h = image_wh
    f_px = config.camera.fy if config.camera is not None else float(max(w, h))
    return PAPER_IMAGE_BEHIND * f_px * PAPER_UNITS_PER_PX, "100 px"


def _empty_geometry(shape: tuple[int, int, int], distance: float, units: str) -> ModeGeometry:
    f, i, p = shape
    wxyz = np.zeros((f, i, p, 4))
    wxyz[..., 0] = 1.0
    return ModeGeometry(
        centre=np.zeros((f, i, p, 3)),
        wxyz=wxyz,
        length=np.zeros((f, i, p)),
        radius=np.zeros((f, i, p)),
        visible=np.zeros((f, i, p), dtype=bool),
        joint=np.full((f, i, 3), np.nan),
        tip=np.full((f, i, 3), np.nan),
        image_distance=distance,
        units=units,
    )


@dataclass
class ReplayPatch:
    """Replay arrays of frames ``[lo, hi)`` computed from a table, not applied yet
    (:meth:`Replay.compute` / :meth:`Replay.apply`)."""

    lo: int
    """First frame."""
    hi: int
    """One past the last frame."""
    instruments: tuple[str, ...]
    """Instrument order the arrays use (the replay's, maybe with new ones appended)."""
    arrays: dict[str, np.ndarray]
    """``"corners"``, ``"status"``, ``"quality"``, ``"<mode>/<field>"`` and
    ``"series/<mode>/<kind>"``: each with leading axis ``hi - lo``."""
    statuses: tuple[str, ...]
    """Status vocabulary the ``status`` codes refer to."""


class Replay:
    """A sequence's replay: dense per-frame arrays for the viewer, which can grow.

    Every array is dense over ``(frame, instrument, part)`` up to :attr:`capacity` frames;
    frames ``[0, tracked)`` hold results so far (the rest shows nothing). A replay is built
    whole by :func:`build_replay`, or empty and then grown with :meth:`write` while a
    sequence is being tracked (``mistool serve``, :class:`mistool.Viewer`). Writes replace
    whole frames; readers may read while another thread writes (a frame's arrays are
    assigned in one step by :meth:`apply`).
    """

    def __init__(
        self,
        config: Config,
        *,
        num_frames: int,
        image_wh: tuple[int, int],
        instruments: tuple[str, ...] = (),
        parts: tuple[str, ...] = ("shaft", "clasper"),
        modes: tuple[str, ...] = MODES,
    ) -> None:
        """
        Args:
            config: the sequence's configuration (fps, camera, instrument dimensions).
            num_frames: frames on the timeline (more can be added by writing past it).
            image_wh: image (width, height), px.
            instruments: instrument names known so far, in colour order.
            parts: parts shown, proximal to distal.
            modes: display modes ("metric" is dropped without a camera).
        """
        self.config = config
        """The sequence's configuration."""
        self.fps = float(config.fps)
        """Frames per second."""
        self.image_wh = (int(image_wh[0]), int(image_wh[1]))
        """Image size (width, height) in px."""
        self.parts = tuple(parts)
        """Parts present, proximal to distal."""
        self.num_frames = max(1, int(num_frames))
        """Frames on the timeline (the sequence's length when known)."""
        self.tracked = 0
        """Frames ``[0, tracked)`` hold results."""
        self.revision = 0
        """Incremented by every change (consumers cache per revision)."""
        self.complete = False
        """Set by the writer when no more frames will come (refinement included)."""
        self.expected_frames: int | None = None
        """The sequence's length when a growing replay learns it. Storage grows by doubling
        from a few frames (the first frames are shown without allocating the whole length:
        0.8 s at 90,000 frames, load average ~8), then jumps to this length once the next
        size would be a quarter of it or more (doubling on would overshoot it)."""
        self.statuses: list[str] = [NOT_VISIBLE, "ok"]
        """Vocabulary of :attr:`status` codes (0 = not visible, 1 = ok)."""
        self._mode_names = tuple(m for m in modes if m != "metric" or config.camera is not None)
        self.instruments: tuple[str, ...] = ()
        """Instrument names, in colour order."""
        self.capacity = 0
        self._allocate(tuple(instruments), self.num_frames)

    # -- storage ------------------------------------------------------------------------
    def _allocate(self, instruments: tuple[str, ...], capacity: int) -> None:
        """(Re)allocate every array for ``instruments`` x ``capacity`` frames, keeping
        what is stored (new instruments are appended)."""
        old_i, old_f = len(self.instruments), self.capacity
        shape = (capacity, len(instruments), len(self.parts))
        old = self.__dict__.copy()
        self.corners = np.full((*shape, 4, 2), np.nan, dtype=np.float32)
        """(F, I, P, 4, 2) float32: each part's box corners in px (NaN where absent)."""
        self.status = np.zeros(shape, dtype=np.uint8)
        """(F, I, P) uint8: why a part has (code 1, "ok") or has no metric pose, an index
        into :attr:`statuses`."""
        self.quality = np.full(shape, np.nan, dtype=np.float32)
        """(F, I, P) float32: the pose's quality column (IoU, [0, 1]), NaN if unknown."""
        self.modes: dict[str, ModeGeometry] = {
            m: _empty_geometry(shape, *mode_constants(m, self.config, self.image_wh))
            for m in self._mode_names
        }
        """Available display modes ("metric" needs a camera)."""
        self.series: dict[str, np.ndarray] = {
            f"{m}/{k}": np.full((*shape, 3), np.nan)
            for m in self._mode_names
            for k in ("position", "rotation")
        }
        """Plot series per mode: ``"<mode>/position"`` and ``"<mode>/rotation"``, each
        (F, I, P, 3) float64 (NaN where unknown)."""
        if old_i or old_f:
            keep = (slice(0, min(old_f, capacity)), slice(0, old_i))
            for name, arr in self._arrays_of(self.__dict__).items():
                arr[keep] = self._arrays_of(old)[name][keep]
        self.instruments = instruments
        self.capacity = capacity
        self.colours = PALETTE[np.arange(len(instruments)) % len(PALETTE)]
        """(I, 3) uint8: one RGB colour per instrument."""

    @staticmethod
    def _arrays_of(attrs: dict[str, Any]) -> dict[str, np.ndarray]:
        out = {"corners": attrs["corners"], "status": attrs["status"], "quality": attrs["quality"]}
        for m, g in attrs["modes"].items():
            for name in ("centre", "wxyz", "length", "radius", "visible", "joint", "tip"):
                out[f"{m}/{name}"] = getattr(g, name)
        for key, arr in attrs["series"].items():
            out[f"series/{key}"] = arr
        return out

    # -- writing ------------------------------------------------------------------------
    def compute(self, table: TrackTable, lo: int, hi: int) -> ReplayPatch:
        """The arrays of frames ``[lo, hi)`` from ``table`` (its rows of those frames;
        other rows are ignored). Pure: the replay is not changed.

        Raises:
            TableError: the table lacks box columns or names an unknown part.
        """
        _check_box_columns(table)
        if table.num_rows:
            fcol = np.asarray(table["frame"], dtype=np.int64)
            table = table[(fcol >= lo) & (fcol < hi)]
        inst_col = np.asarray(table["instrument"]).astype(str)
        part_col = np.asarray(table["part"]).astype(str)
        unknown = sorted(set(part_col) - set(self.parts))
        if unknown:
            raise TableError(
                f"motion table: unknown part(s) {', '.join(unknown)}; "
                f"expected {', '.join(self.parts)}"
            )
        new = sorted(set(inst_col) - set(self.instruments), key=_natural_key)
        instruments = self.instruments + tuple(new)
        fi = np.asarray(table["frame"], dtype=np.int64) - lo
        ii = _codes(inst_col, instruments)
        pi = _codes(part_col, self.parts)
        shape = (hi - lo, len(instruments), len(self.parts))
        arrays: dict[str, np.ndarray] = {}
        corners_cols = tuple(f"{a}{k}_px" for k in range(1, 5) for a in ("x", "y"))
        corners = np.full((*shape, 4, 2), np.nan)
        if all(c in table for c in corners_cols):
            corners = _dense(table, fi, ii, pi, shape, corners_cols).reshape(*shape, 4, 2)
        arrays["corners"] = corners.astype(np.float32)
        quality = np.full(shape, np.nan, dtype=np.float32)
        if "quality" in table:
            quality[fi, ii, pi] = np.asarray(table["quality"], dtype=np.float32)
        arrays["quality"] = quality
        for m in self._mode_names:
            empty = _empty_geometry(shape, 0.0, "")
            found = (
                _metric_geometry(table, fi, ii, pi, shape, self.parts, instruments, self.config)
                if m == "metric"
                else _paper_geometry(
                    _paper_columns(table), fi, ii, pi, shape, self.parts, self.config, self.image_wh
                )
            )
            nothing = np.full((*shape, 3), np.nan)
            g, position, rotation = found if found is not None else (empty, nothing, nothing)
            for name in ("centre", "wxyz", "length", "radius", "visible", "joint", "tip"):
                arrays[f"{m}/{name}"] = getattr(g, name)
            arrays[f"series/{m}/position"] = position
            arrays[f"series/{m}/rotation"] = rotation
        drawn = arrays["metric/visible"][fi, ii, pi] if "metric" in self._mode_names else None
        statuses = list(self.statuses)
        arrays["status"] = self._status(table, fi, ii, pi, shape, statuses, drawn)
        return ReplayPatch(lo, hi, instruments, arrays, tuple(statuses))

    def _status(
        self,
        table: TrackTable,
        fi: np.ndarray,
        ii: np.ndarray,
        pi: np.ndarray,
        shape: tuple[int, int, int],
        statuses: list[str],
        drawn: np.ndarray | None,
    ) -> np.ndarray:
        """Status codes: each row's ``pose_status`` when the table gives one; where it
        gives none (no such column, or an empty cell: a ground-truth table, a table
        written by another tool), "ok" where the row's metric pose is drawn (``drawn``:
        (N,) bool, None without a metric mode) and else :data:`NO_POSE`, or "no camera"
        without a camera."""
        out = np.zeros(shape, dtype=np.uint8)  # 0: no row, not visible
        if table.num_rows == 0:
            return out
        given = np.full(table.num_rows, "", dtype=str)
        if "pose_status" in table:  # (a table's object column holds str(None), str(nan))
            given = np.char.strip(np.asarray(table["pose_status"]).astype(str))
        missing = np.isin(given, _NO_STATUS)
        reason = NO_POSE if self.config.camera is not None else "no camera"
        shown = drawn if drawn is not None else np.zeros(table.num_rows, dtype=bool)
        text = np.where(missing, np.where(shown, "ok", reason), given)
        codes = np.empty(len(text), dtype=np.uint8)
        for value in np.unique(text):
            name = str(value)
            if name not in statuses:
                if len(statuses) >= 255:
                    name = NO_POSE if NO_POSE in statuses else statuses[-1]
                else:
                    statuses.append(name)
            codes[text == value] = statuses.index(name)
        out[fi, ii, pi] = codes
        return out

    def apply(self, patch: ReplayPatch) -> None:
        """Store a computed patch: frames ``[lo, hi)`` replaced, the timeline extended
        past ``hi`` when needed, new instruments added (fast: array copies only)."""
        if patch.hi > self.capacity or len(patch.instruments) > len(self.instruments):
            capacity, expected = self.capacity, self.expected_frames
            while capacity < patch.hi:
                capacity = max(2 * capacity, 64)
            if expected is not None and patch.hi <= expected and 4 * capacity >= expected:
                capacity = expected  # the whole length, once it is no longer a big step
            self._allocate(patch.instruments, capacity)
        self.statuses = list(patch.statuses)
        n_i = len(patch.instruments)
        target = self._arrays_of(self.__dict__)
        window = slice(patch.lo, patch.hi)
        for name, arr in patch.arrays.items():
            dest = target[name]
            if dest.shape[1] == n_i:
                dest[window] = arr
            else:  # cannot happen after _allocate; kept for clarity of shapes
                dest[window, :n_i] = arr
        self.tracked = max(self.tracked, patch.hi)
        self.num_frames = max(self.num_frames, patch.hi)
        self.revision += 1

    def write(self, table: TrackTable, lo: int, hi: int) -> None:
        """:meth:`compute` then :meth:`apply`, in windows of :data:`WRITE_WINDOW` frames."""
        for a in range(lo, hi, WRITE_WINDOW):
            self.apply(self.compute(table, a, min(hi, a + WRITE_WINDOW)))

    # -- reading ------------------------------------------------------------------------
    @property
    def default_mode(self) -> str:
        """Metric when available (camera known and poses present), else paper."""
        return "metric" if "metric" in self.modes else "paper"

    def fov_aspect(self) -> tuple[float, float]:
        """The endoscope's vertical field of view (radians) and aspect (w / h)."""
        w, h = self.image_wh
        fy = self.config.camera.fy if self.config.camera is not None else float(max(w, h))
        return 2.0 * math.atan2(h / 2.0, fy), w / h

    def view_intrinsics(self, mode: str) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy), px (OpenCV: pixel centres at integers), of the image as the
        endoscope at the world origin sees ``mode``'s cylinders: the camera's in metric
        mode; in paper mode the pixel plane at depth fy, centred on the image."""
        w, h = self.image_wh
        cam = self.config.camera
        if mode == "metric" and cam is not None:
            return cam.fx, cam.fy, cam.cx, cam.cy
        f = cam.fy if cam is not None else float(max(w, h))
        return f, f, w / 2.0, h / 2.0

    def part_colour(self, instrument_index: int, part: str) -> tuple[int, int, int]:
        """RGB colour of a part of the instrument at ``instrument_index``."""
        return part_colour(self.colours[instrument_index], part)

    def first_busy_frame(self) -> int | None:
        """The first stored frame where some part is drawn in 3D (None: none so far)."""
        g = self.modes[self.default_mode]
        busy = g.visible[: self.tracked].any(axis=(1, 2))
        hits = np.flatnonzero(busy)
        return int(hits[0]) if len(hits) else None

    def frame_status(self, frame: int) -> list[tuple[str, str, str, float]]:
        """Per instrument and part at ``frame``: (instrument, part, status, quality)."""
        out: list[tuple[str, str, str, float]] = []
        if not 0 <= frame < min(self.tracked, self.capacity):
            return out
        for i, inst in enumerate(self.instruments):
            for p, part in enumerate(self.parts):
                code = int(self.status[frame, i, p])
                out.append((inst, part, self.statuses[code], float(self.quality[frame, i, p])))
        return out


_END_COLUMNS = ("end_x_mm", "end_y_mm", "end_z_mm")
#: ``pose_status`` cells that give no reason (empty; a missing value turned into text).
_NO_STATUS = ("", "nan", "NaN", "None")


def _codes(values: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """Index of each value in ``names`` (every value must be one of them)."""
    distinct, inverse = np.unique(values, return_inverse=True)
    lut = np.array([names.index(str(v)) for v in distinct], dtype=np.int64)
    return lut[inverse.reshape(-1)] if len(values) else np.zeros(0, dtype=np.int64)


def _dense(
    table: TrackTable,
    fi: np.ndarray,
    ii: np.ndarray,
    pi: np.ndarray,
    shape: tuple[int, int, int],
    names: tuple[str, ...],
) -> np.ndarray:
    out = np.full((*shape, len(names)), np.nan)
    for c, name in enumerate(names):
        out[fi, ii, pi, c] = np.asarray(table[name], dtype=np.float64)
    return out


def _paper_columns(table: TrackTable) -> TrackTable:
    """The table with the paper's per-frame columns, computed when they are all missing."""
    if table.num_rows == 0:
        return table
    if "paper_x_px" in table and np.isfinite(np.asarray(table["paper_x_px"], float)).any():
        return table
    corners = [f"{a}{k}_px" for k in range(1, 5) for a in ("x", "y")]
    if not all(c in table and np.isfinite(np.asarray(table[c], float)).all() for c in corners):
        return table  # Algorithm 2 needs every box's corners
    from mistool.paper import paper_motion

    return paper_motion(table)


def _check_box_columns(table: TrackTable) -> None:
    for name in ("frame", "instrument", "part", "cx_px", "cy_px", "length_px", "width_px"):
        if name not in table:
            raise TableError(
                f"motion table: missing column {name!r}; the viewer needs the "
                "boxes (cx_px, cy_px, length_px, width_px, angle_deg)"
            )


def table_instruments(table: TrackTable, config: Config) -> tuple[str, ...]:
    """Instrument names of a table in colour order: the config's, then natural order."""
    present = {str(s) for s in np.asarray(table["instrument"]).astype(str)}
    return tuple(
        dict.fromkeys(
            [s.name for s in config.instruments if s.name in present]
            + sorted(present, key=_natural_key)
        )
    )


def config_parts(config: Config) -> tuple[str, ...]:
    """Parts the config's labels have, proximal to distal (shaft and clasper at least)."""
    named = set(config.parts) | {p for s in config.instruments for p in s.parts}
    return tuple(p for p in PARTS if p in named or p in ("shaft", "clasper"))


def build_replay(
    table: TrackTable,
    config: Config,
    *,
    num_frames: int | None = None,
    image_wh: tuple[int, int] | None = None,
) -> Replay:
    """Precompute a replay from a whole track table.

    Args:
        table: The motion table (box columns required; paper and metric columns used
            when present, NaN meaning unknown).
        config: The sequence's configuration (fps, camera, instrument dimensions).
        num_frames: Frames in the sequence; default: last table frame + 1.
        image_wh: Image (width, height) px; default: from the camera's principal point,
            else the boxes' extent.

    Returns:
        The replay (:attr:`Replay.complete` set).

    Raises:
        TableError: the table has no rows or lacks box columns.
    """
    _check_box_columns(table)
    if table.num_rows == 0:
        raise TableError("motion table: no rows (no instrument was found in any frame)")
    frames = np.asarray(table["frame"], dtype=np.int64)
    if frames.min() < 0:
        raise TableError(f"motion table: negative frame index {int(frames.min())}")
    last = int(frames.max())
    n_frames = last + 1 if num_frames is None else max(int(num_frames), last + 1)
    part_col = set(np.asarray(table["part"]).astype(str))
    unknown = sorted(part_col - set(PARTS))
    if unknown:
        raise TableError(
            f"motion table: unknown part(s) {', '.join(unknown)}; expected {', '.join(PARTS)}"
        )
    if image_wh is None:
        image_wh = _image_wh_of(table, config)
    modes = []
    if _has_values(table, ("paper_x_px",)) or _has_values(table, ("x1_px",)):
        modes.append("paper")
    if config.camera is not None and _has_values(table, _END_COLUMNS):
        modes.insert(0, "metric")
    if not modes:
        raise TableError(
            "motion table: neither paper columns (paper_x_px ...) nor metric "
            "columns (end_x_mm ...) hold any value; nothing to show in 3D"
        )
    replay = Replay(
        config,
        num_frames=int(n_frames),
        image_wh=image_wh,
        instruments=table_instruments(table, config),
        parts=tuple(p for p in PARTS if p in part_col),
        modes=tuple(modes),
    )
    if "paper" in modes and not _has_values(table, ("paper_x_px",)):
        table = _paper_columns(table)  # over the whole table: Eq. 5 needs consecutive rows
        if not _has_values(table, ("paper_x_px",)):
            replay._mode_names = tuple(m for m in replay._mode_names if m != "paper")
            replay.modes.pop("paper")
            replay.series = {k: v for k, v in replay.series.items() if not k.startswith("paper")}
            if not replay.modes:
                raise TableError(
                    "motion table: neither paper columns (paper_x_px ...) nor metric "
                    "columns (end_x_mm ...) hold any value; nothing to show in 3D"
                )
    replay.write(table, 0, replay.num_frames)
    replay.complete = True
    return replay


def _has_values(table: TrackTable, names: tuple[str, ...]) -> bool:
    return all(n in table for n in names) and bool(
        np.isfinite(np.column_stack([np.asarray(table[n], float) for n in names])).all(axis=1).any()
    )


def _image_wh_of(table: TrackTable, config: Config) -> tuple[int, int]:
    if config.camera is not None:
        return (int(round(2 * config.camera.cx + 1)), int(round(2 * config.camera.cy + 1)))
    cx = np.asarray(table["cx_px"], float)
    cy = np.asarray(table["cy_px"], float)
    return (int(np.nanmax(cx) * 1.2 + 1), int(np.nanmax(cy) * 1.2 + 1))


def _natural_key(text: str) -> tuple[Any, ...]:
    import re

    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text))


def _cylinders(
    start: np.ndarray,
    end: np.ndarray,
    radius: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cylinder centre, wxyz, length and visibility from world start/end points."""
    vec = end - start
    length = np.linalg.norm(vec, axis=-1)
    visible = np.isfinite(length) & (length > 1e-9) & np.isfinite(radius) & (radius > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = vec / length[..., None]
    direction[~visible] = (0.0, 0.0, 1.0)
    wxyz = quat_z_to(direction)
    centre = 0.5 * (start + end)
    centre[~visible] = 0.0
    length = np.where(visible, length, 0.0)
    return centre, wxyz, length, visible


def _chain(start: np.ndarray, end: np.ndarray, parts: tuple[str, ...]) -> None:
    """Attach each part's base to the previous part's end where that end is known
    (in place; arrays (F, I, P, 3))."""
    for p in range(1, len(parts)):
        prev_end = end[:, :, p - 1]
        known = np.isfinite(prev_end).all(axis=-1) & np.isfinite(end[:, :, p]).all(axis=-1)
        start[:, :, p][known] = prev_end[known]


def _paper_geometry(
    table: TrackTable,
    fi: np.ndarray,
    ii: np.ndarray,
    pi: np.ndarray,
    shape: tuple[int, int, int],
    parts: tuple[str, ...],
    config: Config,
    image_wh: tuple[int, int],
) -> tuple[ModeGeometry, np.ndarray, np.ndarray] | None:
    names = (
        "paper_x_px",
        "paper_y_px",
        "paper_z",
        "paper_roll_deg",
        "paper_pitch_deg",
        "paper_yaw_deg",
        "length_px",
        "width_px",
    )
    v = _dense(table, fi, ii, pi, shape, names)
    if not np.isfinite(v[..., 0]).any():
        return None
    s = PAPER_UNITS_PER_PX
    w, h = image_wh
    f_px = config.camera.fy if config.camera is not None else float(max(w, h))
    # Pixel frame (x right, y down, z = Eq. 5's z) -> camera-like frame centred on the
    # image, with the pixel plane at depth f_px, then to the world.
    # Eq. 5's z is undefined on a part's first frame (no previous area): drawn as 0 there.
    z = np.where(np.isfinite(v[..., 0]), np.nan_to_num(v[..., 2], nan=0.0), np.nan)
    base_px = np.stack([v[..., 0] - w / 2.0, v[..., 1] - h / 2.0, f_px + z], axis=-1)
    axis = _rpy_axis(v[..., 3], v[..., 4], v[..., 5])  # in the pixel frame
    vec_px = axis * v[..., 6:7]
    start = np.empty_like(base_px)
    end = np.empty_like(base_px)
    start[...] = base_px
    end[...] = base_px + vec_px
    # The paper attaches each part's base to the previous part's end.
    for p in range(1, len(parts)):
        prev_end = end[:, :, p - 1]
        known = np.isfinite(prev_end).all(axis=-1) & np.isfinite(end[:, :, p]).all(axis=-1)
        start[:, :, p][known] = prev_end[known]
        end[:, :, p][known] = prev_end[known] + vec_px[:, :, p][known]
    start_w = (start @ R_WORLD_CAMERA.T) * s
    end_w = (end @ R_WORLD_CAMERA.T) * s
    radius = 0.5 * v[..., 7] * s
    centre, wxyz, length, visible = _cylinders(start_w, end_w, radius)
    joint = _part_point(end_w, parts, "shaft")
    tip = _distal_point(end_w, visible)
    geometry = ModeGeometry(
        centre=centre,
        wxyz=wxyz,
        length=length,
        radius=radius,
        visible=visible,
        joint=joint,
        tip=tip,
        image_distance=PAPER_IMAGE_BEHIND * f_px * s,
        units="100 px",
    )
    return geometry, v[..., 0:3].copy(), v[..., 3:6].copy()


def _metric_geometry(
    table: TrackTable,
    fi: np.ndarray,
    ii: np.ndarray,
    pi: np.ndarray,
    shape: tuple[int, int, int],
    parts: tuple[str, ...],
    instruments: tuple[str, ...],
    config: Config,
) -> tuple[ModeGeometry, np.ndarray, np.ndarray] | None:
    if config.camera is None:
        return None
    names = (
        "start_x_mm",
        "start_y_mm",
        "start_z_mm",
        "end_x_mm",
        "end_y_mm",
        "end_z_mm",
        "axis_x",
        "axis_y",
        "axis_z",
        "qw",
        "qx",
        "qy",
        "qz",
    )
    v = _dense(table, fi, ii, pi, shape, names)
    start, end, axis, quat = v[..., 0:3].copy(), v[..., 3:6].copy(), v[..., 6:9], v[..., 9:13]
    if not np.isfinite(end).all(axis=-1).any():
        return None
    _wrist_ends(start, end, axis, parts, config)
    # Unknown proximal ends: go back along the axis by a nominal length.
    for p, part in enumerate(parts):
        missing = ~np.isfinite(start[:, :, p]).all(axis=-1)
        if part == "shaft":
            back_mm = DEFAULT_SHAFT_LENGTH_MM
        else:
            back_mm = config.clasper_length_mm or 10.0
            if part == "wrist":
                back_mm *= 0.5
        start[:, :, p][missing] = end[:, :, p][missing] - back_mm * axis[:, :, p][missing]
    _chain(start, end, parts)
    s = METRIC_UNITS_PER_MM
    start_w = (start @ R_WORLD_CAMERA.T) * s
    end_w = (end @ R_WORLD_CAMERA.T) * s
    radius = np.zeros(shape)
    for i, name in enumerate(instruments):
        shaft_r = 0.5 * (config.shaft_diameter_for(name) or 8.0)
        for p, part in enumerate(parts):
            radius[:, i, p] = shaft_r * PART_RADIUS_RATIO.get(part, 1.0) * s
    centre, wxyz, length, visible = _cylinders(start_w, end_w, radius)
    # Orientation for the plots: the pose's quaternion, else the axis direction.
    q = quat.copy()
    no_q = ~np.isfinite(q).all(axis=-1)
    axis_dir = end - start
    with np.errstate(invalid="ignore", divide="ignore"):
        axis_dir = axis_dir / np.linalg.norm(axis_dir, axis=-1, keepdims=True)
    q[no_q] = quat_z_to(axis_dir[no_q]) if no_q.any() else q[no_q]
    rotation = euler_from_quat(q)
    geometry = ModeGeometry(
        centre=centre,
        wxyz=wxyz,
        length=length,
        radius=radius,
        visible=visible,
        joint=_part_point(end_w, parts, "shaft"),
        tip=_distal_point(end_w, visible),
        image_distance=20.0 * s,
        units="1 cm",
    )
    return geometry, end.copy(), rotation


def _wrist_ends(
    start: np.ndarray,
    end: np.ndarray,
    axis: np.ndarray,
    parts: tuple[str, ...],
    config: Config,
) -> None:
    """Give a wrist whose metric pose is its proximal end (the joint) and its axis, as
    :mod:`mistool.pose` measures it (no distal end: ``pose_status`` "ok" all the same),
    a distal end to be drawn to: the nominal wrist length along its axis (half the
    clasper's length), at most half way to the clasper's tip (in place; (F, I, P, 3))."""
    if "wrist" not in parts:
        return
    w = parts.index("wrist")
    need = ~np.isfinite(end[:, :, w]).all(axis=-1)
    need &= np.isfinite(start[:, :, w]).all(axis=-1) & np.isfinite(axis[:, :, w]).all(axis=-1)
    if not need.any():
        return
    length = np.full(need.shape, 0.5 * (config.clasper_length_mm or 10.0))
    if "clasper" in parts:
        to_tip = end[:, :, parts.index("clasper")] - start[:, :, w]
        with np.errstate(invalid="ignore"):
            along = 0.5 * np.einsum("fij,fij->fi", to_tip, axis[:, :, w])
        shorter = np.isfinite(along) & (along > 0) & (along < length)
        length[shorter] = along[shorter]
    end[:, :, w][need] = start[:, :, w][need] + length[need][:, None] * axis[:, :, w][need]


def _part_point(end_w: np.ndarray, parts: tuple[str, ...], part: str) -> np.ndarray:
    if part not in parts:
        return np.full(end_w.shape[:2] + (3,), np.nan)
    return end_w[:, :, parts.index(part)].copy()


def _distal_point(end_w: np.ndarray, visible: np.ndarray) -> np.ndarray:
    """Each (frame, instrument)'s most distal visible part end."""
    out = np.full(end_w.shape[:2] + (3,), np.nan)
    for p in range(end_w.shape[2]):
        vis = visible[:, :, p]
        out[vis] = end_w[:, :, p][vis]
    return out


def scene_extent(replay: Replay, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) world corners of the 2nd..98th percentiles of the cylinders' ends,
    including the endoscope at the origin (so a preset camera frames whole tools, not
    only their centres: a long shaft's outer end was cut off)."""
    g = replay.modes[mode]
    visible = g.visible
    centre, q = g.centre[visible], g.wxyz[visible]
    if len(centre) == 0:
        pts = np.zeros((1, 3))
    else:
        w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
        axis = np.stack(  # the rotation of wxyz applied to +z
            [2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1
        )
        half = 0.5 * g.length[visible][:, None] * axis
        pts = np.concatenate([centre - half, centre + half])
    lo = np.minimum(np.percentile(pts, 2, axis=0), 0.0)
    hi = np.maximum(np.percentile(pts, 98, axis=0), 0.0)
    return lo, hi
