"""The instrument meshes (mistool.viewer.meshes): built once with trimesh, posed from the
replay's cylinders so that the drawn instrument ends where the estimate says."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from mistool.viewer.meshes import JAW_OPEN_DEG, WRIST_FRACTION, part_poses, unit_meshes


def _quat(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])


def _place(mesh, pose) -> np.ndarray:
    """World vertices of a unit mesh at a pose (scale, then rotate, then translate)."""
    R = trimesh.transformations.quaternion_matrix(pose.wxyz)[:3, :3]
    return (mesh.vertices * np.array(pose.scale)) @ R.T + pose.position


def test_unit_meshes_are_closed_solids_of_unit_size() -> None:
    meshes = unit_meshes()
    for name, m in meshes.items():
        tm = trimesh.Trimesh(m.vertices, m.faces)
        assert tm.is_watertight and tm.volume > 0, name
    cyl = meshes["cylinder"].vertices
    assert np.allclose([cyl[:, 2].min(), cyl[:, 2].max()], [-0.5, 0.5], atol=1e-6)
    assert np.isclose(np.hypot(cyl[:, 0], cyl[:, 1]).max(), 1.0, atol=1e-6)
    jaw = meshes["jaw"].vertices
    assert np.allclose([jaw[:, 2].min(), jaw[:, 2].max()], [0.0, 1.0])
    assert unit_meshes() is meshes  # built once


CASES = [  # (centre, axis, rotation angle about it) of a part's cylinder
    (np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 1.0]), 0.0),
    (np.array([-4.0, 0.5, 2.0]), np.array([1.0, -2.0, 0.5]), 1.1),
    (np.array([0.0, 9.0, 1.0]), np.array([-0.3, 0.2, -1.0]), -2.0),
]


def _wxyz_to(axis: np.ndarray, roll: float) -> np.ndarray:
    """A quaternion taking +z to ``axis`` (then a roll about it)."""
    a = axis / np.linalg.norm(axis)
    z = np.array([0.0, 0.0, 1.0])
    c = np.cross(z, a)
    s = np.linalg.norm(c)
    q = _quat(c, math.atan2(s, a @ z)) if s > 1e-9 else np.array([1.0, 0, 0, 0])
    r = _quat(z, roll)
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


@pytest.mark.parametrize(("centre", "axis", "roll"), CASES)
def test_shaft_spans_its_cylinder_with_a_round_end(centre, axis, roll) -> None:
    a = axis / np.linalg.norm(axis)
    poses = part_poses("shaft", centre, _wxyz_to(a, roll), 10.0, 0.4, with_wrist=False)
    body = _place(unit_meshes()["cylinder"], poses[""])
    cap = _place(unit_meshes()["sphere"], poses["_end"])
    t = (np.concatenate([body, cap]) - centre) @ a
    assert np.isclose(t.min(), -5.0) and np.isclose(t.max(), 5.0)  # ends at the joint
    assert np.isclose(((body - centre) @ a).max(), 5.0 - 0.4)  # the round end's base
    assert np.allclose(cap.mean(axis=0), centre + (5.0 - 0.4) * a, atol=1e-6)
    assert np.isclose(np.linalg.norm(cap - (centre + 4.6 * a), axis=1).max(), 0.4)


@pytest.mark.parametrize(("centre", "axis", "roll"), CASES)
@pytest.mark.parametrize("with_wrist", [True, False])
def test_jaws_open_symmetrically_and_their_tips_meet_the_tip(
    centre, axis, roll, with_wrist: bool
) -> None:
    a = axis / np.linalg.norm(axis)
    length, radius = 3.0, 0.3
    poses = part_poses("clasper", centre, _wxyz_to(a, roll), length, radius, with_wrist)
    assert ("" in poses) is with_wrist
    start, end = centre - 0.5 * length * a, centre + 0.5 * length * a
    pivot = start + (WRIST_FRACTION * length * a if with_wrist else 0.0)
    tips, dirs = [], []
    for k in (0, 1):
        p = poses[f"_jaw{k}"]
        R = trimesh.transformations.quaternion_matrix(p.wxyz)[:3, :3]
        assert np.allclose(p.position, pivot)
        tips.append(p.position + p.scale[2] * R[:, 2])  # the jaw's axis, pivot to tip
        dirs.append(R[:, 2])
    assert np.allclose(0.5 * (tips[0] + tips[1]), end, atol=1e-9)  # the tip's definition
    opening = math.degrees(math.acos(np.clip(dirs[0] @ dirs[1], -1, 1)))
    assert math.isclose(opening, JAW_OPEN_DEG, abs_tol=1e-6)
    assert math.isclose(float(dirs[0] @ a), float(dirs[1] @ a))  # symmetric about the axis


def test_meshes_are_closed_solids_and_serve_starts_without_trimesh() -> None:
    """The unit shapes are closed, outward-facing solids; the viewer starts without
    importing trimesh (and scipy with it: a third of a second before the URL), which
    builds them when the first instrument is drawn."""
    import subprocess
    import sys

    for name, mesh in unit_meshes().items():
        solid = trimesh.Trimesh(mesh.vertices, mesh.faces)
        assert solid.is_watertight and solid.volume > 0, name
    cylinder = trimesh.Trimesh(unit_meshes()["cylinder"].vertices, unit_meshes()["cylinder"].faces)
    assert 0.95 * np.pi < cylinder.volume <= np.pi  # radius 1, height 1
    code = (
        "import sys, mistool.cli.serve; from mistool.viewer import ReplayViewer, load_sequence; "
        "print(sorted(m for m in ('trimesh', 'scipy') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_a_viewer_starting_without_instruments_builds_the_meshes_before_they_come() -> None:
    """``mistool.Viewer`` (and ``mistool serve`` tracking in the background) start with
    no instrument: trimesh's import (0.3-0.6 s) runs in a background thread while the
    browser loads the page, instead of delaying the first instrument's picture. In a new
    interpreter, so that trimesh is not imported already."""
    import subprocess
    import sys

    code = (
        "import sys, threading, mistool\n"
        "from mistool.viewer.meshes import unit_meshes\n"
        "with mistool.Viewer(port=0) as v:\n"
        "    [t.join(60) for t in threading.enumerate() if t.name == 'mistool-meshes']\n"
        "    print('trimesh' in sys.modules, unit_meshes.cache_info().currsize)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-2:] == ["True", "1"], out.stdout
