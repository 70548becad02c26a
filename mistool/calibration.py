"""Camera calibration files: the files people have, read into a :class:`~mistool.config.Camera`.

Two families, both read with OpenCV's own parser (:class:`cv2.FileStorage`, which reads
YAML, XML and JSON), so there is no YAML dependency and no hand-written parser:

- **OpenCV FileStorage** (YAML ``%YAML:1.0``, XML ``<opencv_storage>``, JSON), as written by
  OpenCV's calibration sample and tools: ``camera_matrix`` (3x3 ``!!opencv-matrix``),
  ``distortion_coefficients`` (1xN or Nx1: 4, 5, 8, 12 or 14 values), ``image_width``,
  ``image_height``; also the spellings ``cameraMatrix``/``K`` and
  ``distCoeffs``/``dist_coeffs``/``D``. An optional ``distortion_model`` (or ``model``)
  string says ``fisheye``.
- **ROS** ``camera_info`` YAML (``camera_calibration``'s output, ``sensor_msgs/CameraInfo``):
  ``image_width``, ``image_height``, ``camera_matrix: {rows, cols, data}``,
  ``distortion_model`` (``plumb_bob``/``rational_polynomial``: OpenCV's pinhole model;
  ``equidistant``/``fisheye``: OpenCV's fisheye model) and ``distortion_coefficients:
  {rows, cols, data}``. (``rectification_matrix`` and ``projection_matrix`` are for
  stereo rectification and are not used: mistool undistorts with ``camera_matrix``.)

Both give the same :class:`Camera` as the equivalent ``[camera]`` table, plus the image size
the calibration is for (``image_wh``), which :func:`mistool.lens.fit_camera` checks against
the masks.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2

from mistool.config import Camera, Config, make_camera
from mistool.errors import ConfigError

__all__ = ["read_calibration", "with_calibration"]

_MATRIX_KEYS = ("camera_matrix", "cameraMatrix", "K")
_DIST_KEYS = ("distortion_coefficients", "distCoeffs", "dist_coeffs", "D")
_MODEL_KEYS = ("distortion_model", "model")
#: Distortion model names (ROS ``distortion_model``, OpenCV tools) -> mistool's model.
MODEL_NAMES: dict[str, str] = {
    "plumb_bob": "pinhole",
    "rational_polynomial": "pinhole",
    "pinhole": "pinhole",
    "radtan": "pinhole",
    "equidistant": "fisheye",
    "fisheye": "fisheye",
}


def _first(fs: Any, keys: tuple[str, ...]) -> tuple[str, Any] | None:
    for key in keys:
        node = fs.getNode(key)
        if not node.empty() and not node.isNone():
            return key, node
    return None


def _numbers(node: Any, key: str, where: str) -> list[float]:
    """The numbers of a matrix node: an ``!!opencv-matrix`` / ROS ``{rows, cols, data}`` map
    or a plain sequence."""
    if node.isMap():
        data = node.getNode("data")
        if data.empty() or data.isNone():
            raise ConfigError(f"{where}: {key} has no data")
        node = data
    if node.isSeq():
        items = [node.at(i) for i in range(node.size())]
    elif node.isReal() or node.isInt():
        items = [node]
    else:
        raise ConfigError(f"{where}: {key} must be a matrix or a list of numbers")
    values = []
    for item in items:
        if not (item.isReal() or item.isInt()):
            raise ConfigError(f"{where}: {key} holds a value that is not a number")
        v = float(item.real())
        if not math.isfinite(v):
            raise ConfigError(f"{where}: {key} holds a non-finite value {v}")
        values.append(v)
    return values


def _size(fs: Any, where: str) -> tuple[int, int] | None:
    w, h = fs.getNode("image_width"), fs.getNode("image_height")
    if w.empty() and h.empty():
        return None
    if w.empty() or h.empty() or not (w.isInt() or w.isReal()) or not (h.isInt() or h.isReal()):
        raise ConfigError(f"{where}: image_width and image_height must both be numbers")
    wh = (int(w.real()), int(h.real()))
    if wh[0] < 1 or wh[1] < 1 or wh != (w.real(), h.real()):
        raise ConfigError(f"{where}: image size {w.real()}x{h.real()} is not a positive integer")
    return wh


def _model(fs: Any, where: str) -> str:
    found = _first(fs, _MODEL_KEYS)
    if found is None:
        return "pinhole"
    key, node = found
    name = node.string() if node.isString() else ""
    if name.lower() not in MODEL_NAMES:
        raise ConfigError(
            f"{where}: {key} = {name!r} is not a known lens model; known: {', '.join(MODEL_NAMES)}"
        )
    return MODEL_NAMES[name.lower()]


def read_calibration(path: str | Path) -> Camera:
    """Read a camera calibration file (OpenCV FileStorage YAML/XML/JSON or ROS camera_info).

    Args:
        path: the file.

    Returns:
        The camera, with ``image_wh`` set when the file gives the image size.

    Raises:
        ConfigError: a missing or unreadable file, or one without a valid camera matrix or
            with distortion coefficients of an unsupported length.
    """
    p = Path(path)
    where = str(p)
    if not p.is_file():
        raise ConfigError(f"{where}: no such calibration file")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
        opened = fs.isOpened()
    except (cv2.error, SystemError) as exc:
        cause = exc.__cause__ if isinstance(exc, SystemError) and exc.__cause__ else exc
        text = str(cause).strip().splitlines()[-1] if str(cause).strip() else type(exc).__name__
        first = text.split("error: ")[-1].split(") ", 1)[-1].strip()
        raise ConfigError(
            f"{where}: cannot parse as an OpenCV YAML/XML/JSON or ROS camera_info file ({first})"
        ) from None
    if not opened:
        raise ConfigError(f"{where}: cannot open as an OpenCV YAML/XML/JSON calibration file")
    try:
        return _camera(fs, where)
    finally:
        fs.release()


def _camera(fs: Any, where: str) -> Camera:
    found = _first(fs, _MATRIX_KEYS)
    if found is None:
        raise ConfigError(
            f"{where}: no camera matrix; expected one of {', '.join(_MATRIX_KEYS)} "
            "(OpenCV calibration or ROS camera_info)"
        )
    key, node = found
    k = _numbers(node, key, where)
    if len(k) != 9:
        raise ConfigError(f"{where}: {key} must be 3x3 (9 values), got {len(k)}")
    fx, skew, cx, zero1, fy, cy, zero2, zero3, one = k
    if zero1 != 0 or zero2 != 0 or zero3 != 0 or one != 1:
        raise ConfigError(
            f"{where}: {key} is not an intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"
        )
    if abs(skew) > 1e-9 * max(abs(fx), 1.0):
        raise ConfigError(f"{where}: {key} has a skew term ({skew}); mistool needs skew = 0")
    if not (fx > 0 and fy > 0):
        raise ConfigError(f"{where}: {key} focal lengths must be > 0, got fx={fx}, fy={fy}")
    dist_found = _first(fs, _DIST_KEYS)
    dist = _numbers(dist_found[1], dist_found[0], where) if dist_found is not None else []
    return make_camera([fx, fy, cx, cy], dist, _model(fs, where), where, _size(fs, where))


def with_calibration(config: Config, path: str | Path | None) -> Config:
    """``config`` with its camera read from a calibration file (``--calibration FILE``
    overrides ``[camera]`` and ``calibration =`` of ``mistool.toml``); unchanged for None."""
    if path is None:
        return config
    return replace(config, camera=read_calibration(path), calibration=Path(path))
