"""The 3D scene: each instrument's parts as meshes (:mod:`mistool.viewer.meshes`), the
endoscope frustum with the current mask on its image plane, a ground grid, and trails of
each tip and joint.

World frame, units and the two display modes are described in :mod:`mistool.viewer.replay`.
Node names: ``/instruments/<instrument>/<part>`` (a part's body; its end cap and jaws
beside it, see :mod:`mistool.viewer.meshes`),
``/endoscope`` (frustum), ``/grid``, ``/trails/<instrument>/tip`` and ``.../joint``.
"""

from __future__ import annotations

import math
import re

import numpy as np
import viser

from mistool.viewer.meshes import PartNodes
from mistool.viewer.replay import R_WORLD_CAMERA, Replay, scene_extent

#: Camera presets offered in the GUI.
PRESETS = ("Endoscope", "Side", "Top", "Reset")


def _wxyz_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (wxyz) of a rotation matrix."""
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    x = math.copysign(
        math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2.0, r[2, 1] - r[1, 2]
    )
    y = math.copysign(
        math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2.0, r[0, 2] - r[2, 0]
    )
    z = math.copysign(
        math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2.0, r[1, 0] - r[0, 1]
    )
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def node_name(text: str) -> str:
    """A scene-tree-safe name for an instrument (no slashes or spaces)."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text) or "_"


