"""Per-frame metric pose of one instrument from its part masks (:func:`measure_instance`).

Steps (camera frame, mm; see the package docstring for the conventions):

1. Shaft limb lines: sub-pixel boundary points between the shaft and background
   (:mod:`mistool.pose.silhouette`), minus the distal end zone (the joint's cap), the
   proximal end zone when it is inside the image, points next to other parts, and holes;
   split by side of the mask's principal axis; one robust line per side.
2. Shaft axis in closed form from the two tangent planes (:mod:`mistool.pose.cylinder`).
3. Joint J: the shaft's distal outline (shaft pixels next to the clasper/wrist, or the
   shaft's free end cap) lies where the viewing rays meet the cylinder at J's axial
   coordinate, so J's axial coordinate is the median over those boundary points of the
   axial coordinate where their rays meet the cylinder (entry point next to the clasper,
   nearest-to-proximal point of the chord next to background). On a short visible
   stretch the lines are fitted once more with the points proximal of that J.
4. Tip: the clasper's far end in the image (the mid-point of the jaw ends), at the depth
   along its ray that best fits the known clasper length and a small bend from the shaft
   axis; when the tip is cut by the image border, J + length x the least-bent direction
   that projects along the clasper's image direction.
5. ``quality``: IoU of the re-rendered part with its mask (:mod:`mistool.pose.quality`).

Never a confident wrong answer: where the geometry is degenerate (one limb line, the
shaft seen end-on, J out of the image, numerically unstable solutions) the cells are NaN.

Where the work runs: compiled kernels (:mod:`mistool.kernels.pose`, imported at the
first pose: numba is not loaded by a program that only imports mistool) do steps 1-4 in a
few passes; the parameters below are passed to them as one array (:func:`_params`). For
an undistorted lens an instrument of a shaft, a clasper and a wrist goes from its masks
to its rows in one call (:func:`_instance_in_one_call`: the shaft's kernel, then the
clasper's, each row written in order with its reasons); else the shaft goes from its
mask to its row in one call (:func:`_shaft_in_one_call`, the masks' outlines traced as
OpenCV traces them, :mod:`mistool.kernels.contours`: one piece or several, a gap at the
junction or none), the clasper in another (:func:`_tip_in_one_call`);
the steps in Python (:func:`_shaft_in_steps`, OpenCV's contours) answer for a piece
whose bounding box holds another's (it may lie in a hole), an outline without area, an
instrument of more than three parts, and a distorted lens, whose points are undistorted
(:mod:`mistool.lens`) between the kernels.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping, Sequence

import cv2
import numpy as np

from mistool.config import Camera
from mistool.lens import distort_points, undistort_points
from mistool.model import InstanceObservation, PartObservation
from mistool.pose.quality import Rims, cylinder_iou, rims_iou
from mistool.pose.silhouette import (
    FIT_MAX_POINTS,
    FIT_THRESH_PX,
    OTHER,
    SHAFT,
    Boundary,
    as_mask,
    kernels,
    outline_points,
    paste,
)
from mistool.pose.status import AUX_STATUS, reason_code

__all__ = [
    "AUX_KEYS",
    "MAX_SIGMA_DEG",
    "MAX_SIGMA_MM",
    "POSE_KEYS",
    "ROW_KEYS",
    "ROW_LEN",
    "SLOTS",
    "SLOT_OF",
    "measure_instance",
    "measure_rows",
]

#: The metric columns :func:`measure_instance` fills for each part.
POSE_KEYS: tuple[str, ...] = (
    "end_x_mm",
    "end_y_mm",
    "end_z_mm",
    "axis_x",
    "axis_y",
    "axis_z",
    "start_x_mm",
    "start_y_mm",
    "start_z_mm",
    "qw",
    "qx",
    "qy",
    "qz",
    "quality",
)
#: Per-frame auxiliary values (extra columns) that :func:`refine_sequence` uses to
#: re-solve frames with the trocar constraint, then drops. Limb lines are image lines
#: ``a u + b v + c = 0`` (px, unit normal, shaft inside positive); ``aux_u_px, aux_v_px``
#: is the joint's pixel (shaft row) or the tip's pixel (clasper row); ``aux_sigma_mm``,
#: ``aux_sigma_deg`` the 1-sigma errors of J (mm) and of the axis direction (degrees)
#: propagated from the limb lines' fits; ``aux_distal`` 1 when the distal direction was
#: seen in this frame, else 0; ``aux_su_px, aux_sv_px`` the pixel where the shaft leaves
#: the view (its proximal end).
AUX_KEYS: tuple[str, ...] = (
    "aux_l1a",
    "aux_l1b",
    "aux_l1c",
    "aux_l2a",
    "aux_l2b",
    "aux_l2c",
    "aux_u_px",
    "aux_v_px",
    "aux_su_px",
    "aux_sv_px",
    "aux_sigma_mm",
    "aux_sigma_deg",
    "aux_distal",
    AUX_STATUS,
)

#: Above this 1-sigma joint error (mm) the shaft pose is left empty: the view is too close
#: to end-on, or the limb lines too short, to trust the depth.
MAX_SIGMA_MM = 4.0
#: Above this 1-sigma axis-direction error (degrees) the axis is left empty (J is kept).
MAX_SIGMA_DEG = 3.0
_PX_NOISE = 0.3
#: A free distal end (no clasper next to it) is taken as the joint only when its outline
#: is the shaft's round end: its points' axial coordinates agree within this (mm, robust
#: sigma); an occluder's cut across the shaft does not.
_MAX_CAP_SPREAD_MM = 1.0
_PX_BIAS = 0.1
_MIN_LINE_POINTS = 10
_MIN_LINE_SPAN_PX = 12.0
#: A shaft whose depth is too uncertain is reported as ``"pointing at camera"`` when its
#: axis is within this angle (degrees) of the viewing ray, else as ``"low quality"``.
_END_ON_DEG = 30.0


#: RANSAC hypotheses of the limb-line fit (``silhouette.fit_line_robust``).
_FIT_ITERS = 12


#: The cells of a part's row, in order (:data:`POSE_KEYS`, then :data:`AUX_KEYS`).
ROW_KEYS: tuple[str, ...] = POSE_KEYS + AUX_KEYS
ROW_LEN = len(ROW_KEYS)
#: The rows of :func:`measure_rows`' array, by part (the order of
#: :func:`mistool.kernels.pose.instance_from_masks`' answer).
SLOTS: tuple[str, ...] = ("shaft", "clasper", "wrist")
SLOT_OF: dict[str, int] = {name: k for k, name in enumerate(SLOTS)}
_STATUS_CELL = ROW_KEYS.index(AUX_STATUS)

_NAN_ROW = {k: math.nan for k in ROW_KEYS}

#: The shaft row's cells the kernel fills (``mistool.kernels.pose.OUT["row"]`` onward):
#: the distal flag, the limb lines to the sigmas, then the pose without its quality.
_SHAFT_CELLS: tuple[str, ...] = ("aux_distal", *AUX_KEYS[:12], *POSE_KEYS[:13])
_CLASPER_CELLS = POSE_KEYS[:6]  # end and axis
_START_CELLS = POSE_KEYS[6:9]
_QUAT_CELLS = POSE_KEYS[9:13]


def _nan_row() -> dict[str, float]:
    return _NAN_ROW.copy()


@functools.cache
def _params() -> np.ndarray:
    """The pose's parameters in the kernels' order (``mistool.kernels.pose.PARAMS``)."""
    from mistool.kernels.pose import PARAMS

    values = {
        "max_sigma_mm": MAX_SIGMA_MM,
        "max_sigma_deg": MAX_SIGMA_DEG,
        "px_noise": _PX_NOISE,
        "px_bias": _PX_BIAS,
        "max_cap_spread_mm": _MAX_CAP_SPREAD_MM,
        "min_line_points": _MIN_LINE_POINTS,
        "min_line_span_px": _MIN_LINE_SPAN_PX,
        "end_on_deg": _END_ON_DEG,
        "fit_max_points": FIT_MAX_POINTS,
        "fit_thresh_px": FIT_THRESH_PX,
        "fit_iters": _FIT_ITERS,
        "tip_length_factor": _TIP_LENGTH_FACTOR,
        "tip_length_sigma": _TIP_LENGTH_SIGMA,
        "tip_bend_sigma_rad": _TIP_BEND_SIGMA_RAD,
        "jaw_sep": _JAW_SEP,
        "jaw_rad": _JAW_RAD,
        "cut_angle_deg": _CUT_ANGLE_DEG,
        "cut_offset_frac": _CUT_OFFSET_FRAC,
    }
    return np.array([float(values[name]) for name in PARAMS])


#: The quality IoU's canvas is sampled every other pixel beyond this size (px).
_QUALITY_MAX_PIXELS = 40000


_LAST_CAMERA: list[tuple[Camera, np.ndarray, bool]] = []


def _camera(camera: Camera) -> tuple[np.ndarray, bool]:
    """``camera.K`` (3, 3) float64 (not to be written) and ``camera.distorted``, kept for
    the last camera seen (a run passes one camera to every call)."""
    last = _LAST_CAMERA[0] if _LAST_CAMERA else None
    if last is None or last[0] is not camera:
        last = (camera, np.ascontiguousarray(camera.K, dtype=np.float64), camera.distorted)
        _LAST_CAMERA[:] = [last]  # one reference swapped: safe across threads
    return last[1], last[2]


def _crop_bounds(mask: np.ndarray, offset: tuple[int, int]) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the full-image pixels a crop covers (inclusive)."""
    h, w = mask.shape
    return offset[0], offset[1], offset[0] + w - 1, offset[1] + h - 1


