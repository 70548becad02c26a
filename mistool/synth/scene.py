"""The 3D model of a synthetic scene: a pinhole camera and instruments made of primitives.

Conventions (as everywhere in mistool): camera frame OpenCV (x right, y down, z forward),
millimetres; pixels x right, y down, pixel centres at integer coordinates.

An instrument is, proximal to distal:

- the **shaft**: a cylinder of diameter ``shaft_diameter_mm`` from the trocar point ``T``
  (the fixed fulcrum in the abdominal wall, outside the view) along the unit axis ``a_s``
  to the joint ``J = T + insertion * a_s``;
- the **wrist**: a sphere at ``J`` and a cylinder of length ``wrist_length_mm`` from ``J``
  to the jaw pivot ``W``, bent at ``J`` by ``wrist_deg`` about the shaft frame's x axis;
- the **jaws**: a small sphere at ``W`` (the clevis) and two cylinders of length
  ``jaw_length_mm`` from ``W``, symmetric about the bisector ``b`` (the wrist axis turned by
  ``jaw_yaw_deg`` about the wrist frame's y axis), opened by ``jaw_open_deg`` in total.

Part frames (``R_camera_part``, columns x, y, z; +z along the part's distal axis):

- shaft: ``z = a_s``; ``x0 = normalize(z_cam x a_s)`` (perpendicular to the shaft, in the
  image plane) turned by the roll ``roll_deg`` about ``a_s``; this is "the true roll about
  the shaft" written to ``truth.csv``;
- wrist: the shaft frame turned by ``wrist_deg`` about its x axis;
- clasper (jaws): the wrist frame turned by ``jaw_yaw_deg`` about its y axis; the jaws open
  in its x-z plane.

Ground-truth points: the shaft's distal end is ``J``; the wrist's is ``W``; the clasper's is
the tip, the mid-point of the two jaw tips, ``W + jaw_length * cos(jaw_open / 2) * b``.
Parts are linked: shaft ``T -> J``, wrist ``J -> W``, clasper ``W -> tip`` (axis ``b``);
with labels that have no wrist (EndoVis'15) the head is one clasper part ``J -> tip``
with axis ``normalize(tip - J)`` (:func:`merged_head`).
The clasper length written to ``mistool.toml`` is ``wrist_length + jaw_length`` (joint to
tip, wrist straight and jaws closed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mistool.config import Camera


@dataclass(frozen=True)
class ImageCamera:
    """A pinhole camera with its image size."""

    camera: Camera
    """Intrinsics (px)."""
    width: int = 720
    """Image width (px)."""
    height: int = 576
    """Image height (px)."""

    @staticmethod
    def default(
        width: int = 720,
        height: int = 576,
        focal_px: float = 600.0,
        distortion: tuple[float, ...] = (),
        model: str = "pinhole",
    ) -> ImageCamera:
        """A camera with square pixels and the principal point at the image centre, and
        optionally a distorted lens (OpenCV coefficients, :class:`mistool.config.Camera`)."""
        cam = Camera(
            fx=focal_px,
            fy=focal_px,
            cx=(width - 1) / 2.0,
            cy=(height - 1) / 2.0,
            distortion=tuple(float(d) for d in distortion),
            model=model,
        )
        return ImageCamera(cam, width, height)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project camera-frame points (..., 3) mm to pixels (..., 2) of the ideal pinhole
        image (z must be > 0; :func:`mistool.lens.distort_points` gives the camera's)."""
        p = np.asarray(points, dtype=np.float64)
        c = self.camera
        return np.stack(
            [c.fx * p[..., 0] / p[..., 2] + c.cx, c.fy * p[..., 1] / p[..., 2] + c.cy], axis=-1
        )


@dataclass(frozen=True)
class InstrumentGeometry:
    """Dimensions of one instrument (mm)."""

    shaft_diameter_mm: float = 8.0
    """Shaft diameter: 8 mm robotic (default), 5 mm laparoscopic."""
    wrist_length_mm: float = 6.0
    """Joint ``J`` to jaw pivot ``W``."""
    wrist_diameter_mm: float | None = None
    """Wrist diameter; default 0.85 x the shaft's."""
    jaw_length_mm: float = 10.0
    """Jaw pivot ``W`` to a jaw's tip."""
    jaw_diameter_mm: float | None = None
    """Diameter of one jaw; default 0.3 x the shaft's."""

    @property
    def clasper_length_mm(self) -> float:
        """Joint to tip with the wrist straight and the jaws closed (mm)."""
        return self.wrist_length_mm + self.jaw_length_mm

    @property
    def wrist_radius_mm(self) -> float:
        d = self.wrist_diameter_mm or 0.85 * self.shaft_diameter_mm
        return d / 2.0

    @property
    def jaw_radius_mm(self) -> float:
        d = self.jaw_diameter_mm or 0.3 * self.shaft_diameter_mm
        return d / 2.0

    @staticmethod
    def for_tool(tool: str, shaft_diameter_mm: float | None = None) -> InstrumentGeometry:
        """Geometry of a ``"robotic"`` (8 mm, EndoWrist-like) or ``"laparoscopic"`` (5 mm)
        instrument; ``shaft_diameter_mm`` overrides the diameter, scaling the head."""
        if tool == "robotic":
            base = 8.0
            g = InstrumentGeometry(8.0, wrist_length_mm=6.0, jaw_length_mm=10.0)
        elif tool == "laparoscopic":
            base = 5.0
            g = InstrumentGeometry(5.0, wrist_length_mm=5.0, jaw_length_mm=12.0)
        else:
            raise ValueError(f"tool must be 'robotic' or 'laparoscopic', got {tool!r}")
        if shaft_diameter_mm is None:
            return g
        k = shaft_diameter_mm / base
        return InstrumentGeometry(
            shaft_diameter_mm, g.wrist_length_mm * k, None, g.jaw_length_mm * k, None
        )


