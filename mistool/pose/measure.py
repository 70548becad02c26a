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
   nearest-to-proximal point of the chord next to background).
4. Tip: the clasper's far end in the image (jaw tips' mid-point), back-projected at the
   known clasper length from J (the solution bending least from the shaft axis); when
   the tip is cut by the image border, J + length x the least-bent direction that
   projects along the clasper's image direction.
5. ``quality``: IoU of the re-rendered part with its mask (:mod:`mistool.pose.quality`).

Never a confident wrong answer: where the geometry is degenerate (one limb line, the
shaft seen end-on, J out of the image, numerically unstable solutions) the cells are NaN.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from mistool.pose.cylinder import (
    axis_from_lines,
    closest_on_axis,
    cross3,
    pixel_rays,
    project,
    quat_from_z,
    ray_cylinder,
    tangent_plane,
)
from mistool.pose.quality import hull_of_cylinder, iou_polygon_mask
from mistool.pose.silhouette import boundary_points, fit_line_robust, make_canvas

__all__ = ["AUX_KEYS", "POSE_KEYS", "SENSITIVITY_MAX_MM_PER_PX", "measure_instance"]

#: The metric columns :func:`measure_instance` fills for each part.
POSE_KEYS: tuple[str, ...] = (
    "end_x_mm", "end_y_mm", "end_z_mm", "axis_x", "axis_y", "axis_z",
    "start_x_mm", "start_y_mm", "start_z_mm", "qw", "qx", "qy", "qz", "quality",
)
#: Per-frame auxiliary values (extra columns) that :func:`refine_sequence` uses to
#: re-solve frames with the trocar constraint, then drops. Limb lines are image lines
#: ``a u + b v + c = 0`` (px, unit normal, shaft inside positive); ``aux_u_px, aux_v_px``
#: is the joint's pixel (shaft row) or the tip's pixel (clasper row); ``aux_sens_mm_px``
#: the joint's sensitivity to a limb line moving by one pixel (mm/px);
#: ``aux_distal`` 1 when the distal direction was seen in this frame, else 0.
AUX_KEYS: tuple[str, ...] = (
    "aux_l1a", "aux_l1b", "aux_l1c", "aux_l2a", "aux_l2b", "aux_l2c",
    "aux_u_px", "aux_v_px", "aux_sens_mm_px", "aux_distal",
)

#: Above this joint sensitivity (mm per px of limb-line error) the shaft pose is left
#: empty: the view is too close to end-on (or the lines too short) to trust the depth.
SENSITIVITY_MAX_MM_PER_PX = 25.0
_MIN_LINE_POINTS = 10
_MIN_LINE_SPAN_PX = 12.0
_SEED = 12345


def _nan_row() -> dict[str, float]:
    return {k: math.nan for k in POSE_KEYS + AUX_KEYS}


def _as_u8(mask: np.ndarray) -> np.ndarray:
    m = np.ascontiguousarray(mask)
    return m.view(np.uint8) if m.dtype == np.bool_ else (m != 0).astype(np.uint8)


def _outline(mask_u8: np.ndarray, offset: tuple[int, int]
             ) -> tuple[np.ndarray, dict[str, float]]:
    """Outline pixels (N, 2) of a mask (full-image px) and its region moments.

    A region's extreme points in any direction are outline pixels, so the outline
    replaces the full pixel list wherever only extremes are needed (much faster).
    """
    contours, _ = cv2.findContours(mask_u8, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64)
    mom = {"m00": 0.0, "m10": 0.0, "m01": 0.0, "m20": 0.0, "m11": 0.0, "m02": 0.0}
    for c in contours:
        m = cv2.moments(c)
        for k in mom:
            mom[k] += m[k]
    if mom["m00"] < 1.0:  # degenerate outlines (lines of pixels): count pixels instead
        m = cv2.moments(mask_u8, binaryImage=True)
        mom = {k: m[k] for k in mom}
    pts += offset
    return pts, mom


def _on_border(px: np.ndarray, image_shape: tuple[int, int]) -> np.ndarray:
    H, W = image_shape
    return (px[:, 0] <= 0) | (px[:, 1] <= 0) | (px[:, 0] >= W - 1) | (px[:, 1] >= H - 1)


def _fill_pose(row: dict[str, float], end: np.ndarray | None, axis: np.ndarray | None,
               start: np.ndarray | None) -> None:
    if end is not None:
        row["end_x_mm"], row["end_y_mm"], row["end_z_mm"] = (float(v) for v in end)
    if axis is not None:
        row["axis_x"], row["axis_y"], row["axis_z"] = (float(v) for v in axis)
        row["qw"], row["qx"], row["qy"], row["qz"] = (float(v) for v in quat_from_z(axis))
    if start is not None:
        row["start_x_mm"], row["start_y_mm"], row["start_z_mm"] = (float(v) for v in start)