def _why(out: dict[str, dict[str, float]], reason: str, parts: Iterable[str] | None = None) -> None:
    """Record why the pose is empty (:mod:`mistool.pose.status`) on the given parts' rows
    (default: all), keeping a reason already recorded."""
    code = reason_code(reason)
    for name in out if parts is None else parts:
        if name in out and not out[name][AUX_STATUS] >= 0:
            out[name][AUX_STATUS] = code


def ideal_outline(pix: np.ndarray, bnd: Boundary, camera: Camera) -> tuple[np.ndarray, Boundary]:
    """The one place where mask points enter the pose: outline pixels (N, 2) and boundary
    points in the camera's image -> the same points in its ideal pinhole image
    (:func:`mistool.lens.undistort_points`; unchanged for an undistorted lens)."""
    if not camera.distorted:
        return pix, bnd
    n, m = len(pix), len(bnd.bg)
    ideal = undistort_points(np.concatenate([pix, bnd.bg, bnd.other]), camera)
    return ideal[:n], Boundary(bg=ideal[n : n + m], other=ideal[n + m :])


def _ideal_px(px: np.ndarray, camera: Camera) -> np.ndarray:
    """One pixel (2,) of the camera's image in its ideal image (``undistort_points``; the
    pixel itself for an undistorted lens)."""
    return undistort_points(px[None], camera)[0] if camera.distorted else px


