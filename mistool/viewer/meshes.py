"""The instruments as they look: meshes built once, posed per frame.

Each part the replay places as a cylinder (centre, wxyz taking +z to the part's axis,
length, radius; :class:`mistool.viewer.replay.ModeGeometry`) is drawn as:

- **shaft**: a cylinder with a rounded distal end (a half sphere of the shaft's radius,
  within the shaft's length: the drawn shaft still ends at the joint J);
- **wrist** (labels with a wrist part): its knuckle (a sphere at J, as ``mistool synth``
  models it) and a cylinder;
- **clasper**: the knuckle and the wrist segment, when the labels have no wrist part
  (EndoVis'15: the clasper label covers wrist and jaws), then two tapered jaws hinged at
  the jaw pivot,
  opened symmetrically by :data:`JAW_OPEN_DEG` (mistool's pose measures no jaw angle; the
  opening plane is the part frame's x-z plane: roll about the axis is not observable from
  masks) so that the jaw tips' mid-point is the part's distal end (the tip).

The meshes are unit shapes in the part's frame (+z along the axis), built once
(:func:`unit_meshes`), and every frame only sets each node's position, orientation and
scale, as the plain cylinders were. Node names: ``/instruments/<inst>/<part>`` (the body),
``.../<part>_end`` (shaft end cap, wrist knuckle), ``.../<part>_jaw0`` and ``_jaw1``.
"""

from __future__ import annotations

import contextlib
import math
import threading
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import viser

#: Fixed jaw opening (degrees, between the two jaws) drawn for every clasper.
JAW_OPEN_DEG = 30.0
#: Fraction of a clasper's length that is its wrist segment when the labels have no
#: wrist part (the rest is the jaws, pivot to tip).
WRIST_FRACTION = 0.35
#: A jaw's base half-width and half-thickness, and its tip half-width, as fractions of
#: the clasper's radius.
JAW_HALF_WIDTH = 0.55
JAW_HALF_THICKNESS = 0.35
JAW_TIP_HALF_WIDTH = 0.25
#: Segments around the round meshes.
SECTIONS = 24


@dataclass(frozen=True)
class UnitMesh:
    """Vertices (V, 3) float32 and faces (T, 3) uint32 of a unit shape."""

    vertices: np.ndarray
    faces: np.ndarray


def _unit(mesh: Any) -> UnitMesh:
    return UnitMesh(
        np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.uint32)
    )


