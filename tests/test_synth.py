"""mistool.synth: exact projection, kinematics, motion, corruptions, the written folder."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.config import load_config
from mistool.errors import ConfigError, InputPathError
from mistool.evaluation import with_mask_areas
from mistool.export import read_csv
from mistool.geometry import mask_box
from mistool.synth import (
    Corruptions,
    ImageCamera,
    InstrumentGeometry,
    InstrumentPose,
    MotionOptions,
    RayCaster,
    SceneOptions,
    synthesize,
)
from mistool.synth.motion import DEPTH_RANGE_MM, generate_motion
from mistool.synth.render import PART_CODES
from mistool.synth.scene import Cylinder, PartGeometry, Sphere, instrument_parts, matrix_to_wxyz

CAM = ImageCamera.default()


def _render_prims(prims: list, cam: ImageCamera = CAM):
    parts = [[PartGeometry("shaft", (p,), np.zeros(3), np.zeros(3), np.eye(3))] for p in prims]
    return RayCaster(cam).render(parts)


def _limb_lines(p0: np.ndarray, a: np.ndarray, r: float) -> list[np.ndarray]:
    """The cylinder's two limb lines, analytically.

    A plane through the camera centre tangent to the infinite cylinder (axis through
    ``p0`` along unit ``a``, radius ``r``) is parallel to the axis, so its unit normal
    ``m`` has ``m . a = 0`` and ``m . p0 = r``: ``m = cos(phi) e1 + sin(phi) e2`` with
    ``e1`` the unit perpendicular from the camera centre to the axis, ``e2 = a x e1`` and
    ``cos(phi) = r / |p0_perp|``. The image of the plane is the line ``m . d = 0`` with
    ``d = ((u - cx) / fx, (v - cy) / fy, 1)``. Returned as (A, B, C), ``A u + B v + C``
    the signed distance in px, positive on the cylinder's side.
    """
    perp = p0 - (p0 @ a) * a
    rho = np.linalg.norm(perp)
    e1 = perp / rho
    e2 = np.cross(a, e1)
    c = CAM.camera
    lines = []
    for sgn in (1.0, -1.0):
        cos_phi = r / rho
        m = cos_phi * e1 + sgn * math.sqrt(1 - cos_phi**2) * e2
        line = np.array([m[0] / c.fx, m[1] / c.fy, m[2] - m[0] * c.cx / c.fx - m[1] * c.cy / c.fy])
        lines.append(line / math.hypot(line[0], line[1]))  # m . p0 = r > 0: positive side
    return lines


@pytest.mark.parametrize(
    "p0,a",
    [
        ((-60.0, -30.0, 70.0), (1.0, 0.45, 0.35)),
        ((40.0, 50.0, 120.0), (-0.7, -0.6, -0.2)),
        ((-5.0, -120.0, 90.0), (0.1, 1.0, 0.05)),  # near-vertical in the image
    ],
)
def test_cylinder_silhouette_is_bounded_by_its_analytic_limb_lines(p0, a):
    p0 = np.array(p0)
    a = np.array(a) / np.linalg.norm(a)
    r, length = 4.0, 200.0
    buf = _render_prims([Cylinder(p0, a, length, r)])
    mask = buf.instance > 0
    lines = _limb_lines(p0, a, r)
    # the verdict near the caps involves the caps; look at the middle of the shaft only
    h, w = mask.shape
    vv, uu = np.mgrid[0:h, 0:w]
    c = CAM.camera
    d = np.stack([(uu - c.cx) / c.fx, (vv - c.cy) / c.fy, np.ones_like(uu, float)], -1)
    # axial coordinate of the closest point of each ray to the axis
    w0 = -p0
    da, dw, dd = d @ a, d @ w0, np.sum(d * d, -1)
    t = (da * (w0 @ a) - dw) / (dd - da**2)
    s = t * da + w0 @ a
    middle = (s > 20) & (s < length - 20) & (t > 5)
    assert middle.sum() > 2000
    side = np.stack([ln[0] * uu + ln[1] * vv + ln[2] for ln in lines])  # signed px
    inside = (side > 0.01).all(0)  # exact up to float32 rounding (0.01 px)
    outside = (side < -0.01).any(0)
    assert np.array_equal(mask[middle & inside], np.ones((middle & inside).sum(), bool))
    assert not mask[middle & outside].any()
    # sub-pixel: edge points (mid-way between the last pixel in and the first out, along
    # rows for a steep line, along columns otherwise) lie on the analytic line
    for k, ln in enumerate(lines):
        other = lines[1 - k]
        if abs(ln[0]) > abs(ln[1]):
            ys, xs = np.nonzero((mask[:, :-1] != mask[:, 1:]) & middle[:, :-1] & middle[:, 1:])
            pts = np.stack([xs + 0.5, ys], 1)
        else:
            ys, xs = np.nonzero((mask[:-1] != mask[1:]) & middle[:-1] & middle[1:])
            pts = np.stack([xs, ys + 0.5], 1)
        dist = pts @ ln[:2] + ln[2]
        mine = np.abs(dist) < np.abs(pts @ other[:2] + other[2])
        dist = dist[mine]
        assert len(dist) > 50
        assert np.abs(dist).max() <= 0.5 + 1e-4  # within half a pixel step
        assert abs(dist.mean()) < 0.1  # and unbiased: sub-pixel agreement


@pytest.mark.parametrize("bias", [0.5, -0.5, 0.3])
def test_fractional_bias_moves_limb_lines_by_bias_px(bias):
    """Rendered with ``bias_px``, the shaft's outline is its analytic limb lines moved
    outward by exactly ``bias_px`` px (sub-pixel: within 0.01 px over thousands of
    pixels), and the clean render (the truth's) does not change."""
    p0 = np.array([-60.0, -30.0, 70.0])
    a = np.array([1.0, 0.45, 0.35]) / np.linalg.norm([1.0, 0.45, 0.35])
    parts = [
        [PartGeometry("shaft", (Cylinder(p0, a, 200.0, 4.0),), np.zeros(3), np.zeros(3), np.eye(3))]
    ]
    caster = RayCaster(CAM)
    clean = caster.render(parts).instance > 0
    mask = caster.render(parts, bias_px=bias).instance > 0
    assert np.array_equal(clean, _render_prims([parts[0][0].primitives[0]]).instance > 0)
    lines = _limb_lines(p0, a, 4.0)
    h, w = mask.shape
    vv, uu = np.mgrid[0:h, 0:w]
    c = CAM.camera
    d = np.stack([(uu - c.cx) / c.fx, (vv - c.cy) / c.fy, np.ones_like(uu, float)], -1)
    da, dd = d @ a, np.sum(d * d, -1)
    t = (da * (-p0 @ a) + d @ p0) / (dd - da**2)
    s = t * da - p0 @ a
    middle = (s > 20) & (s < 180) & (t > 5)
    side = np.min([ln[0] * uu + ln[1] * vv + ln[2] for ln in lines], axis=0)  # signed px
    clear = middle & (np.abs(side + bias) > 0.01)
    band = (
        clear
        & (np.abs(side) > 0.01)
        & (np.minimum(side, side + bias) < 0)
        & (np.maximum(side, side + bias) > 0)
    )
    assert np.count_nonzero(band) > 300  # pixels whose verdict the bias changes
    assert np.array_equal(mask[clear], side[clear] > -bias)
    assert np.array_equal(clean[band], ~mask[band])


@pytest.mark.parametrize("bias", [0.5, -0.5, 1.0])
def test_fractional_bias_grows_spheres_and_caps_by_bias_px(bias):
    sph = Sphere(np.array([10.0, -8.0, 80.0]), 6.0)
    ax = np.array([0.0, 0.1, 0.995]) / np.linalg.norm([0.0, 0.1, 0.995])
    cap = Cylinder(np.array([20.0, 10.0, 150.0]), ax, 50.0, 10.0)  # seen end-on: its cap
    for prim in (sph, cap):
        parts = [[PartGeometry("shaft", (prim,), np.zeros(3), np.zeros(3), np.eye(3))]]
        caster = RayCaster(CAM)
        a0 = np.count_nonzero(caster.render(parts).instance)
        a1 = np.count_nonzero(caster.render(parts, bias_px=bias).instance)
        # the near-circular outline's equivalent radius grows by the bias (pixel-count
        # quantisation: a few hundredths of a px)
        assert math.sqrt(a1 / math.pi) - math.sqrt(a0 / math.pi) == pytest.approx(bias, abs=0.1)


def test_sphere_depth_and_outline_are_exact():
    c = np.array([10.0, -8.0, 80.0])
    r = 6.0
    buf = _render_prims([Sphere(c, r)])
    u, v = CAM.project(c)
    # the ray through the projected centre hits at distance |c| - r, depth scaled by z
    ui, vi = int(round(u)), int(round(v))
    d = np.array([(ui - CAM.camera.cx) / CAM.camera.fx, (vi - CAM.camera.cy) / CAM.camera.fy, 1.0])
    b = d @ c
    t_exact = (b - math.sqrt(b * b - (d @ d) * (c @ c - r * r))) / (d @ d)
    assert buf.depth[vi, ui] == pytest.approx(t_exact, abs=1e-3)
    # a pixel is inside iff its ray passes within r of the centre
    vv, uu = np.mgrid[0 : CAM.height, 0 : CAM.width]
    dx = (uu - CAM.camera.cx) / CAM.camera.fx
    dy = (vv - CAM.camera.cy) / CAM.camera.fy
    dist2 = (dx**2 + dy**2 + 1) * (c @ c) - (dx * c[0] + dy * c[1] + c[2]) ** 2
    dist2 /= dx**2 + dy**2 + 1
    clear = np.abs(dist2 - r * r) > 1e-3
    assert np.array_equal((buf.instance > 0)[clear], (dist2 <= r * r)[clear])


def test_nearer_instrument_hides_the_farther_one():
    far = Cylinder(np.array([-80.0, 0.0, 120.0]), np.array([1.0, 0.0, 0.0]), 160.0, 5.0)
    near = Cylinder(np.array([0.0, -60.0, 70.0]), np.array([0.0, 1.0, 0.0]), 120.0, 4.0)
    buf = _render_prims([far, near])
    u, v = CAM.project(np.array([0.0, 0.0, 70.0]))
    assert buf.instance[int(round(v)), int(round(u))] == 2
    # swap the order of drawing: the answer must not change
    buf2 = _render_prims([near, far])
    assert buf2.instance[int(round(v)), int(round(u))] == 1
    assert np.array_equal(buf.depth, buf2.depth)
    # each instrument alone: the far one is complete there; the composite is their union
    assert buf.alone[0][int(round(v)), int(round(u))] > 0
    assert np.array_equal(buf.instance > 0, (buf.alone[0] > 0) | (buf.alone[1] > 0))
    assert np.array_equal(buf.instance == 1, (buf.alone[0] > 0) & ~(buf.instance == 2))


def _pose(axis, insertion=110.0, roll=0.0, wrist=0.0, yaw=0.0, jaw=30.0):
    return InstrumentPose(
        np.array([100.0, -40.0, 5.0]),
        np.asarray(axis, float) / np.linalg.norm(axis),
        insertion,
        roll,
        wrist,
        yaw,
        jaw,
    )


def test_projected_joint_sits_on_the_shaft_clasper_boundary():
    geom = InstrumentGeometry()
    # shaft perpendicular to the ray through J: its end cap projects to a segment through
    # the projected joint, so the shaft / wrist boundary passes through it
    trocar = np.array([100.0, -40.0, 5.0])
    j = np.array([0.0, 5.0, 90.0])
    v = j - trocar
    a = v - (v @ j) / (j @ j) * j  # remove the component along the ray through J
    a /= np.linalg.norm(a)
    trocar = j - 120.0 * a
    pose = InstrumentPose(trocar, a, 120.0, 20.0, 0.0, 0.0, 30.0)
    parts = instrument_parts(pose, geom)
    buf = RayCaster(CAM).render([parts])
    uj, vj = CAM.project(parts[0].end_mm)
    shaft = buf.part == PART_CODES["shaft"]
    head = buf.part >= PART_CODES["wrist"]
    border = shaft & (
        np.roll(head, 1, 0) | np.roll(head, -1, 0) | np.roll(head, 1, 1) | np.roll(head, -1, 1)
    )
    ys, xs = np.nonzero(border)
    assert len(xs) > 10
    assert np.hypot(xs - uj, ys - vj).min() <= 1.0


def test_kinematics_truth_points():
    geom = InstrumentGeometry()
    pose = _pose([-1.0, 0.5, 0.9], roll=40.0, wrist=25.0, yaw=-15.0, jaw=50.0)
    shaft, wrist, clasper = instrument_parts(pose, geom)
    # the shaft runs through the trocar, J at the insertion distance
    assert np.allclose(shaft.start_mm, pose.trocar_mm)
    assert np.allclose(shaft.end_mm, pose.trocar_mm + pose.insertion_mm * pose.axis)
    assert np.linalg.norm(wrist.end_mm - wrist.start_mm) == pytest.approx(geom.wrist_length_mm)
    # the tip is the mid-point of the two jaw tips
    jaws = clasper.primitives
    tips = [j.p0 + j.length * j.axis for j in jaws]
    assert np.allclose(clasper.end_mm, (tips[0] + tips[1]) / 2)
    opening = math.degrees(math.acos(np.clip(jaws[0].axis @ jaws[1].axis, -1, 1)))
    assert opening == pytest.approx(50.0)
    # frames are rotations; the wrist bend is the angle between shaft and wrist axes
    for pg in (shaft, wrist, clasper):
        assert np.allclose(pg.rotation.T @ pg.rotation, np.eye(3), atol=1e-12)
        assert np.linalg.det(pg.rotation) == pytest.approx(1.0)
        q = matrix_to_wxyz(pg.rotation)
        assert np.linalg.norm(q) == pytest.approx(1.0)
    bend = math.degrees(math.acos(shaft.rotation[:, 2] @ wrist.rotation[:, 2]))
    assert bend == pytest.approx(25.0)
    # with everything straight and closed, joint to tip is the clasper length
    s2, _, c2 = instrument_parts(_pose([-1.0, 0.5, 0.9], jaw=0.0), geom)
    assert np.linalg.norm(c2.end_mm - s2.end_mm) == pytest.approx(geom.clasper_length_mm)


def test_motion_is_smooth_pivots_about_a_fixed_trocar_and_stays_in_depth():
    geom = InstrumentGeometry()
    poses = generate_motion(CAM, [geom, geom], 250, 25.0, seed=3)
    for inst in poses:
        trocars = np.array([p.trocar_mm for p in inst])
        assert np.ptp(trocars, axis=0).max() == 0.0
        # the trocar is outside the view
        t = trocars[0]
        u, v = CAM.project(t) if t[2] > 0 else (1e9, 1e9)
        assert not (0 <= u < CAM.width and 0 <= v < CAM.height)
        joints = np.array([p.trocar_mm + p.insertion_mm * p.axis for p in inst])
        uv = CAM.project(joints)
        seen = (uv[:, 0] >= 0) & (uv[:, 0] < CAM.width) & (uv[:, 1] >= 0) & (uv[:, 1] < CAM.height)
        assert seen.mean() > 0.5
        z = joints[seen, 2]
        assert z.min() >= DEPTH_RANGE_MM[0] and z.max() <= DEPTH_RANGE_MM[1]
        # smooth: joint speed bounded (< 10 mm per frame at 25 fps)
        assert np.linalg.norm(np.diff(joints, axis=0), axis=1).max() < 10.0
        # the tool moves: insertion, roll and jaws all vary
        for attr in ("insertion_mm", "roll_deg", "wrist_deg", "jaw_open_deg"):
            assert np.ptp([getattr(p, attr) for p in inst]) > 5.0


def test_leave_view_takes_the_tool_out_and_back():
    geom = InstrumentGeometry()
    inst = generate_motion(CAM, [geom], 250, 25.0, seed=1, options=MotionOptions(leave_view=True))[
        0
    ]
    buf = [RayCaster(CAM).render([instrument_parts(p, geom)]).instance.any() for p in inst[::5]]
    runs = np.flatnonzero(np.diff(np.array(buf, int)))
    assert len(runs) >= 3  # enters, leaves, comes back


def _png_bytes(folder: Path) -> list[bytes]:
    return [p.read_bytes() for p in sorted(folder.glob("*.png"))]


def test_same_seed_same_files_other_seed_other_files(tmp_path):
    kw = dict(frames=6, instruments=2, corruptions=Corruptions(jitter_px=1.5, speckle=3))
    a = synthesize(tmp_path / "a", seed=5, **kw)
    b = synthesize(tmp_path / "b", seed=5, **kw)
    c = synthesize(tmp_path / "c", seed=6, **kw)
    assert _png_bytes(a.path) == _png_bytes(b.path)
    assert (a.path / "truth.csv").read_text() == (b.path / "truth.csv").read_text()
    assert (a.path / "truth.csv").read_text() != (c.path / "truth.csv").read_text()


@pytest.mark.parametrize(
    "corr",
    [
        Corruptions(jitter_px=2.0),
        Corruptions(bias_px=2),
        Corruptions(bias_px=-2),
        Corruptions(bias_px=0.5),
        Corruptions(holes=6),
        Corruptions(speckle=20),
        Corruptions(occluders=3),
        Corruptions(hide_clasper=1.0),
    ],
)
def test_corruptions_change_masks_never_truth(tmp_path, corr):
    kw = dict(
        frames=4, instruments=2, seed=2, scene=SceneOptions(motion=MotionOptions(enter=False))
    )
    clean = synthesize(tmp_path / "clean", **kw)
    bad = synthesize(tmp_path / "bad", corruptions=corr, **kw)
    assert (clean.path / "truth.csv").read_text() == (bad.path / "truth.csv").read_text()
    assert _png_bytes(clean.path) != _png_bytes(bad.path)


def test_truth_boxes_are_the_clean_masks_boxes(tmp_path):
    res = synthesize(
        tmp_path / "s",
        frames=3,
        instruments=1,
        seed=4,
        scene=SceneOptions(motion=MotionOptions(enter=False)),
    )
    truth = read_csv(res.path / "truth.csv")
    cfg = load_config(res.path)
    for f in range(3):
        img = cv2.imread(str(res.path / f"{f:06d}.png"), cv2.IMREAD_UNCHANGED)
        for part, (lo, hi) in cfg.parts.items():
            ys, xs = np.nonzero((img >= lo) & (img <= hi))
            rows = np.flatnonzero((truth["frame"] == f) & (truth["part"] == part))
            if len(xs) == 0:
                assert len(rows) == 0
                continue
            # the tracker's convention: every pixel, box grown to the pixel edges
            box, _ = mask_box(((img >= lo) & (img <= hi)).astype(np.uint8))
            (r,) = rows
            assert truth["cx_px"][r] == pytest.approx(box.cx, abs=1e-4)
            assert truth["cy_px"][r] == pytest.approx(box.cy, abs=1e-4)
            assert truth["length_px"][r] == pytest.approx(box.length, abs=1e-4)
            assert truth["width_px"][r] == pytest.approx(box.width, abs=1e-4)
            assert truth["angle_deg"][r] == pytest.approx(box.angle_deg, abs=1e-4)
            assert truth["area_px"][r] == len(xs)
    assert np.all(truth["visible_frac"] == 1.0)  # one instrument: nothing hides it
    # exact 3D: unit axes, and the clasper tip lies near its box
    ax = np.stack([truth["axis_x"], truth["axis_y"], truth["axis_z"]], 1)
    assert np.allclose(np.linalg.norm(ax, axis=1), 1.0, atol=1e-5)
    cl = truth["part"] == "clasper"
    tip = np.stack([truth["end_x_mm"][cl], truth["end_y_mm"][cl], truth["end_z_mm"][cl]], 1)
    uv = CAM.project(tip)
    dist = np.hypot(uv[:, 0] - truth["cx_px"][cl], uv[:, 1] - truth["cy_px"][cl])
    assert (dist <= truth["length_px"][cl] / 2 + 2).all()


def test_visible_fraction_counts_what_the_other_instrument_hides(tmp_path):
    res = synthesize(
        tmp_path / "s",
        frames=60,
        instruments=2,
        seed=0,
        scene=SceneOptions(motion=MotionOptions(enter=False)),
    )
    v = read_csv(res.path / "truth.csv")["visible_frac"]
    assert np.all((v > 0) & (v <= 1.0))
    assert (v < 0.999).any() and (v == 1.0).mean() > 0.5  # tools cross, mostly apart


def test_mask_area_counts_the_pixels_left_in_the_written_masks(tmp_path):
    clean = synthesize(tmp_path / "c", frames=12, instruments=2, seed=0, preset="endovis17")
    t = with_mask_areas(read_csv(clean.path / "truth.csv"), read_csv(clean.path / "mask_areas.csv"))
    assert np.array_equal(t["mask_area_px"], t["area_px"])  # nothing corrupted
    res = synthesize(
        tmp_path / "o",
        frames=12,
        instruments=2,
        seed=0,
        preset="endovis17",
        corruptions=Corruptions(occluders=2),
    )
    t = with_mask_areas(read_csv(res.path / "truth.csv"), read_csv(res.path / "mask_areas.csv"))
    assert not np.isnan(t["mask_area_px"]).any()
    assert np.all(t["mask_area_px"] <= t["area_px"]) and (t["mask_area_px"] < t["area_px"]).any()
    for f in range(12):  # every written pixel is some tool's part: the rows share them all
        labels = cv2.imread(str(res.path / f"{f:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert t["mask_area_px"][t["frame"] == f].sum() == np.count_nonzero(labels)


def test_folder_config_and_labels(tmp_path):
    res = synthesize(tmp_path / "m", frames=2, instruments=2, preset="endovis17")
    cfg = load_config(res.path)
    assert cfg.labels == "endovis17" and cfg.instruments == ()
    assert cfg.camera is not None and cfg.camera.fx == 600.0
    assert cfg.shaft_diameter_mm == 8.0
    assert cfg.clasper_length_mm == pytest.approx(16.0)
    res = synthesize(
        tmp_path / "d", frames=2, instruments=2, preset="endovis15", distinct_labels=True
    )
    cfg = load_config(res.path)
    assert [i.name for i in cfg.instruments] == ["1", "2"]
    assert cfg.instruments[1].parts == {"shaft": (159, 159), "clasper": (69, 69)}
    assert cfg.instruments[0].shaft_diameter_mm == 8.0
    lap = synthesize(
        tmp_path / "l", frames=2, instruments=1, scene=SceneOptions(tool="laparoscopic")
    )
    assert load_config(lap.path).shaft_diameter_mm == 5.0
    assert np.all(read_csv(lap.path / "truth.csv")["wrist_deg"] == 0.0)


def test_video_is_written_and_its_ranges_hold_the_smeared_values(tmp_path):
    res = synthesize(
        tmp_path / "v",
        frames=5,
        instruments=2,
        video="mjpg",
        scene=SceneOptions(motion=MotionOptions(enter=False)),
    )
    checked = 0
    cap = cv2.VideoCapture(str(res.path / "masks.avi"))
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        n += 1
        png = cv2.imread(str(res.path / f"{n - 1:06d}.png"), cv2.IMREAD_UNCHANGED)
        grey = frame[..., 0].astype(int)
        for lo, hi in res.config.parts.values():
            inside = (png >= lo) & (png <= hi)
            # away from edges, the decoded value stays within the part's range
            core = cv2.erode(inside.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
            if core.sum() > 100:
                assert ((grey[core] >= lo) & (grey[core] <= hi)).mean() > 0.99
                checked += 1
    assert n == 5 and checked >= 5


def test_refuses_a_non_empty_folder_and_leaves_nothing_on_failure(tmp_path):
    out = tmp_path / "s"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(InputPathError, match="not empty"):
        synthesize(out, frames=1)
    with pytest.raises(InputPathError, match="only replaces a folder written by"):
        synthesize(out, frames=1, force=True)  # never wipes a folder it did not write
    assert (out / "keep.txt").read_text() == "mine"
    (out / "keep.txt").unlink()
    synthesize(out, frames=1)
    (out / "extra.txt").write_text("x")
    synthesize(out, frames=2, force=True)  # an earlier synth output is replaced whole
    assert not (out / "extra.txt").exists() and (out / "000001.png").exists()
    with pytest.raises(ConfigError):
        synthesize(tmp_path / "bad", frames=0)
    with pytest.raises(ConfigError):
        synthesize(tmp_path / "bad", frames=2, preset="nope")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_corruption_strengths_do_what_they_say():
    from mistool.synth.corrupt import Corruptor

    labels = np.zeros((120, 160), np.uint8)
    labels[40:80, 20:140] = 160
    labels[50:70, 100:140] = 70
    inst = (labels > 0).astype(np.uint8)
    part = np.where(labels == 160, 1, np.where(labels == 70, 3, 0)).astype(np.uint8)

    def run(**kw):
        c = Corruptor(Corruptions(**kw), labels.shape, 100, 1, 25.0, seed=0)
        return c, c.apply(labels, inst, part, 0, [70, 160])

    area = np.count_nonzero(labels)
    assert np.count_nonzero(run(bias_px=2)[1]) > area
    eroded = run(bias_px=-2)[1]
    assert np.count_nonzero(eroded) < area
    assert (eroded[40:42] == 0).all() and (eroded[44:76, 24:136] == labels[44:76, 24:136]).all()
    jit = run(jitter_px=3.0)[1]
    moved = np.argwhere(jit != labels)
    assert len(moved) and np.abs(np.count_nonzero(jit) - area) < 0.1 * area
    c, _ = run(hide_clasper=0.3)
    assert c._hidden.sum() == 30
    hidden_frame = int(np.flatnonzero(c._hidden[0])[0])
    out = c.apply(labels, inst, part, hidden_frame, [70, 160])
    assert not (out == 70).any() and (out == 160).sum() == (labels == 160).sum()
    _, occ = run(occluders=2)
    assert np.count_nonzero(occ) < area and set(np.unique(occ)) <= {0, 70, 160}


def test_bundled_sample_is_a_small_endovis15_sequence_with_truth():
    from mistool.resources import sample_masks_dir

    root = sample_masks_dir()
    pngs = sorted(root.glob("*.png"))
    assert len(pngs) == 250
    assert sum(p.stat().st_size for p in root.iterdir()) < 5_000_000
    cfg = load_config(root)
    assert cfg.labels == "endovis15" and cfg.camera is not None and cfg.fps == 25.0
    for p in pngs[::50]:
        img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert img.shape == (576, 720) and img.dtype == np.uint8
        assert set(np.unique(img)) <= {0, 70, 160}
    truth = read_csv(root / "truth.csv")
    assert set(truth["instrument"]) == {"1", "2"}
    assert truth["frame"].min() > 0  # the tools enter after the first frame
    assert np.ptp(truth["jaw_open_deg"]) > 20  # and grasp


@pytest.mark.parametrize(
    "preset,parts",
    [("endovis15", ["shaft", "clasper"]), ("endovis17", ["shaft", "wrist", "clasper"])],
)
def test_truth_parts_are_linked_segments_along_their_axes(tmp_path, preset, parts):
    res = synthesize(
        tmp_path / "s",
        frames=3,
        instruments=1,
        preset=preset,
        seed=3,
        scene=SceneOptions(motion=MotionOptions(enter=False)),
    )
    t = read_csv(res.path / "truth.csv")
    for f in range(3):
        rows = {p: np.flatnonzero((t["frame"] == f) & (t["part"] == p))[0] for p in parts}

        def vec(prefix: str, r: int, t=t) -> np.ndarray:
            return np.array(
                [t[f"{prefix}_{a}" + ("_mm" if prefix != "axis" else "")][r] for a in "xyz"]
            )

        for k, p in enumerate(parts):
            r = rows[p]
            seg = vec("end", r) - vec("start", r)
            assert np.allclose(seg / np.linalg.norm(seg), vec("axis", r), atol=1e-5)
            if k:  # each part starts where the previous one ends
                assert np.allclose(vec("start", r), vec("end", rows[parts[k - 1]]), atol=1e-5)
    # the head's length: joint to tip at most the clasper length of the config
    clasper, shaft = rows["clasper"], rows["shaft"]
    joint_to_tip = np.linalg.norm(vec("end", clasper) - vec("end", shaft))
    assert joint_to_tip <= res.config.clasper_length_mm + 1e-6