class _ShaftPoints:
    """Every image point of the shaft that the pose uses (full-image px).

    Gathered in one place (:func:`_shaft_points`); the clasper's points enter separately,
    in :func:`_tip`. Points are in the camera's *ideal* pinhole image: with a distorted
    lens they are undistorted here (:func:`ideal_outline`); ``border`` and ``mask`` stay
    in the camera's image. (A plain class: a frozen dataclass costs microseconds to build.)

    Attributes:
        pix: (N, 2) outline pixels of the measured shaft region (ideal image).
        centre: (2,) the region's centroid (ideal image).
        moments: (6,) its region moments ``m00, m10, m01, m20, m11, m02`` (crop
            coordinates, as ``cv2.moments``).
        offset: (x0, y0) of the crop the moments refer to.
        bnd: sub-pixel boundary points: ``bg`` next to background, ``other`` next to the
            instrument's other parts.
        border: (N,) bool: the outline pixel is on the image border.
        mask: the measured shaft region (bool crop at ``offset``), for the quality IoU.
        merged: two shafts were found in the instance (only the larger is measured).
    """

    __slots__ = ("border", "bnd", "centre", "mask", "merged", "moments", "offset", "pix")

    def __init__(
        self,
        pix: np.ndarray,
        centre: np.ndarray,
        moments: np.ndarray,
        offset: tuple[int, int],
        bnd: Boundary,
        border: np.ndarray,
        mask: np.ndarray,
        merged: bool,
    ) -> None:
        self.pix, self.centre, self.moments, self.offset = pix, centre, moments, offset
        self.bnd, self.border, self.mask, self.merged = bnd, border, mask, merged