@lru_cache(maxsize=1)
def unit_meshes() -> dict[str, UnitMesh]:
    """The unit shapes, built once, with trimesh (imported here, when the first
    instrument is drawn, not when the viewer starts: with scipy it costs a third of a
    second, which would delay ``mistool serve``'s URL).

    - ``"cylinder"``: radius 1, z in [-0.5, 0.5] (scaled per frame by (r, r, length));
    - ``"sphere"``: radius 1, centred (scaled by r: the shaft's round end, the knuckles);
    - ``"jaw"``: one jaw, z in [0, 1] from the pivot to its tip, x across the opening
      (scaled by (r, r, jaw length)).
    """
    import trimesh

    cylinder = trimesh.creation.cylinder(radius=1.0, height=1.0, sections=SECTIONS)
    sphere = trimesh.creation.uv_sphere(radius=1.0, count=(SECTIONS // 2, SECTIONS))
    w, t, tip = JAW_HALF_WIDTH, JAW_HALF_THICKNESS, JAW_TIP_HALF_WIDTH
    corners = [
        (x, y, z)
        for z, hx, hy in ((0.0, w, t), (1.0, tip, 0.6 * t))
        for x in (-hx, hx)
        for y in (-hy, hy)
    ]
    jaw = trimesh.convex.convex_hull(np.array(corners))
    return {"cylinder": _unit(cylinder), "sphere": _unit(sphere), "jaw": _unit(jaw)}


def warm_up() -> threading.Thread:
    """Build :func:`unit_meshes` in a background thread and return it: a viewer that
    starts with no instrument (tracking in the background, ``mistool.Viewer``) has
    trimesh imported while the browser loads the page, not when the first instrument
    arrives (its import, with scipy's, is 0.3-0.6 s of the time to the first picture).
    An error is left for the first instrument's own call to raise."""

    def build() -> None:
        with contextlib.suppress(Exception):
            unit_meshes()

    thread = threading.Thread(target=build, name="mistool-meshes", daemon=True)
    thread.start()
    return thread


def _quat_mul(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions (4,) x (4,)."""
    w0, x0, y0, z0 = q
    w1, x1, y1, z1 = r
    return np.array(
        [
            w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1,
            w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
            w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1,
            w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1,
        ]
    )


def _z_axis(wxyz: np.ndarray) -> np.ndarray:
    """The rotated +z axis (3,) of a unit wxyz quaternion."""
    w, x, y, z = wxyz
    return np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])


@dataclass(frozen=True)
class PartPose:
    """Where one node goes: position (3,), wxyz (4,), scale (3,)."""

    position: np.ndarray
    wxyz: np.ndarray
    scale: tuple[float, float, float]


def part_poses(
    part: str,
    centre: np.ndarray,
    wxyz: np.ndarray,
    length: float,
    radius: float,
    with_wrist: bool,
    jaw_open_deg: float = JAW_OPEN_DEG,
) -> dict[str, PartPose]:
    """Poses of a part's nodes from its cylinder (world frame and units).

    Args:
        part: ``"shaft"``, ``"wrist"`` or ``"clasper"``.
        centre: (3,) the cylinder's centre; wxyz: (4,) +z to the part's (distal) axis.
        length, radius: the cylinder's length and radius.
        with_wrist: for a clasper, draw the wrist segment too (no wrist part in the labels).
        jaw_open_deg: angle between the two jaws (degrees).

    Returns:
        Node suffix (``""`` the body, ``"_end"``, ``"_jaw0"``, ``"_jaw1"``) -> pose; a
        clasper's body is its wrist segment (absent without ``with_wrist``).
    """
    axis = _z_axis(wxyz)
    start = centre - 0.5 * length * axis
    end = centre + 0.5 * length * axis
    if part == "shaft":  # rounded within its length: the drawn shaft still ends at J
        cap = max(length - radius, 0.0)
        return {
            "": PartPose(start + 0.5 * cap * axis, wxyz, (radius, radius, cap)),
            "_end": PartPose(start + cap * axis, wxyz, (radius, radius, radius)),
        }
    if part != "clasper":  # the wrist: its knuckle (a sphere at J), then a cylinder
        return {
            "": PartPose(centre, wxyz, (radius, radius, length)),
            "_end": PartPose(start, wxyz, (radius, radius, radius)),
        }
    out: dict[str, PartPose] = {}
    pivot = start
    if with_wrist:
        w_len = WRIST_FRACTION * length
        pivot = start + w_len * axis
        out[""] = PartPose(start + 0.5 * w_len * axis, wxyz, (radius, radius, w_len))
        out["_end"] = PartPose(start, wxyz, (radius, radius, radius))
    reach = float(np.linalg.norm(end - pivot))
    half = math.radians(0.5 * jaw_open_deg)
    jaw_len = reach / max(math.cos(half), 1e-6)  # the jaw tips' mid-point is the tip
    for k, sign in enumerate((1.0, -1.0)):
        turn = np.array([math.cos(0.5 * sign * half), 0.0, math.sin(0.5 * sign * half), 0.0])
        out[f"_jaw{k}"] = PartPose(pivot, _quat_mul(wxyz, turn), (radius, radius, jaw_len))
    return out


class PartNodes:
    """The scene nodes that draw one part of one instrument."""

    def __init__(
        self,
        scene: viser.SceneApi,
        name: str,
        part: str,
        colour: tuple[int, int, int],
        wrist_colour: tuple[int, int, int],
        with_wrist: bool,
    ) -> None:
        """
        Args:
            scene: where to add the nodes.
            name: the body's node name (``/instruments/<inst>/<part>``).
            part: ``"shaft"``, ``"wrist"`` or ``"clasper"``.
            colour: the part's colour; wrist_colour: its wrist segment's (claspers).
            with_wrist: a clasper also draws its wrist segment.
        """
        self.part = part
        self.with_wrist = with_wrist
        meshes = unit_meshes()
        kinds = {"": "cylinder", "_end": "sphere"}
        if part == "clasper":
            kinds = ({"": "cylinder", "_end": "sphere"} if with_wrist else {}) | {
                "_jaw0": "jaw",
                "_jaw1": "jaw",
            }
        self.nodes: dict[str, viser.MeshHandle] = {}
        for suffix, kind in kinds.items():
            mesh = meshes[kind]
            wrist_piece = part == "clasper" and suffix in ("", "_end")
            self.nodes[suffix] = scene.add_mesh_simple(
                name + suffix,
                mesh.vertices,
                mesh.faces,
                color=wrist_colour if wrist_piece else colour,
                flat_shading=kind == "jaw",
                cast_shadow=False,
                receive_shadow=False,
                visible=False,
            )
        self.visible = False

    def show(self, centre: np.ndarray, wxyz: np.ndarray, length: float, radius: float) -> None:
        """Pose and show every node of the part (see :func:`part_poses`)."""
        poses = part_poses(self.part, centre, wxyz, length, radius, self.with_wrist)
        for suffix, node in self.nodes.items():
            pose = poses[suffix]
            node.position = pose.position
            node.wxyz = pose.wxyz
            node.scale = pose.scale
            if not node.visible:
                node.visible = True
        self.visible = True

    def hide(self) -> None:
        """Hide every node of the part."""
        if self.visible:
            for node in self.nodes.values():
                node.visible = False
            self.visible = False