class SceneView:
    """Owns the scene nodes and updates them for one frame at a time."""

    def __init__(
        self,
        server: viser.ViserServer,
        replay: Replay,
        mode: str,
        overlay: np.ndarray | None = None,
        trail_frames: int = 25,
        jpeg_quality: int = 80,
    ) -> None:
        """
        Args:
            server: the viser server (the scene is shared by every client).
            replay: the precomputed replay.
            mode: ``"metric"`` or ``"paper"`` (must be in ``replay.modes``).
            overlay: first overlay image (RGB) for the frustum, or None.
            trail_frames: initial trail length N (frames; 0 = off).
            jpeg_quality: JPEG quality (1-100) of the overlay images on the frustum.
        """
        self.server = server
        self.replay = replay
        self.mode = mode
        self.trail_frames = int(trail_frames)
        self.frame = 0
        self.show_frustum_image = True
        scene = server.scene
        scene.set_up_direction("+z")
        # Without the environment map only viser's directional lights remain; a sky/ground
        # hemisphere light keeps the cylinders' undersides readable.
        scene.add_light_hemisphere(
            "/lights/hemisphere",
            sky_color=(255, 255, 255),
            ground_color=(110, 110, 120),
            intensity=1.6,
        )
        self.parts: dict[tuple[int, int], PartNodes] = {}
        fov, aspect = replay.fov_aspect()
        self.frustum = scene.add_camera_frustum(
            "/endoscope",
            fov=fov,
            aspect=aspect,
            scale=1.0,
            color=(90, 90, 90),
            thickness=0.02,
            image=overlay,
            format="jpeg",
            jpeg_quality=jpeg_quality,
            wxyz=_wxyz_from_matrix(R_WORLD_CAMERA),
            position=(0.0, 0.0, 0.0),
            cast_shadow=False,
            receive_shadow=False,
        )
        self._canonical_depth = self.frustum.compute_canonical_frustum_size()[2]
        self.grid: viser.GridHandle | None = None
        self.trails: dict[tuple[int, str], viser.LineSegmentsHandle] = {}
        self.add_instruments()
        self.set_mode(mode)

    def add_instruments(self) -> None:
        """Create the nodes (cylinders, trails) of instruments the replay has gained."""
        scene, replay = self.server.scene, self.replay
        known = {i for i, _ in self.parts}
        for i, inst in enumerate(replay.instruments):
            if i in known:
                continue
            for p, part in enumerate(replay.parts):
                self.parts[i, p] = PartNodes(
                    scene,
                    f"/instruments/{node_name(inst)}/{part}",
                    part,
                    replay.part_colour(i, part),
                    replay.part_colour(i, "wrist"),
                    with_wrist="wrist" not in replay.parts,
                )
            for kind, part in (("tip", replay.parts[-1]), ("joint", "shaft")):
                colour = np.array(replay.part_colour(i, part), dtype=np.uint8)
                self.trails[i, kind] = scene.add_line_segments(
                    f"/trails/{node_name(inst)}/{kind}",
                    points=np.zeros((1, 2, 3)),
                    colors=colour,
                    thickness=3.0 if kind == "tip" else 2.0,
                    thickness_units="screen",
                    visible=False,
                )

    # -- modes and static parts ---------------------------------------------------------
    def set_mode(self, mode: str) -> None:
        """Switch display mode (metric or paper): regrid, rescale the frustum, redraw."""
        if mode not in self.replay.modes:
            raise ValueError(
                f"mode {mode!r} not available; choose from {', '.join(self.replay.modes)}"
            )
        self.mode = mode
        geometry = self.replay.modes[mode]
        self.frustum.scale = geometry.image_distance / self._canonical_depth
        lo, hi = scene_extent(self.replay, mode)
        size = float(max(hi[0] - lo[0], hi[1] - lo[1], 1.0)) * 1.6
        size = float(math.ceil(size / 2.0) * 2.0)
        centre = 0.5 * (lo + hi)
        floor = float(lo[2] - 0.15 * max(hi[2] - lo[2], 1.0))
        if self.grid is not None:
            self.grid.remove()
        self.grid = self.server.scene.add_grid(
            "/grid",
            width=size,
            height=size,
            cell_size=0.5,
            section_size=2.0,
            position=(float(centre[0]), float(centre[1]), floor),
            shadow_opacity=0.0,
            visible=self.show_frustum_image,
        )
        self.show(self.frame)

    def set_frustum_image_visible(self, visible: bool) -> None:
        """Show or hide the frustum (with its image) and the grid: hidden while a browser
        looks through the endoscope (they would cover the view and the mask behind)."""
        self.show_frustum_image = visible
        self.frustum.visible = visible
        if self.grid is not None:
            self.grid.visible = visible

    def set_overlay(self, rgb: np.ndarray) -> None:
        """Put an overlay image (RGB uint8) on the frustum's image plane."""
        self.frustum.image = rgb

    # -- per frame ----------------------------------------------------------------------
    def show(self, frame: int) -> None:
        """Pose every cylinder and trail for ``frame`` (call inside ``server.atomic()``)."""
        self.frame = frame
        g = self.replay.modes[self.mode]
        for (i, p), nodes in self.parts.items():
            if g.visible[frame, i, p]:
                r, length = float(g.radius[frame, i, p]), float(g.length[frame, i, p])
                nodes.show(g.centre[frame, i, p], g.wxyz[frame, i, p], length, r)
            else:
                nodes.hide()
        self._show_trails(frame)

    def set_trail_frames(self, n: int) -> None:
        """Trail length N in frames (0 = off)."""
        self.trail_frames = max(0, int(n))
        self._show_trails(self.frame)

    def _show_trails(self, frame: int) -> None:
        g = self.replay.modes[self.mode]
        n = self.trail_frames
        lo = max(0, frame - n + 1)
        for (i, kind), handle in self.trails.items():
            pts = (g.tip if kind == "tip" else g.joint)[lo : frame + 1, i]
            if n < 2 or len(pts) < 2:
                if handle.visible:
                    handle.visible = False
                continue
            ok = np.isfinite(pts).all(axis=1)
            seg_ok = ok[:-1] & ok[1:]
            if not seg_ok.any():
                if handle.visible:
                    handle.visible = False
                continue
            segs = np.stack([pts[:-1][seg_ok], pts[1:][seg_ok]], axis=1).astype(np.float32)
            handle.points = segs
            if not handle.visible:
                handle.visible = True

    # -- cameras ------------------------------------------------------------------------
    def camera_pose(self, preset: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """(position, look_at, up, vertical fov rad) of a camera preset, world frame."""
        fov, _ = self.replay.fov_aspect()
        lo, hi = scene_extent(self.replay, self.mode)
        target = 0.5 * (lo + hi)
        radius = max(float(np.linalg.norm(hi - lo)), 1.0)
        up = np.array([0.0, 0.0, 1.0])
        if preset == "Endoscope":
            return np.zeros(3), np.array([0.0, 1.0, 0.0]), up, fov
        if preset == "Side":
            return target + np.array([1.6 * radius, 0.0, 0.0]), target, up, math.radians(50)
        if preset == "Top":
            # Looking down; a small offset along -y keeps the up vector well defined.
            return (
                target + np.array([0.0, -0.01 * radius, 1.8 * radius]),
                target,
                np.array([0.0, 1.0, 0.0]),
                math.radians(50),
            )
        if preset == "Reset":
            return (
                target + np.array([0.75 * radius, -0.85 * radius, 0.6 * radius]),
                target,
                up,
                math.radians(50),
            )
        raise ValueError(f"unknown camera preset {preset!r}; choose from {', '.join(PRESETS)}")

    def apply_camera(
        self, client: viser.ClientHandle, preset: str, fov: float | None = None
    ) -> None:
        """Move one client's camera to a preset (cameras are per browser); ``fov``
        (vertical, rad) overrides the preset's."""
        position, look_at, up, preset_fov = self.camera_pose(preset)
        fov = preset_fov if fov is None else fov
        with client.atomic():
            client.camera.up_direction = tuple(up)
            client.camera.position = tuple(position)
            client.camera.look_at = tuple(look_at)
            client.camera.fov = fov