#: A shaft separated from its own wrist or clasper by a thin gap (a segmentation that
#: misses the junction) still meets them there: its outline points within this many px
#: of them are taken as next to them.
_JUNCTION_GAP_PX = 5
_GAP_DISK = cv2.getStructuringElement(
    cv2.MORPH_ELLIPSE, (2 * _JUNCTION_GAP_PX + 1, 2 * _JUNCTION_GAP_PX + 1)
)
#: The disk's half-width at each of its rows (the kernels' form of it; each row is
#: centred and unbroken, ``tests/test_pose_contours.py``).
_GAP_ROWS = ((_GAP_DISK.sum(axis=1) - 1) // 2).astype(np.int64)


def _across_gap(
    bnd: Boundary,
    shaft_mask: np.ndarray,
    offset: tuple[int, int],
    contours: Sequence[np.ndarray],
    others: list[tuple[np.ndarray, tuple[int, int]]],
    image_shape: tuple[int, int],
) -> Boundary:
    """The boundary points with the instrument's other parts grown by
    :data:`_JUNCTION_GAP_PX` (a thin gap at the junction closed), when that finds the
    junction; else ``bnd`` unchanged.

    The other parts count within the shaft's crop and a margin (``2 + gap`` px); grown,
    they reach ``gap`` px further, so only the window of their crops (within that margin)
    plus ``gap`` px is labelled and grown."""
    g = _JUNCTION_GAP_PX
    H, W = image_shape
    h, w = shaft_mask.shape
    cx0, cy0 = max(offset[0] - 2 - g, 0), max(offset[1] - 2 - g, 0)
    cx1, cy1 = min(offset[0] + w + 2 + g, W), min(offset[1] + h + 2 + g, H)
    x0, y0, x1, y1 = cx1, cy1, cx0, cy0  # the others' crops within the shaft's
    for m, (ox, oy) in others:
        x0, y0 = min(x0, max(ox, cx0)), min(y0, max(oy, cy0))
        x1, y1 = max(x1, min(ox + m.shape[1], cx1)), max(y1, min(oy + m.shape[0], cy1))
    x0, y0, x1, y1 = max(x0 - g, cx0), max(y0 - g, cy0), min(x1 + g, cx1), min(y1 + g, cy1)
    if x0 >= x1 or y0 >= y1:
        return bnd
    lab = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
    for m, (ox, oy) in others:
        paste(lab, x0, y0, as_mask(m), ox, oy, OTHER)
    paste(lab, x0, y0, shaft_mask, offset[0], offset[1], SHAFT)
    near = cv2.dilate(cv2.compare(lab, OTHER, cv2.CMP_EQ), _GAP_DISK) > 0  # type: ignore[call-overload]
    # the grown other parts: every pixel near one (the shaft's own stay the shaft's)
    found = outline_points(shaft_mask, offset, contours, [(near, (x0, y0))], image_shape)
    return found[2] if len(found[2].other) >= 3 else bnd


#: Shaft pieces are one shaft cut across when their directions agree within this (deg)
#: and each piece's centroid is within this fraction of the larger piece's width of
#: its axis line.
_CUT_ANGLE_DEG = 8.0
_CUT_OFFSET_FRAC = 0.35


def _one_cut_shaft(contours: Sequence[np.ndarray], areas: np.ndarray, big: int) -> bool:
    """Whether the large shaft pieces (area >= 25% of the largest) are one shaft cut
    across: each piece's centroid on the pieces' common axis (within
    :data:`_CUT_OFFSET_FRAC` of its own width across it) and each elongated piece along
    it (:data:`_CUT_ANGLE_DEG`); two tools side by side are half a width off it."""
    pieces = [
        c.reshape(-1, 2) for c, a in zip(contours, areas, strict=True) if a >= 0.25 * areas[big]
    ]
    pts = np.concatenate(pieces)
    x0, y0, w, h = cv2.boundingRect(pts)  # the points' min and max (numpy's are slow here)
    union = np.zeros((h, w), np.uint8)
    cv2.drawContours(union, [c - np.array([x0, y0], np.int32) for c in pieces], -1, 1, thickness=-1)
    starts = np.cumsum([0] + [len(c) for c in pieces], dtype=np.int64)
    return bool(
        kernels().one_cut_shaft(pts, starts, union, x0, y0, _CUT_ANGLE_DEG, _CUT_OFFSET_FRAC)
    )


def _shaft_points(
    parts: Mapping[str, PartObservation],
    image_shape: tuple[int, int],
    camera: Camera,
    distorted: bool,
) -> _ShaftPoints | str:
    """Gather the shaft's image points (the pose's pixel input, in the ideal image of
    ``camera``), or why there are none (``"not visible"``: no pixel; ``"rejected"``: no
    region).

    Two shafts in one instance (two tools touching in a merged mask): only the larger
    shaft is kept (and ``merged`` set: the clasper, whose jaws may be either tool's, is
    then left empty). Pieces of one shaft cut across (a specular streak, a thread, a
    segmentation gap: :func:`_one_cut_shaft`) are kept together: they share its limb lines.
    ``distorted``: ``camera.distorted``.
    """
    shaft = parts["shaft"]
    shaft_mask = as_mask(shaft.mask)
    smask = shaft_mask.view(np.uint8)
    contours, _ = cv2.findContours(smask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return "not visible"
    merged = False
    if len(contours) > 1:
        areas = np.array([cv2.contourArea(c) for c in contours])
        big = int(np.argmax(areas))
        if np.count_nonzero(areas >= 0.25 * areas[big]) > 1 and not _one_cut_shaft(
            contours, areas, big
        ):
            merged = True
            keep_u8 = np.zeros_like(smask)
            cv2.drawContours(keep_u8, contours, big, 1, thickness=-1)
            smask = np.ascontiguousarray(keep_u8 & smask)
            shaft_mask = smask.view(bool)
            contours = (contours[big],)
    others = [(p.mask, p.offset) for n, p in parts.items() if n != "shaft"]
    pix, border, bnd, mom = outline_points(shaft_mask, shaft.offset, contours, others, image_shape)
    if mom[0] < 1.0:  # degenerate outlines (lines of pixels): count pixels instead
        m = cv2.moments(smask, binaryImage=True)
        mom = np.array([m["m00"], m["m10"], m["m01"], m["m20"], m["m11"], m["m02"]])
    if mom[0] <= 0:
        return "rejected"
    if len(bnd.other) < 3 and others:  # a thin gap between the shaft and its head?
        bnd = _across_gap(bnd, shaft_mask, shaft.offset, contours, others, image_shape)
    m00, m10, m01 = mom[:3].tolist()
    centre = np.array([m10 / m00 + shaft.offset[0], m01 / m00 + shaft.offset[1]])
    ideal_pix = pix
    if distorted:
        ideal_pix, bnd = ideal_outline(pix, bnd, camera)
        centre = _ideal_px(centre, camera)
    return _ShaftPoints(ideal_pix, centre, mom, shaft.offset, bnd, border, shaft_mask, merged)


_NO_MASK = np.zeros((0, 0), dtype=bool)


class _ShaftMask:
    """The measured shaft region of :func:`_shaft_in_one_call` (the fields of
    :class:`_ShaftPoints` that :func:`measure_instance` reads after the kernel)."""

    __slots__ = ("mask", "merged", "offset")

    def __init__(self, mask: np.ndarray, offset: tuple[int, int], merged: bool) -> None:
        self.mask, self.offset, self.merged = mask, offset, merged


def _shaft_in_one_call(
    parts: Mapping[str, PartObservation],
    shaft: PartObservation,
    image_shape: tuple[int, int],
    K: np.ndarray,  # noqa: N803
    radius: float,
    res: np.ndarray,
    rims: Rims,
) -> _ShaftMask | str | None:
    """:func:`_shaft_points` and the shaft's pose in one kernel call
    (:func:`mistool.kernels.pose.shaft_from_masks`: one piece or several, a gap at the
    junction or none) for an undistorted camera and at most two other parts: the
    measured shaft region (``res`` and ``rims`` filled), ``"not visible"``, or None where
    :func:`_shaft_points` must answer (a piece that may lie in another's hole, an outline
    without area; nothing filled)."""
    others = [p for n, p in parts.items() if n != "shaft"]
    if len(others) > 2:
        return None
    kp = kernels()
    mask = as_mask(shaft.mask)
    masks = [(as_mask(p.mask), int(p.offset[0]), int(p.offset[1])) for p in others]
    masks += [(_NO_MASK, 0, 0)] * (2 - len(masks))
    (m1, x1, y1), (m2, x2, y2) = masks
    ox, oy = int(shaft.offset[0]), int(shaft.offset[1])
    H, W = image_shape
    geo = np.array([ox, oy, *mask.shape, H, W, _QUALITY_MAX_PIXELS, len(others)], np.int64)
    kept = np.empty(mask.shape, np.bool_)
    got = kp.shaft_from_masks(
        mask,
        m1,
        x1,
        y1,
        m2,
        x2,
        y2,
        K,
        radius,
        _params(),
        res,
        geo,
        rims.pts,
        rims.shifted,
        rims.canvas,
        kept,
        _GAP_ROWS,
    )
    if got == kp.SHAFT_MEASURED:
        return _ShaftMask(mask, (ox, oy), False)
    if got == kp.SHAFT_MERGED:
        return _ShaftMask(kept, (ox, oy), True)
    return "not visible" if got == kp.SHAFT_NOT_VISIBLE else None


def _shaft_in_steps(
    parts: Mapping[str, PartObservation],
    image_shape: tuple[int, int],
    camera: Camera,
    distorted: bool,
    K: np.ndarray,  # noqa: N803
    radius: float,
    res: np.ndarray,
    rims: Rims,
) -> _ShaftPoints | str:
    """:func:`_shaft_points`, then the shaft's pose from them
    (:func:`mistool.kernels.pose.shaft_pose`, into ``res`` and ``rims``): every path
    (a distorted lens, several pieces, a gap at the junction)."""
    sp = _shaft_points(parts, image_shape, camera, distorted)
    if isinstance(sp, str):
        return sp
    geo = np.array([*sp.offset, *sp.mask.shape, *image_shape, _QUALITY_MAX_PIXELS])
    bnd = sp.bnd
    kernels().shaft_pose(
        sp.pix,
        sp.border,
        sp.centre,
        sp.moments,
        bnd.bg,
        bnd.other,
        K,
        radius,
        _params(),
        res,
        geo,
        rims.pts,
        rims.shifted,
        rims.canvas,
    )
    return sp


def measure_instance(
    instance: InstanceObservation,
    image_shape: tuple[int, int],
    camera: Camera | None,
    shaft_diameter_mm: float | None,
    clasper_length_mm: float | None,
) -> dict[str, dict[str, float]]:
    """Metric pose of one instrument in one frame, by part name (a view of
    :func:`measure_rows`' array, for callers that want names: the viewer, tests).

    Args:
        instance: an ``InstanceObservation`` (``.parts``: part name -> observation with
            ``.mask`` (h, w) bool crop, ``.offset`` (x0, y0) px, ``.box`` RotatedBox).
        image_shape: (H, W) of the frame (px).
        camera: the pinhole intrinsics, or None (then every value is NaN).
        shaft_diameter_mm: the shaft's diameter (mm), or None (then NaN).
        clasper_length_mm: joint-to-tip length (mm), or None (the tip is then placed on
            the shaft axis' extension, i.e. assuming no bend out of the image plane).

    Returns:
        Part name -> {column: value} for every part of ``instance`` (of
        :data:`~mistool.model.PARTS`, the only ones a config can name): the columns of
        :data:`POSE_KEYS` (camera frame, mm, unit axes, quaternion wxyz, quality in [0, 1])
        plus :data:`AUX_KEYS`; NaN where unknown or not trustworthy.
    """
    rows = measure_rows(instance, image_shape, camera, shaft_diameter_mm, clasper_length_mm)
    cells = rows.tolist()
    return {
        name: dict(zip(ROW_KEYS, cells[SLOT_OF[name]], strict=True))
        for name in instance.parts
        if name in SLOT_OF
    }


def measure_rows(
    instance: InstanceObservation,
    image_shape: tuple[int, int],
    camera: Camera | None,
    shaft_diameter_mm: float | None,
    clasper_length_mm: float | None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """Metric pose of one instrument in one frame, as one array (what a worker sends and
    :class:`mistool.rows.RowBuilder` copies into its columns: no dict per part).

    Pure and thread-safe (no shared state; RANSAC uses a fixed table of draws). The steps
    (see the module docstring): gather the shaft's points (:func:`_shaft_points`), then
    the kernel :func:`mistool.kernels.pose.shaft_pose` (the shaft's image frame, limb
    lines, axis, joint, uncertainties, row), the shaft's quality, then the clasper's and
    the wrist's rows (:func:`_clasper_rows`); all in one kernel call where it can
    (:func:`_instance_in_one_call`), else in :func:`_instance_in_steps`.

    Args:
        instance, image_shape, camera, shaft_diameter_mm, clasper_length_mm: as
            :func:`measure_instance`.
        out: where to write the rows ((3, :data:`ROW_LEN`) float64, C-contiguous, e.g. a
            frame's ``(n, 3, ROW_LEN)`` array's ``[k]``); None: a new array.

    Returns:
        ``out``: row ``SLOT_OF[part]`` (:data:`SLOTS`: shaft, clasper, wrist) of each of
        ``instance``'s parts holds its :data:`ROW_KEYS` (:func:`measure_instance`'s
        values); the rows of parts it does not have are not to be read.
    """
    if out is None:
        out = np.empty((len(SLOTS), ROW_LEN))
    parts = instance.parts
    shaft = parts.get("shaft")
    if camera is None or shaft is None or shaft_diameter_mm is None or not shaft_diameter_mm > 0:
        out[:] = math.nan
        if camera is None:
            reason = "no camera"
        elif shaft is None or not shaft.mask.any():
            reason = "not visible"
        else:
            reason = "no shaft diameter"
        code = reason_code(reason)
        for name in parts:
            if name in SLOT_OF:
                out[SLOT_OF[name], _STATUS_CELL] = code
        return out
    K, distorted = _camera(camera)
    radius = 0.5 * float(shaft_diameter_mm)
    if not distorted and _instance_in_one_call(
        parts, shaft, image_shape, K, radius, clasper_length_mm, out
    ):
        return out
    steps = _instance_in_steps(
        parts, shaft, image_shape, camera, K, distorted, radius, clasper_length_mm
    )
    out[:] = math.nan
    for name, row in steps.items():
        if name in SLOT_OF:
            out[SLOT_OF[name]] = [row[k] for k in ROW_KEYS]
    return out


@functools.cache
def _reasons() -> np.ndarray:
    """The status code of each reason :func:`mistool.kernels.pose.instance_from_masks`
    records (``ONE_CALL_REASONS``; NaN for the first, no reason)."""
    names = kernels().ONE_CALL_REASONS
    return np.array([math.nan] + [reason_code(name) for name in names[1:]])


def _instance_in_one_call(
    parts: Mapping[str, PartObservation],
    shaft: PartObservation,
    image_shape: tuple[int, int],
    K: np.ndarray,  # noqa: N803
    radius: float,
    clasper_length_mm: float | None,
    rows: np.ndarray,
) -> bool:
    """:func:`measure_instance` in one kernel call for an undistorted camera and a shaft
    with at most a clasper and a wrist (:func:`mistool.kernels.pose.instance_from_masks`:
    :func:`_shaft_in_one_call`'s kernel, then :func:`_tip_in_one_call`'s, the rows written
    in order with their reasons) into ``rows`` (:func:`measure_rows`' ``out``): whether it
    answered; False where :func:`_instance_in_steps` must (:func:`_shaft_in_one_call` or
    :func:`_tip_in_one_call` would ask for the steps, a quality left to OpenCV, other
    parts: ``rows`` is not to be read then)."""
    if len(parts) > 3:
        return False
    m1 = m2 = _NO_MASK
    x1 = y1 = x2 = y2 = clasper = n = 0
    for name, p in parts.items():
        if name == "shaft":
            continue
        if name not in SLOT_OF:
            return False
        n += 1
        if n == 1:
            m1, x1, y1 = as_mask(p.mask), int(p.offset[0]), int(p.offset[1])
        else:
            m2, x2, y2 = as_mask(p.mask), int(p.offset[0]), int(p.offset[1])
        if name == "clasper":
            clasper = n
    H, W = image_shape
    asked = kernels().instance_from_masks(
        as_mask(shaft.mask),
        m1,
        x1,
        y1,
        m2,
        x2,
        y2,
        clasper,
        int(shaft.offset[0]),
        int(shaft.offset[1]),
        int(H),
        int(W),
        _QUALITY_MAX_PIXELS,
        n,
        K,
        radius,
        math.nan if clasper_length_mm is None else float(clasper_length_mm),
        float(_TIP_CAP),
        _params(),
        _GAP_ROWS,
        _reasons(),
        rows,
    )
    return not asked


def _instance_in_steps(
    parts: Mapping[str, PartObservation],
    shaft: PartObservation,
    image_shape: tuple[int, int],
    camera: Camera,
    K: np.ndarray,  # noqa: N803
    distorted: bool,
    radius: float,
    clasper_length_mm: float | None,
) -> dict[str, dict[str, float]]:
    """:func:`measure_instance` in steps: the shaft (:func:`_shaft_in_one_call`, else
    :func:`_shaft_in_steps`), its quality, then the clasper's and the wrist's rows
    (:func:`_clasper_rows`): every path."""
    out = {name: _nan_row() for name in parts}
    kp = kernels()
    OUT = kp.OUT
    res = np.empty(OUT["size"])
    rims = Rims()
    sp: _ShaftMask | _ShaftPoints | str | None = None
    if not distorted:
        sp = _shaft_in_one_call(parts, shaft, image_shape, K, radius, res, rims)
    if sp is None:
        sp = _shaft_in_steps(parts, image_shape, camera, distorted, K, radius, res, rims)
    if isinstance(sp, str):
        _why(out, sp)
        return out
    row = out["shaft"]
    row.update(zip(_SHAFT_CELLS, res[: len(_SHAFT_CELLS)].tolist(), strict=True))
    qa, qb = OUT["quality_a"], OUT["quality_b"]
    if distorted and not math.isnan(res[qa]):
        ends = res[qa : qa + 3], res[qb : qb + 3]
        row["quality"] = cylinder_iou(
            *ends, radius, radius, K, sp.mask, sp.offset, image_shape, camera
        )
    elif not math.isnan(res[qa]):
        if isinstance(sp, _ShaftMask) and not res[OUT["quality_opencv"]]:
            row["quality"] = float(res[OUT["quality"]])  # given by the one call
        else:
            row["quality"] = rims_iou(rims, sp.mask, sp.offset)
    why_shaft, why_all = int(res[OUT["why_shaft"]]), int(res[OUT["why_all"]])
    if why_shaft:
        _why(out, kp.WHY[why_shaft], ("shaft",))
    if why_all:
        _why(out, kp.WHY[why_all])
    elif res[OUT["clasper"]]:
        if sp.merged:
            _why(out, "merged")
        else:
            j, a = OUT["joint"], OUT["a"]
            joint, axis = res[j : j + 3], res[a : a + 3]
            _clasper_rows(
                out,
                parts,
                joint,
                axis,
                K,
                radius,
                image_shape,
                clasper_length_mm,
                camera,
                distorted,
            )
    return out


#: Tip depth prior: the joint-to-tip distance is the configured clasper length when the
#: wrist is straight and the jaws closed; opening and bending shorten it by a few percent.
_TIP_LENGTH_FACTOR = 1.0
_TIP_LENGTH_SIGMA = 0.05  # relative
_TIP_BEND_SIGMA_RAD = math.radians(45.0)
#: Jaw-end search: two jaw ends are distinct when more than this many jaw widths apart;
#: an end's jaw axis is estimated from the clasper pixels within this many jaw widths.
_JAW_SEP = 1.0
_JAW_RAD = 2.5
#: Fraction of the end-cap overshoot (jaw image radius x |cos(jaw, ray)|) removed.
_TIP_CAP = 1.0


def _clasper_rows(
    out: dict[str, dict[str, float]],
    parts: Mapping[str, PartObservation],
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,
    radius: float,
    image_shape: tuple[int, int],
    clasper_length_mm: float | None,
    camera: Camera,
    distorted: bool,
) -> None:
    """Fill the clasper's row (tip, clasper axis, quality) and the wrist's (its axis);
    ``distorted``: ``camera.distorted``."""
    clasper = parts.get("clasper")
    kp = kernels()
    tip = np.full(kp.TIP["size"], math.nan)
    got, quality = kp.CLASPER_EMPTY, math.nan
    if clasper is not None:
        mask = as_mask(clasper.mask)
        length_mm = math.nan if clasper_length_mm is None else float(clasper_length_mm)
        got = kp.CLASPER_ASK_PYTHON
        if not distorted:
            got, quality = _tip_in_one_call(
                clasper, mask, joint, a, K, image_shape, length_mm, radius, tip
            )
        if got == kp.CLASPER_ASK_PYTHON:
            got, quality = _tip_in_steps(
                clasper, mask, joint, a, K, image_shape, length_mm, radius, camera, distorted, tip
            )
    if got >= 0:  # a clasper with pixels
        crow = out["clasper"]
        if got:
            crow["aux_u_px"], crow["aux_v_px"] = tip[0], tip[1]
        if got == 2:
            crow.update(zip(_CLASPER_CELLS, tip[2:8].tolist(), strict=True))
            crow.update(zip(_QUAT_CELLS, tip[8:12].tolist(), strict=True))
            crow.update(zip(_START_CELLS, joint.tolist(), strict=True))
            crow["quality"] = quality
        else:
            _why(out, "tip not found", ("clasper", "wrist"))
    else:
        _why(out, "no clasper", ("wrist",))
    if "wrist" in parts:
        wrow = out["wrist"]
        if not math.isnan(tip[5]):
            wrow.update(zip(_CLASPER_CELLS[3:], tip[5:8].tolist(), strict=True))
            wrow.update(zip(_QUAT_CELLS, tip[8:12].tolist(), strict=True))
        wrow.update(zip(_START_CELLS, joint.tolist(), strict=True))


def _tip_in_one_call(
    clasper: PartObservation,
    mask: np.ndarray,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,  # noqa: N803
    image_shape: tuple[int, int],
    length_mm: float,
    radius: float,
    tip: np.ndarray,
) -> tuple[int, float]:
    """The clasper's tip and quality in one kernel call for an undistorted camera
    (:func:`mistool.kernels.pose.clasper_from_mask`: its outline, :func:`_tip`'s kernel,
    the quality): ``(got, quality)``, ``got`` as :func:`_tip` or the kernel's
    ``CLASPER_EMPTY`` / ``CLASPER_ASK_PYTHON`` (a crop of several pieces where one's box
    holds another's: nothing done)."""
    kp = kernels()
    ox, oy = int(clasper.offset[0]), int(clasper.offset[1])
    H, W = image_shape
    rims, quality = Rims(), np.empty(2)
    got = int(
        kp.clasper_from_mask(
            mask,
            ox,
            oy,
            joint,
            a,
            K,
            length_mm,
            int(H),
            int(W),
            float(_TIP_CAP),
            _params(),
            tip,
            radius,
            _QUALITY_MAX_PIXELS,
            rims.pts,
            rims.shifted,
            rims.canvas,
            quality,
        )
    )
    if got == 2 and quality[1]:  # the hull rests on float rounding: OpenCV's
        return got, rims_iou(rims, mask, (ox, oy))
    return got, float(quality[0])


def _tip_in_steps(
    clasper: PartObservation,
    mask: np.ndarray,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,  # noqa: N803
    image_shape: tuple[int, int],
    length_mm: float,
    radius: float,
    camera: Camera,
    distorted: bool,
    tip: np.ndarray,
) -> tuple[int, float]:
    """:func:`_tip` on the clasper's longest outline (:func:`_longest_outline`), then the
    quality: every path (a distorted lens, a crop whose pieces' boxes nest); ``(got, quality)``
    as :func:`_tip_in_one_call`."""
    outline = _longest_outline(mask)
    if outline is None:
        return kernels().CLASPER_EMPTY, math.nan
    rims = Rims()
    got = _tip(
        clasper,
        mask,
        outline,
        joint,
        a,
        K,
        image_shape,
        length_mm,
        radius,
        camera,
        distorted,
        tip,
        rims,
    )
    if got != 2:
        return got, math.nan
    if distorted:
        ends = joint, tip[2:5]
        return got, cylinder_iou(
            *ends,
            0.5 * radius,
            0.25 * radius,
            K,
            clasper.mask,
            clasper.offset,
            image_shape,
            camera,
        )
    return got, rims_iou(rims, mask, clasper.offset)


def _longest_outline(mask: np.ndarray) -> np.ndarray | None:
    """The longest outer contour of a bool crop (N, 2) int32 (crop px, every outline
    pixel: ``cv2.findContours``' first longest, traced by
    :func:`mistool.kernels.contours.outer_contour` when the crop holds one piece), or
    None for an empty crop."""
    from mistool.kernels.contours import outer_contour

    h, w = mask.shape
    buf = np.empty((4 * (h + w) + 16, 2), np.int32)
    n = outer_contour(mask, buf)
    if n == -2:  # a long border: the bound that always holds
        buf = np.empty((4 * h * w + 4, 2), np.int32)
        n = outer_contour(mask, buf)
    if n > 0:
        return buf[:n]
    if n == 0:
        return None
    contours = cv2.findContours(mask.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0]
    return max(contours, key=len).reshape(-1, 2)


def _tip(
    clasper: PartObservation,
    mask: np.ndarray,
    ci: np.ndarray,
    joint: np.ndarray,
    a: np.ndarray,
    K: np.ndarray,
    image_shape: tuple[int, int],
    length_mm: float,
    radius: float,
    camera: Camera,
    distorted: bool,
    out: np.ndarray,
    rims: Rims,
) -> int:
    """The tip's pixel, the tip and the clasper axis (ideal image; camera frame, mm) into
    ``out`` (``mistool.kernels.pose.TIP``) from the clasper's crop ``mask`` and its
    outline pixels ``ci`` (crop px, :func:`_longest_outline`); 0: none found, 1: the
    tip's pixel only, 2: all.
    Undistorted, the clasper's quality cylinder's image into ``rims`` as well.

    The jaw ends are found on the clasper's mask, in the camera's image
    (:func:`mistool.kernels.pose.jaw_ends`: the local maxima of the distance from J's
    pixel along the clasper's outline, at least half as far as the farthest; the two
    farthest more than ``_JAW_SEP`` jaw widths apart are two open jaws, a single one
    closed jaws; each end moved onto its jaw's axis, the principal direction of the
    clasper pixels within ``_JAW_RAD`` jaw widths), and undistorted (:mod:`mistool.lens`)
    before they meet the 3D geometry.

    The tip's pixel is the mid-point of the jaw ends, each end pulled back by its end
    cap's overshoot (the truth's jaw end is the cap's centre, the image ends at the cap's
    rim: a jaw's image radius x |cos(jaw, viewing ray)|). Its depth along the pixel's ray
    minimises a two-term cost (:func:`mistool.kernels.pose.tip_solve`): the joint-to-tip
    distance near the clasper length (well conditioned when the clasper is foreshortened)
    and a small bend from the shaft axis (well conditioned when the clasper is seen
    side-on). When the tip is cut by the image border it is placed at the nominal length
    along the least bent direction that projects along the clasper's image direction.
    """
    kp = kernels()
    ox, oy = clasper.offset
    H, W = image_shape
    width_px = max(K[0, 0] * 0.25 * (2.0 * radius) / max(float(joint[2]), 1.0), 2.0)
    box = _crop_bounds(mask, clasper.offset)
    at_border = min(box[:2]) <= 0 or box[2] >= W - 1 or box[3] >= H - 1
    par, cap = _params(), float(_TIP_CAP)
    if not distorted:
        return int(
            kp.tip_pose(
                ci,
                mask,
                ox,
                oy,
                joint,
                a,
                K,
                width_px,
                length_mm,
                at_border,
                H,
                W,
                cap,
                par,
                out,
                radius,
                _QUALITY_MAX_PIXELS,
                rims.pts,
                rims.shifted,
                rims.canvas,
            )
        )
    jx, jy, jz = joint.tolist()
    jpx = np.array([K[0, 0] * jx / jz + K[0, 2], K[1, 1] * jy / jz + K[1, 2]])  # project()
    ju, jv = distort_points(jpx[None], camera)[0].tolist()
    ends = np.empty((2, 5))
    found = int(kp.jaw_ends(ci, mask, ox, oy, ju, jv, width_px, at_border, H, W, par, ends))
    n, hidden = found & 3, found >= 4
    if not n:
        return 0
    ju, jv = jpx.tolist()
    tu, tv = _ideal_px(_mid(ends, n), camera).tolist()
    got = int(kp.tip_solve(tu, tv, joint, a, K, length_mm, hidden, ju, jv, par, out))
    if got < 2 or hidden or not cap:
        return got
    # a jaw's image ends at its end cap's rim, which reaches beyond the cap's centre (the
    # truth's jaw end) by the jaw's image radius x |cos(jaw, viewing ray)|: pull each end
    # back by that (the clasper axis stands in for each jaw's direction) and solve again
    tx, ty, tz, cx, cy, cz = out[2:8].tolist()
    cos_v = abs(cx * tx + cy * ty + cz * tz) / math.sqrt(tx * tx + ty * ty + tz * tz)
    for k in range(n):
        ends[k, :2] -= cap * ends[k, 4] * cos_v * ends[k, 2:4]
    tu, tv = _ideal_px(_mid(ends, n), camera).tolist()
    return int(kp.tip_solve(tu, tv, joint, a, K, length_mm, hidden, ju, jv, par, out))


def _mid(ends: np.ndarray, n: int) -> np.ndarray:
    """The tip's pixel: the jaw end, or the mid-point of the two (``ends`` (2, 5))."""
    return ends[0, :2] if n == 1 else 0.5 * (ends[0, :2] + ends[1, :2])