@dataclass(frozen=True)
class InstrumentPose:
    """One instrument's configuration in one frame."""

    trocar_mm: np.ndarray
    """Trocar point ``T`` (3,), camera frame, mm."""
    axis: np.ndarray
    """Shaft unit axis (3,), pointing distally (away from the trocar)."""
    insertion_mm: float
    """Distance from the trocar to the joint ``J`` along the axis (mm)."""
    roll_deg: float = 0.0
    """Roll about the shaft (see the module docstring for its zero)."""
    wrist_deg: float = 0.0
    """Wrist bend at ``J`` about the shaft frame's x axis."""
    jaw_yaw_deg: float = 0.0
    """Jaw bisector's turn at ``W`` about the wrist frame's y axis."""
    jaw_open_deg: float = 0.0
    """Total opening angle between the two jaws."""


def _rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def shaft_frame(axis: np.ndarray, roll_deg: float) -> np.ndarray:
    """``R_camera_shaft`` (3, 3): columns x, y, z with z the shaft axis and x the roll
    reference ``normalize(z_cam x axis)`` turned by ``roll_deg`` about z."""
    z = np.asarray(axis, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x0 = np.cross([0.0, 0.0, 1.0], z)
    n = np.linalg.norm(x0)
    if n < 1e-9:  # shaft along the viewing axis: any perpendicular will do
        x0 = np.array([1.0, 0.0, 0.0])
    else:
        x0 = x0 / n
    y0 = np.cross(z, x0)
    return np.column_stack([x0, y0, z]) @ _rot_z(roll_deg)


def matrix_to_wxyz(r: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (4,) wxyz with w >= 0."""
    m = np.asarray(r, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    qa = np.asarray(q)
    qa /= np.linalg.norm(qa)
    return -qa if qa[0] < 0 else qa


@dataclass(frozen=True)
class Cylinder:
    """A solid finite cylinder with flat caps."""

    p0: np.ndarray
    """Centre of the proximal cap (3,), mm."""
    axis: np.ndarray
    """Unit axis (3,) from ``p0`` to the distal cap."""
    length: float
    """Length along the axis (mm)."""
    radius: float
    """Radius (mm)."""


@dataclass(frozen=True)
class Sphere:
    """A solid sphere."""

    centre: np.ndarray
    """Centre (3,), mm."""
    radius: float
    """Radius (mm)."""


Primitive = Cylinder | Sphere


@dataclass(frozen=True)
class PartGeometry:
    """One part's primitives and its ground truth in one frame."""

    part: str
    """"shaft" | "wrist" | "clasper" (the 3D part; the label may merge wrist into clasper)."""
    primitives: tuple[Primitive, ...]
    """What is rendered with this part's label."""
    start_mm: np.ndarray
    """Proximal end (3,): shaft T, wrist J, clasper W."""
    end_mm: np.ndarray
    """Distal end (3,): shaft J, wrist W, clasper the tip."""
    rotation: np.ndarray
    """``R_camera_part`` (3, 3); its z column is the part's unit axis, distal."""


def instrument_parts(pose: InstrumentPose, geom: InstrumentGeometry) -> list[PartGeometry]:
    """Forward kinematics: the instrument's parts (shaft, wrist, clasper) in one frame."""
    t = np.asarray(pose.trocar_mm, dtype=np.float64)
    r_s = shaft_frame(pose.axis, pose.roll_deg)
    a_s = r_s[:, 2]
    j = t + pose.insertion_mm * a_s
    r_w = r_s @ _rot_x(pose.wrist_deg)
    a_w = r_w[:, 2]
    w = j + geom.wrist_length_mm * a_w
    r_j = r_w @ _rot_y(pose.jaw_yaw_deg)
    b, x_j = r_j[:, 2], r_j[:, 0]
    half = math.radians(pose.jaw_open_deg) / 2.0
    jaws = [math.cos(half) * b + sgn * math.sin(half) * x_j for sgn in (1.0, -1.0)]
    tip = w + geom.jaw_length_mm * math.cos(half) * b
    rs, rw, rj = geom.shaft_diameter_mm / 2.0, geom.wrist_radius_mm, geom.jaw_radius_mm
    shaft = PartGeometry("shaft", (Cylinder(t, a_s, float(pose.insertion_mm), rs),), t, j, r_s)
    wrist = PartGeometry(
        "wrist",
        (Sphere(j, rw), Cylinder(j, a_w, geom.wrist_length_mm, rw), Sphere(w, min(rw, 1.6 * rj))),
        j,
        w,
        r_w,
    )
    clasper = PartGeometry(
        "clasper", tuple(Cylinder(w, d, geom.jaw_length_mm, rj) for d in jaws), w, tip, r_j
    )
    return [shaft, wrist, clasper]


def merged_head(wrist: PartGeometry, clasper: PartGeometry) -> PartGeometry:
    """The instrument's head as one part (labels without a wrist, e.g. EndoVis'15, paint the
    wrist as clasper): from the joint ``J`` to the tip, axis ``normalize(tip - J)``, the x
    axis the jaw frame's x made orthogonal to it."""
    start, end = wrist.start_mm, clasper.end_mm
    z = (end - start) / np.linalg.norm(end - start)
    x = clasper.rotation[:, 0] - (clasper.rotation[:, 0] @ z) * z
    x /= np.linalg.norm(x)
    return PartGeometry(
        "clasper",
        wrist.primitives + clasper.primitives,
        start,
        end,
        np.column_stack([x, np.cross(z, x), z]),
    )
