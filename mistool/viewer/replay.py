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

#: One colour per instrument (RGB), in instrument order; cycled beyond ten.
PALETTE = np.array(
    [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ],
    dtype=np.uint8,
)
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


@dataclass(frozen=True)
class Replay:
    """A sequence's replay: the table plus dense per-frame arrays for the viewer."""

    table: TrackTable
    """The track table it was built from."""
    config: Config
    """The sequence's configuration."""
    num_frames: int
    """Number of frames of the sequence (at least one past the last table frame)."""
    fps: float
    """Frames per second."""
    image_wh: tuple[int, int]
    """Image size (width, height) in px."""
    instruments: tuple[str, ...]
    """Instrument names, in colour order."""
    parts: tuple[str, ...]
    """Parts present, proximal to distal."""
    colours: np.ndarray
    """(I, 3) uint8: one RGB colour per instrument."""
    corners: np.ndarray
    """(F, I, P, 4, 2) float32: each part's box corners in px (NaN where absent)."""
    modes: dict[str, ModeGeometry]
    """Available display modes ("metric" needs a camera and metric columns)."""
    series: dict[str, np.ndarray]
    """Plot series per mode: ``"<mode>/position"`` and ``"<mode>/rotation"``, each
    (F, I, P, 3) float64 (NaN where unknown)."""

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
    if "paper_x_px" in table and np.isfinite(np.asarray(table["paper_x_px"], float)).any():
        return table
    corners = [f"{a}{k}_px" for k in range(1, 5) for a in ("x", "y")]
    if not all(c in table and np.isfinite(np.asarray(table[c], float)).all() for c in corners):
        return table  # Algorithm 2 needs every box's corners
    try:
        from mistool.paper import paper_motion  # the algorithms helper's Algorithm 2
    except ImportError:  # pragma: no cover - until mistool.paper exists
        return table
    return paper_motion(table)


def build_replay(
    table: TrackTable,
    config: Config,
    *,
    num_frames: int | None = None,
    image_wh: tuple[int, int] | None = None,
) -> Replay:
    """Precompute a replay from a track table.

    Args:
        table: The motion table (box columns required; paper and metric columns used
            when present, NaN meaning unknown).
        config: The sequence's configuration (fps, camera, instrument dimensions).
        num_frames: Frames in the sequence; default: last table frame + 1.
        image_wh: Image (width, height) px; default: from the camera's principal point,
            else the boxes' extent.

    Returns:
        The replay.

    Raises:
        TableError: the table has no rows or lacks box columns.
    """
    for name in ("frame", "instrument", "part", "cx_px", "cy_px", "length_px", "width_px"):
        if name not in table:
            raise TableError(
                f"motion table: missing column {name!r}; the viewer needs the "
                "boxes (cx_px, cy_px, length_px, width_px, angle_deg)"
            )
    if table.num_rows == 0:
        raise TableError("motion table: no rows (no instrument was found in any frame)")
    table = _paper_columns(table)
    frames = np.asarray(table["frame"], dtype=np.int64)
    if frames.min() < 0:
        raise TableError(f"motion table: negative frame index {int(frames.min())}")
    n_frames = (
        int(frames.max()) + 1 if num_frames is None else max(int(num_frames), int(frames.max()) + 1)
    )
    inst_col = np.asarray(table["instrument"]).astype(str)
    present = {str(s) for s in inst_col}
    instruments = tuple(
        dict.fromkeys(
            [s.name for s in config.instruments if s.name in present]
            + sorted(present, key=_natural_key)
        )
    )
    part_col = np.asarray(table["part"]).astype(str)
    unknown = sorted(set(part_col) - set(PARTS))
    if unknown:
        raise TableError(
            f"motion table: unknown part(s) {', '.join(unknown)}; expected {', '.join(PARTS)}"
        )
    parts = tuple(str(p) for p in PARTS if p in set(part_col))
    ii = np.array([instruments.index(s) for s in inst_col], dtype=np.int64)
    pi = np.array([parts.index(s) for s in part_col], dtype=np.int64)
    shape = (n_frames, len(instruments), len(parts))

    corners_cols = tuple(f"{a}{k}_px" for k in range(1, 5) for a in ("x", "y"))
    if all(c in table for c in corners_cols):
        corners = _dense(table, frames, ii, pi, shape, corners_cols).reshape(*shape, 4, 2)
    else:
        corners = np.full((*shape, 4, 2), np.nan)
    if image_wh is None:
        if config.camera is not None:
            image_wh = (int(round(2 * config.camera.cx + 1)), int(round(2 * config.camera.cy + 1)))
        else:
            cx = np.asarray(table["cx_px"], float)
            cy = np.asarray(table["cy_px"], float)
            image_wh = (int(np.nanmax(cx) * 1.2 + 1), int(np.nanmax(cy) * 1.2 + 1))
    colours = PALETTE[np.arange(len(instruments)) % len(PALETTE)]
    fps = float(config.fps)

    modes: dict[str, ModeGeometry] = {}
    series: dict[str, np.ndarray] = {}
    paper = _paper_geometry(table, frames, ii, pi, shape, parts, config, image_wh)
    if paper is not None:
        modes["paper"], series["paper/position"], series["paper/rotation"] = paper
    metric = _metric_geometry(table, frames, ii, pi, shape, parts, instruments, config)
    if metric is not None:
        modes["metric"], series["metric/position"], series["metric/rotation"] = metric
    if not modes:
        raise TableError(
            "motion table: neither paper columns (paper_x_px ...) nor metric "
            "columns (end_x_mm ...) hold any value; nothing to show in 3D"
        )
    return Replay(
        table=table,
        config=config,
        num_frames=n_frames,
        fps=fps,
        image_wh=(int(image_wh[0]), int(image_wh[1])),
        instruments=instruments,
        parts=parts,
        colours=colours,
        corners=corners.astype(np.float32),
        modes=modes,
        series=series,
    )


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


def default_camera_target(replay: Replay, mode: str) -> np.ndarray:
    """A robust centre (world) of the instruments' cylinders in ``mode``: (3,)."""
    g = replay.modes[mode]
    pts = g.centre[g.visible]
    if len(pts) == 0:
        return np.array([0.0, g.image_distance, 0.0])
    return np.median(pts, axis=0)


def scene_extent(replay: Replay, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) world corners of the 2nd..98th percentiles of the cylinders' ends,
    including the endoscope at the origin."""
    g = replay.modes[mode]
    pts = g.centre[g.visible]
    if len(pts) == 0:
        pts = np.zeros((1, 3))
    lo = np.minimum(np.percentile(pts, 2, axis=0), 0.0)
    hi = np.maximum(np.percentile(pts, 98, axis=0), 0.0)
    return lo, hi