def _joint_t(pts: np.ndarray, is_other: np.ndarray, p0: np.ndarray, a: np.ndarray,
             radius: float, K: np.ndarray) -> float:
    """J's axial coordinate from the shaft's distal outline points.

    Next to background the outline is exactly where the ray's chord through the infinite
    cylinder first reaches J's axial coordinate (``min(t_in, t_out) == t_J``); next to the
    clasper it is where the ray enters the cylinder at ``t_J`` (exact for a clasper or
    wrist as wide as the shaft; a narrower clasper seen over the shaft's end face biases it
    distally), so background points are preferred when there are enough of them.
    """
    rays = pixel_rays(pts, K)
    t_in, t_out, _ = ray_cylinder(rays, p0, a, radius)
    bg = ~is_other
    if np.count_nonzero(bg) >= 5:
        return float(np.median(np.minimum(t_in, t_out)[bg]))
    return float(np.median(np.where(is_other, t_in, np.minimum(t_in, t_out))))


def measure_instance(instance: Any, image_shape: tuple[int, int], camera: Any,
                     shaft_diameter_mm: float | None, clasper_length_mm: float | None
                     ) -> dict[str, dict[str, float]]:
    """Metric pose of one instrument in one frame.

    Pure and thread-safe (no shared state; the RANSAC generator is seeded per call).

    Args:
        instance: an ``InstanceObservation`` (``.parts``: part name -> observation with
            ``.mask`` (h, w) bool crop, ``.offset`` (x0, y0) px, ``.box`` RotatedBox).
        image_shape: (H, W) of the frame (px).
        camera: ``mistool.config.Camera`` or None (then every value is NaN).
        shaft_diameter_mm: the shaft's diameter (mm), or None (then NaN).
        clasper_length_mm: joint-to-tip length (mm), or None (the tip is then placed on
            the shaft axis' extension, i.e. assuming no bend out of the image plane).

    Returns:
        Part name -> {column: value} for every part of ``instance``: the columns of
        :data:`POSE_KEYS` (camera frame, mm, unit axes, quaternion wxyz, quality in [0, 1])
        plus :data:`AUX_KEYS`; NaN where unknown or not trustworthy.
    """
    parts = instance.parts
    out = {name: _nan_row() for name in parts}
    shaft = parts.get("shaft")
    if (camera is None or shaft is None or shaft_diameter_mm is None
            or not shaft_diameter_mm > 0 or not np.any(shaft.mask)):
        return out
    K = np.asarray(camera.K, dtype=np.float64)
    radius = 0.5 * float(shaft_diameter_mm)
    row = out["shaft"]
    rng = np.random.default_rng(_SEED)

    smask = _as_u8(shaft.mask)
    others = [(p.mask, p.offset) for n, p in parts.items() if n != "shaft"]
    canvas = make_canvas(shaft.mask, shaft.offset, others, image_shape)

    # principal axis of the shaft's region
    pix, mom = _outline(smask, shaft.offset)
    if mom["m00"] <= 0:
        return out
    bnd = boundary_points(canvas, pix)
    xm, ym = mom["m10"] / mom["m00"], mom["m01"] / mom["m00"]
    mu20 = mom["m20"] / mom["m00"] - xm * xm
    mu02 = mom["m02"] / mom["m00"] - ym * ym
    mu11 = mom["m11"] / mom["m00"] - xm * ym
    theta = 0.5 * math.atan2(2.0 * mu11, mu20 - mu02)
    e = np.array([math.cos(theta), math.sin(theta)])
    centre = np.array([xm + shaft.offset[0], ym + shaft.offset[1]])
    s_pix = (pix - centre) @ e

    # which end is distal: toward the other parts, else away from the image border
    if len(bnd.other) >= 3:
        distal = 1 if float(np.mean((bnd.other - centre) @ e)) >= 0 else -1
    else:
        lo, hi = s_pix.min(), s_pix.max()
        border = _on_border(pix, image_shape)
        t_lo = bool(np.any(border & (s_pix <= lo + 2.0)))
        t_hi = bool(np.any(border & (s_pix >= hi - 2.0)))
        distal = 1 if (t_lo and not t_hi) else (-1 if (t_hi and not t_lo) else 0)
    if distal < 0:
        e = -e
        s_pix = -s_pix
    s_min, s_max = float(s_pix.min()), float(s_pix.max())
    border = _on_border(pix, image_shape)
    prox_at_border = bool(np.any(border & (s_pix <= s_min + 2.0)))
    dist_at_border = bool(np.any(border & (s_pix >= s_max - 2.0)))
    row["aux_distal"] = 1.0 if distal != 0 else 0.0

    # limb-line candidates
    width = float(shaft.box.width) if hasattr(shaft, "box") else 4.0 * math.sqrt(
        max(min(mu20, mu02), 0.25))
    zone = 0.6 * width + 2.0
    pts = bnd.bg
    s = (pts - centre) @ e
    keep = s < s_max - zone
    if not prox_at_border:
        keep &= s > s_min + zone
    if len(bnd.other):  # leave out points within 3 px of another part
        lo, hi = bnd.other.min(axis=0) - 3.0, bnd.other.max(axis=0) + 3.0
        box = np.flatnonzero(keep & np.all((pts >= lo) & (pts <= hi), axis=1))
        if len(box):
            d2 = ((pts[box, None, :] - bnd.other[None, ::2, :]) ** 2).sum(axis=2)
            keep[box[d2.min(axis=1) < 9.0]] = False
    eperp = np.array([-e[1], e[0]])
    q = (pts - centre) @ eperp
    lines: list[np.ndarray | None] = []
    sigmas: list[float] = []
    for side in (q < 0, q > 0):
        sel = keep & side
        fit = fit_line_robust(pts[sel], s[sel], rng) if sel.sum() >= _MIN_LINE_POINTS else None
        if fit is not None:
            line, inl, sig = fit
            span = np.ptp(s[sel][inl]) if inl.any() else 0.0
            if inl.sum() < _MIN_LINE_POINTS or span < _MIN_LINE_SPAN_PX:
                fit = None
        if fit is None:
            lines.append(None)
            sigmas.append(math.inf)
            continue
        line = fit[0]
        if line[:2] @ centre + line[2] < 0:
            line = -line
        lines.append(line)
        sigmas.append(fit[2])
    for k, line in enumerate(lines):
        if line is not None:
            for j, c in enumerate("abc"):
                row[f"aux_l{k + 1}{c}"] = float(line[j])
    # the joint's pixel (for a later trocar-constrained solve)
    if len(bnd.other) >= 3:
        jpx = np.median(bnd.other, axis=0)
    elif distal != 0 and not dist_at_border:
        jpx = pix[s_pix >= s_max - 1.0].mean(axis=0)
    else:
        jpx = None
    if jpx is not None:
        row["aux_u_px"], row["aux_v_px"] = float(jpx[0]), float(jpx[1])
    if lines[0] is None or lines[1] is None:
        return out  # one limb line: refine_sequence may solve it with the trocar

    n1, n2 = tangent_plane(lines[0], K), tangent_plane(lines[1], K)
    sol = axis_from_lines(n1, n2, radius)
    if sol is None:
        return out
    p0, a = sol
    cray = pixel_rays(centre[None], K)
    tc = float(closest_on_axis(cray, p0, a)[0])
    xc = p0 + tc * a
    if xc[2] <= 0:
        return out
    step = project(np.stack([xc, xc + a]), K)
    if float((step[1] - step[0]) @ e) < 0:
        a = -a
        tc = -tc
        p0 = p0.copy()
    if distal == 0 and a[2] < 0:  # no distal cue: by convention, into the scene
        a = -a
    # sanity: apparent width at the centroid vs the mask's
    wc = float(lines[0][:2] @ centre + lines[0][2] + lines[1][:2] @ centre + lines[1][2])
    if not 0.5 * width <= wc <= 1.6 * width + 2.0:
        return out

    # joint J
    joint = None
    if distal != 0 and not (dist_at_border and len(bnd.other) < 3):
        near_end = (s >= s_max - zone)
        d1 = np.abs(pts @ lines[0][:2] + lines[0][2])
        d2 = np.abs(pts @ lines[1][:2] + lines[1][2])
        tol = max(1.0, 2.5 * max(sigmas))
        cap = near_end & (d1 > tol) & (d2 > tol)
        end_pts = np.concatenate([bnd.other, pts[cap]])
        is_other = np.zeros(len(end_pts), dtype=bool)
        is_other[:len(bnd.other)] = True
        if len(end_pts) >= 3:
            tj = _joint_t(end_pts, is_other, p0, a, radius, K)
            joint = p0 + tj * a
            if joint[2] <= 0:
                joint = None

    # sensitivity of the joint (or the centroid's axis point) to a 0.5 px line shift
    ref = joint if joint is not None else xc
    rref = ref / np.linalg.norm(ref)
    sens = 0.0
    for k in range(2):
        moved = [lines[0].copy(), lines[1].copy()]
        moved[k][2] -= 0.5
        solk = axis_from_lines(tangent_plane(moved[0], K), tangent_plane(moved[1], K), radius)
        if solk is None:
            sens = math.inf
            break
        tk = float(closest_on_axis(rref[None], solk[0], solk[1])[0])
        sens += float(np.sum((solk[0] + tk * solk[1] - ref) ** 2))
    sens = math.sqrt(sens) / 0.5
    row["aux_sens_mm_px"] = sens
    if not sens <= SENSITIVITY_MAX_MM_PER_PX:
        return out

    # proximal end: where the shaft leaves the view (or its proximal end)
    prox = pix[s_pix <= s_min + 1.0].mean(axis=0)
    t_start = float(closest_on_axis(pixel_rays(prox[None], K), p0, a)[0])
    start = p0 + t_start * a
    t_far = float(closest_on_axis(pixel_rays(pix[s_pix >= s_max - 1.0].mean(axis=0)[None], K),
                                  p0, a)[0])
    t_end = float((joint - p0) @ a) if joint is not None else t_far
    if start[2] <= 0 or t_end <= t_start:
        start = None
    _fill_pose(row, joint, a, start)
    if start is not None:
        poly = hull_of_cylinder(start, p0 + t_end * a, radius, radius, K)
        row["quality"] = iou_polygon_mask(poly, shaft.mask, shaft.offset, image_shape)

    # clasper / wrist
    if joint is None:
        return out
    clasper = parts.get("clasper")
    c_axis = None
    if clasper is not None and np.any(clasper.mask):
        tip, c_axis, tip_px = _tip(clasper, joint, a, K, image_shape, clasper_length_mm)
        crow = out["clasper"]
        if tip_px is not None:
            crow["aux_u_px"], crow["aux_v_px"] = float(tip_px[0]), float(tip_px[1])
        if tip is not None:
            _fill_pose(crow, tip, c_axis, joint)
            poly = hull_of_cylinder(joint, tip, 0.5 * radius, 0.25 * radius, K)
            crow["quality"] = iou_polygon_mask(poly, clasper.mask, clasper.offset, image_shape)
    if "wrist" in parts:
        _fill_pose(out["wrist"], None, c_axis, joint)
    return out


