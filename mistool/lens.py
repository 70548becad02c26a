"""Lens distortion: pixel points between the camera's image and its ideal pinhole image.

A real endoscope's lens bends straight lines (barrel distortion, ~10-20% at the corners of
a wide-angle view). The metric pose needs the ideal pinhole image, where a cylinder's
outline is two straight lines, so the points it uses (mask outlines, the joint's and the
tip's pixels) are *undistorted* here, never whole images (cheap: a few thousand points
per instrument and frame). The ideal image uses the same intrinsics ``K`` as the camera
(OpenCV's ``P = K``), so a 3D point ``X`` is at ``K X / z`` there.

Models (OpenCV's): ``"pinhole"`` with 4, 5, 8, 12 or 14 coefficients ``(k1, k2, p1, p2,
k3, k4, k5, k6, s1, s2, s3, s4, tx, ty)`` (:func:`cv2.undistortPoints`,
:func:`cv2.projectPoints`) and ``"fisheye"`` with 4 (:func:`cv2.fisheye.undistortPoints`,
:func:`cv2.fisheye.distortPoints`). Undistortion is iterative; it runs to
:data:`UNDISTORT_CRITERIA` (OpenCV's default of 5 iterations leaves ~0.5 px of error at
the corners of a strongly distorted lens; these criteria leave < 1e-9 px).

Conventions: pixels x right, y down, pixel centres at integer coordinates; points are
``(N, 2)`` float64 arrays.
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache

import cv2
import numpy as np

from mistool.config import Camera
from mistool.errors import ConfigError

__all__ = [
    "UNDISTORT_CRITERIA",
    "distort_points",
    "fit_camera",
    "ideal_bounds",
    "undistort_image",
    "undistort_maps",
    "undistort_view",
    "undistort_points",
]

#: Termination of the iterative undistortion: at most 100 iterations or a step < 1e-12
#: (normalised units).
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
#: Masks whose size differs from the calibration's by a factor within this relative
#: tolerance on both axes are a uniform scaling of it (e.g. 1920x1080 -> 960x540).
SCALE_TOLERANCE = 0.01


def _kd(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    K = np.array(
        [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]],
        dtype=np.float64,
    )
    return K, np.asarray(camera.distortion, dtype=np.float64)


def undistort_points(points: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixels of the camera's image -> pixels of its ideal pinhole image (same ``K``).

    Args:
        points: (N, 2) pixel coordinates in the (distorted) image.
        camera: the camera (returned unchanged, as float64, for an ideal lens).

    Returns:
        (N, 2) float64 pixel coordinates in the ideal image.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not camera.distorted or len(pts) == 0:
        return pts.copy()
    K, D = _kd(camera)
    src = pts.reshape(-1, 1, 2)
    if camera.model == "fisheye":
        out = cv2.fisheye.undistortPoints(src, K, D, None, None, K, UNDISTORT_CRITERIA)
    else:
        out = cv2.undistortPoints(src, K, D, None, None, K, UNDISTORT_CRITERIA)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def distort_points(points: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixels of the ideal pinhole image -> pixels of the camera's image (the inverse of
    :func:`undistort_points`).

    Args:
        points: (N, 2) pixel coordinates in the ideal image (same ``K``).
        camera: the camera.

    Returns:
        (N, 2) float64 pixel coordinates in the camera's image.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not camera.distorted or len(pts) == 0:
        return pts.copy()
    K, D = _kd(camera)
    xn = (pts - K[:2, 2]) / np.array([camera.fx, camera.fy])
    if camera.model == "fisheye":
        out = cv2.fisheye.distortPoints(xn.reshape(-1, 1, 2), K, D)
    else:
        obj = np.concatenate([xn, np.ones((len(xn), 1))], axis=1)
        out, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, D)
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


@lru_cache(maxsize=16)
def ideal_bounds(camera: Camera, image_wh: tuple[int, int]) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1): the box of the ideal image holding the camera's whole image
    (its undistorted border), px. Points outside it are never seen; distorting them can
    fold back into the image (a polynomial lens model holds only over the calibrated
    field), so callers clip to this box first."""
    w, h = image_wh
    xs, ys = np.linspace(-0.5, w - 0.5, 65), np.linspace(-0.5, h - 0.5, 65)
    border = np.concatenate(
        [
            np.stack([xs, np.full_like(xs, -0.5)], 1),
            np.stack([xs, np.full_like(xs, h - 0.5)], 1),
            np.stack([np.full_like(ys, -0.5), ys], 1),
            np.stack([np.full_like(ys, w - 0.5), ys], 1),
        ]
    )
    ideal = undistort_points(border, camera)
    lo, hi = ideal.min(axis=0), ideal.max(axis=0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def fit_camera(
    camera: Camera, image_wh: tuple[int, int], where: str = "camera"
) -> tuple[Camera, str | None]:
    """The camera for images of ``image_wh`` (width, height) px.

    A camera whose calibration size (``camera.image_wh``) is unknown or equal is returned
    as is. Images that are a uniform scaling ``s`` of the calibration size (within
    :data:`SCALE_TOLERANCE` on both axes) get scaled intrinsics (``f' = s f``, ``c' = s
    (c + 0.5) - 0.5`` for pixel centres at integers; distortion coefficients act on
    normalised coordinates and do not change) and a note saying so.

    Returns:
        (camera, note or None).

    Raises:
        ConfigError: the sizes differ and are not a uniform scaling.
    """
    if camera.image_wh is None or tuple(camera.image_wh) == tuple(image_wh):
        return camera, None
    cw, ch = camera.image_wh
    w, h = image_wh
    sx, sy = w / cw, h / ch
    if abs(sx - sy) > SCALE_TOLERANCE * max(sx, sy):
        raise ConfigError(
            f"{where}: the calibration is for {cw}x{ch} px images but the masks are "
            f"{w}x{h} px, which is not a uniform scaling of it (x {sx:.4g}, y {sy:.4g}); "
            "calibrate at the masks' size or resize the masks"
        )
    s = 0.5 * (sx + sy)
    scaled = Camera(
        fx=camera.fx * sx,
        fy=camera.fy * sy,
        cx=(camera.cx + 0.5) * sx - 0.5,
        cy=(camera.cy + 0.5) * sy - 0.5,
        distortion=camera.distortion,
        model=camera.model,
        image_wh=(int(w), int(h)),
    )
    note = (
        f"{where}: the calibration is for {cw}x{ch} px images and the masks are {w}x{h} px: "
        f"intrinsics scaled by {s:.4g} (fx {camera.fx:.6g} -> {scaled.fx:.6g})"
    )
    return scaled, note


@lru_cache(maxsize=4)
def undistort_maps(camera: Camera, image_wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Maps for :func:`cv2.remap` that turn the camera's image into its ideal pinhole image
    (same size, same ``K``), computed once per (camera, size) and cached.

    Returns:
        (map1, map2) in OpenCV's fixed-point format (``CV_16SC2`` + ``CV_16UC1``).
    """
    K, D = _kd(camera)
    size = (int(image_wh[0]), int(image_wh[1]))
    if camera.model == "fisheye":
        return cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), K, size, cv2.CV_16SC2)
    return cv2.initUndistortRectifyMap(K, D, np.eye(3), K, size, cv2.CV_16SC2)


def undistort_image(image: np.ndarray, camera: Camera | None) -> np.ndarray:
    """The camera's image (H, W[, C]) as its ideal pinhole image (same size and ``K``);
    the image itself (no copy) when the camera is None or does not distort."""
    if camera is None or not camera.distorted:
        return image
    h, w = image.shape[:2]
    m1, m2 = undistort_maps(camera, (w, h))
    return cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def undistort_view(
    image: np.ndarray, camera: Camera | None, camera_wh: tuple[int, int]
) -> np.ndarray:
    """:func:`undistort_image` for a display copy of the camera's image: ``image`` may be
    the ``camera_wh`` (width, height) image scaled (e.g. a viewer's smaller overlay); the
    intrinsics are scaled to it (:func:`fit_camera`), the maps computed once per size. The
    image itself when the camera is None or does not distort."""
    if camera is None or not camera.distorted:
        return image
    h, w = image.shape[:2]
    wh = (int(camera_wh[0]), int(camera_wh[1]))
    cam = camera if camera.image_wh is not None else replace(camera, image_wh=wh)
    scaled, _ = fit_camera(cam, (w, h))
    return undistort_image(image, scaled)