def _tip(clasper: Any, joint: np.ndarray, a: np.ndarray, K: np.ndarray,
         image_shape: tuple[int, int], length: float | None
         ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """Tip (3,), clasper axis (3,) and the tip's pixel (2,) (or Nones)."""
    pts, _ = _outline(_as_u8(clasper.mask), clasper.offset)
    jpx = project(joint[None], K)[0]
    v = pts - jpx
    mean = v.mean(axis=0)
    if np.linalg.norm(mean) < 2.0:
        return None, None, None
    u = mean / np.linalg.norm(mean)
    s = v @ u
    s_max = float(s.max())
    band = s >= s_max - max(2.0, 0.15 * s_max)
    q = v[band] @ np.array([-u[1], u[0]])
    q_mid = 0.5 * (float(q.min()) + float(q.max()))
    tip_px = jpx + (s_max + 0.5) * u + q_mid * np.array([-u[1], u[0]])
    hidden = bool(np.any(_on_border(pts[band], image_shape)))
    ray = pixel_rays(tip_px[None], K)[0]
    if hidden:
        if length is None:
            return None, None, tip_px
        r2 = pixel_rays((jpx + 10.0 * u)[None], K)[0]
        nc = cross3(joint / np.linalg.norm(joint), r2)
        nc /= np.linalg.norm(nc)
        c = a - (a @ nc) * nc
        if np.linalg.norm(c) < 1e-6:
            return None, None, tip_px
        c /= np.linalg.norm(c)
        step = project(np.stack([joint, joint + c]), K)
        if float((step[1] - step[0]) @ u) < 0:
            c = -c
        return joint + length * c, c, tip_px
    if length is None:
        t = float(closest_on_axis(ray[None], joint, a)[0])
        x = joint + t * a
        s_ray = float(ray @ x)
        tip = s_ray * ray
    else:
        b = float(ray @ joint)
        disc = b * b - float(joint @ joint) + length**2
        if disc < 0:
            tip = b * ray
        else:
            cands = [(b - math.sqrt(disc)) * ray, (b + math.sqrt(disc)) * ray]
            cands = [c for c in cands if c[2] > 0]
            if not cands:
                return None, None, tip_px
            tip = max(cands, key=lambda x: float((x - joint) @ a))
    d = tip - joint
    nd = np.linalg.norm(d)
    if nd < 1e-6:
        return None, None, tip_px
    return tip, d / nd, tip_px
