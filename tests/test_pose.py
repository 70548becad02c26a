"""Metric pose: closed-form cylinder cases, hard views, trocar, filtering.

Masks are ray-cast at known poses (``mistool.pose.raycast``: exact pixel-centre sampling
of a capped cylinder shaft and a thinner clasper), so every expected value is the pose
the image was rendered from.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from mistool.config import Camera, Config
from mistool.model import TrackTable
from mistool.pose import measure_instance, refine_sequence
from mistool.pose.cylinder import axis_from_lines, quat_from_z
from mistool.pose.filtering import filter_series
from mistool.pose.raycast import render_instrument
from mistool.pose.status import AUX_STATUS, reason_code
from mistool.pose.trocar import intersect_lines

CAM = Camera(600.0, 600.0, 359.5, 287.5)
K = CAM.K
SHAPE = (576, 720)
R = 4.0  # 8 mm shaft


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def part_obs(mask: np.ndarray) -> SimpleNamespace | None:
    """A PartObservation-like crop of a full-image bool mask."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return None
    x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
    (cx, cy), (w, h), _ = cv2.minAreaRect(np.stack([xs, ys], 1).astype(np.float32))
    box = SimpleNamespace(cx=cx, cy=cy, length=max(w, h), width=min(w, h))
    return SimpleNamespace(
        mask=mask[y0:y1, x0:x1].copy(), offset=(int(x0), int(y0)), box=box, area_px=len(xs)
    )


def observe(labels: np.ndarray, shaft: int = 160, clasper: int = 70) -> SimpleNamespace:
    parts = {}
    for name, val in (("shaft", shaft), ("clasper", clasper)):
        obs = part_obs(labels == val)
        if obs is not None:
            parts[name] = obs
    return SimpleNamespace(label=None, parts=parts)


def render(J, a, bend=(0.0, 0.0, 0.0), length=10.0, clasper=True):
    a = unit(a)
    tip = J + length * unit(a + np.asarray(bend, float)) if clasper else None
    lab = render_instrument(SHAPE, K, J - 400.0 * a, J, tip, R, 0.6)
    return lab, tip


def vec(row: dict, prefix: str) -> np.ndarray:
    keys = {
        "end": ("end_x_mm", "end_y_mm", "end_z_mm"),
        "axis": ("axis_x", "axis_y", "axis_z"),
        "start": ("start_x_mm", "start_y_mm", "start_z_mm"),
    }[prefix]
    return np.array([row[k] for k in keys])


def angle_deg(u, v) -> float:
    return math.degrees(math.acos(np.clip(float(unit(u) @ unit(v)), -1.0, 1.0)))


# --- closed form ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "p0,a",
    [
        ([10.0, -5.0, 80.0], [1.0, 0.2, 0.3]),
        ([-20.0, 15.0, 140.0], [0.1, -1.0, 0.8]),
        ([0.0, 0.0, 60.0], [0.3, 0.1, -1.0]),
    ],
)
def test_axis_from_tangent_planes_is_exact(p0, a):
    """Planes through the origin tangent to a known cylinder give its axis back."""
    p0, a = np.asarray(p0), unit(a)
    p0 = p0 - (p0 @ a) * a  # the axis point closest to the camera centre
    d = np.linalg.norm(p0)
    u = p0 / d  # toward the axis, perpendicular to it
    w = np.cross(a, u)
    # tangent plane normals n (n.a = 0, n.p0 = R): n = cos(phi) u + sin(phi) w
    c = R / d
    s = math.sqrt(1.0 - c * c)
    n1, n2 = c * u + s * w, c * u - s * w
    got_p, got_a = axis_from_lines(n1, n2, R)
    assert abs(abs(got_a @ a) - 1.0) < 1e-12
    off = got_p - p0
    assert np.linalg.norm(off - (off @ a) * a) < 1e-9


@pytest.mark.parametrize(
    "J,a",
    [
        ([0.0, 0.0, 100.0], [1.0, 0.0, 0.0]),  # across the view, frontal
        ([-15.0, 10.0, 60.0], [0.7, -0.4, 0.6]),  # receding
        ([20.0, -10.0, 140.0], [-0.3, 0.8, 0.5]),  # far, steep
        ([5.0, 5.0, 55.0], [0.5, 0.6, -0.6]),  # pointing toward the camera
        ([10.0, 0.0, 110.0], [1.0, 1.0, 0.0]),  # 45 degrees in the image
    ],
)
def test_clean_render_gives_pose_back(J, a):
    J, a = np.asarray(J), unit(a)
    labels, tip = render(J, a, bend=(0.0, 0.2, 0.0))
    out = measure_instance(observe(labels), SHAPE, CAM, 2 * R, 10.0)
    shaft, clasper = out["shaft"], out["clasper"]
    assert np.linalg.norm(vec(shaft, "end") - J) < 0.3
    assert angle_deg(vec(shaft, "axis"), a) < 0.3
    assert shaft["quality"] > 0.95
    q = np.array([shaft[k] for k in ("qw", "qx", "qy", "qz")])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-9
    # the clasper's tip is the far end of a 0.6 mm-radius rod: its silhouette reaches up
    # to 0.6 mm past the end point
    assert np.linalg.norm(vec(clasper, "end") - tip) < 2.0
    assert np.allclose(vec(clasper, "start"), vec(shaft, "end"))
    assert angle_deg(vec(clasper, "axis"), tip - J) < 15.0
    # the shaft's start lies on the axis, proximal of J and inside the view
    st = vec(shaft, "start")
    assert (J - st) @ a > 5.0
    assert np.linalg.norm(np.cross(st - J, a)) < 0.5


@pytest.mark.parametrize(
    "J,a",
    [
        ([-20.0, 0.0, 80.0], [1.0, 0.0, 0.8]),
        ([10.0, 10.0, 70.0], [-0.3, 0.5, 0.8]),
        ([0.0, -10.0, 90.0], [0.2, 1.0, 0.3]),
    ],
)
def test_tip_is_the_jaw_end_centre_not_its_rim(J, a, monkeypatch):
    """A thick clasper (2 mm radius) receding from the camera: its image ends at the end
    cap's rim, several px beyond the cap's centre (the tip); the tip's pixel is pulled
    back onto the centre."""
    import mistool.pose.measure as measure

    J, a = np.asarray(J), unit(a)
    tip = J + 16.0 * a
    labels = render_instrument(SHAPE, K, J - 400.0 * a, J, tip, R, 2.0)
    uv = K @ tip
    uv = uv[:2] / uv[2]

    def tip_px(cap: float) -> tuple[float, float]:
        monkeypatch.setattr(measure, "_TIP_CAP", cap)
        cl = measure_instance(observe(labels), SHAPE, CAM, 2 * R, 16.0)["clasper"]
        return (
            float(np.linalg.norm([cl["aux_u_px"] - uv[0], cl["aux_v_px"] - uv[1]])),
            float(np.linalg.norm(vec(cl, "end") - tip)),
        )

    px_raw, _ = tip_px(0.0)
    px, mm = tip_px(1.0)
    assert px_raw > 4.0  # the rim overshoots the centre
    assert px < 3.0 and mm < 1.5


def test_quaternion_rotates_z_onto_axis():
    for a in (unit([1, 2, 3]), unit([0, 0, -1]), unit([0.2, -0.9, -0.1]), np.array([0, 0, 1.0])):
        w, x, y, z = quat_from_z(a)
        # third column of the rotation matrix
        col = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
        assert np.allclose(col, a, atol=1e-12)


# --- hard views -----------------------------------------------------------------------


def test_nearly_pointing_at_camera_is_empty_or_right():
    """Shaft 8 degrees off the optical axis: either no answer or a right one."""
    J = np.array([0.0, 0.0, 70.0])
    a = unit([math.sin(math.radians(8)), 0.0, -math.cos(math.radians(8))])
    labels, _ = render(J, a)
    out = measure_instance(observe(labels), SHAPE, CAM, 2 * R, 10.0)
    end = vec(out["shaft"], "end")
    if np.all(np.isfinite(end)):
        assert np.linalg.norm(end - J) < 3.0
        assert angle_deg(vec(out["shaft"], "axis"), a) < 5.0


def test_one_limb_line_is_left_empty():
    """Shaft hugging the image border: one silhouette line is outside the image."""
    a = unit([1.0, 0.0, 0.25])
    J = np.array([10.0, -55.0, 120.0])  # projects ~15 px below the top edge
    labels, _ = render(J, a)
    assert np.any(labels[0] == 160)  # the upper limb is out of the view
    out = measure_instance(observe(labels), SHAPE, CAM, 2 * R, 10.0)
    row = out["shaft"]
    assert math.isnan(row["end_x_mm"]) and math.isnan(row["axis_x"])
    # one line was still measured, for the trocar-constrained solve
    assert np.isfinite(row["aux_l1a"]) != np.isfinite(row["aux_l2a"])


def test_occluder_cutting_the_shaft():
    J, a = np.array([5.0, 0.0, 90.0]), unit([1.0, 0.3, 0.4])
    labels, _ = render(J, a)
    # a tissue blob across the shaft (background), away from the joint
    jx, jy = (K @ J)[:2] / J[2]
    cv2.circle(labels, (int(jx - 110), int(jy - 30)), 28, 0, -1)
    out = measure_instance(observe(labels), SHAPE, CAM, 2 * R, 10.0)
    end = vec(out["shaft"], "end")
    assert np.linalg.norm(end - J) < 1.0
    assert angle_deg(vec(out["shaft"], "axis"), a) < 1.0
    assert out["shaft"]["quality"] < 0.97  # the blob lowers the re-render score


def test_joint_outside_the_image():
    """The clasper is out of the view: axis yes, joint no."""
    a = unit([1.0, 0.1, 0.2])
    J = np.array([90.0, 5.0, 100.0])  # projects at u ~ 900 > 720
    labels, _ = render(J, a)
    out = measure_instance(observe(labels), SHAPE, CAM, 2 * R, 10.0)
    row = out["shaft"]
    assert "clasper" not in out
    assert math.isnan(row["end_x_mm"])
    assert angle_deg(vec(row, "axis"), a) < 0.5
    st = vec(row, "start")
    off = st - J
    assert np.linalg.norm(off - (off @ a) * a) < 0.5  # start is on the true axis


def test_absent_parts_and_unknown_camera():
    J, a = np.array([0.0, 0.0, 100.0]), unit([1.0, 0.2, 0.3])
    labels, _ = render(J, a)
    obs = observe(labels)
    for camera, diameter, reason in ((None, 2 * R, "no camera"), (CAM, None, "no shaft diameter")):
        out = measure_instance(obs, SHAPE, camera, diameter, 10.0)
        assert all(math.isnan(v) for row in out.values() for k, v in row.items() if k != AUX_STATUS)
        assert all(row[AUX_STATUS] == reason_code(reason) for row in out.values())
    only_clasper = SimpleNamespace(label=None, parts={"clasper": obs.parts["clasper"]})
    out = measure_instance(only_clasper, SHAPE, CAM, 2 * R, 10.0)
    assert set(out) == {"clasper"} and math.isnan(out["clasper"]["end_x_mm"])
    assert out["clasper"][AUX_STATUS] == reason_code("not visible")


def test_wrong_diameter_lowers_nothing_but_depth_scales():
    """The depth scales with the assumed diameter (a sanity check of the closed form)."""
    J, a = np.array([0.0, 5.0, 100.0]), unit([1.0, 0.2, 0.3])
    labels, _ = render(J, a)
    e8 = vec(measure_instance(observe(labels), SHAPE, CAM, 8.0, 10.0)["shaft"], "end")
    e5 = vec(measure_instance(observe(labels), SHAPE, CAM, 5.0, 10.0)["shaft"], "end")
    assert np.allclose(e5, e8 * 5.0 / 8.0, rtol=2e-3)


# --- sequence level -------------------------------------------------------------------


def _pivot_sequence(n: int, seed: int):
    """Axis lines through a trocar T with J at varying insertion depth."""
    rng = np.random.default_rng(seed)
    T = np.array([-120.0, -60.0, 20.0])
    js = []
    for k in range(n):
        target = np.array(
            [10 * math.sin(k / 15), 8 * math.cos(k / 20), 100 + 20 * math.sin(k / 25)]
        )
        js.append(target + rng.normal(0, 0.01, 3))
    js = np.array(js)
    axes = js - T
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return T, js, axes


def test_trocar_from_axis_lines_with_outliers():
    T, js, axes = _pivot_sequence(40, 0)
    bad = axes.copy()
    bad[::8] = unit([0.0, 1.0, 0.0])  # 5 wrong frames
    est = intersect_lines(js, bad)
    assert est is not None
    assert np.linalg.norm(est.point - T) < 0.5
    assert not est.inliers[::8].any()
    # parallel lines: no trocar
    assert intersect_lines(js, np.repeat(axes[:1], len(js), axis=0)) is None


def _table(js, axes, frames=None, noise=0.0, seed=1):
    rng = np.random.default_rng(seed)
    n = len(js)
    frames = np.arange(n) if frames is None else frames
    e = js + rng.normal(0, noise, js.shape) if noise else js
    return TrackTable(
        {
            "frame": frames,
            "instrument": ["1"] * n,
            "part": ["shaft"] * n,
            "end_x_mm": e[:, 0],
            "end_y_mm": e[:, 1],
            "end_z_mm": e[:, 2],
            "axis_x": axes[:, 0],
            "axis_y": axes[:, 1],
            "axis_z": axes[:, 2],
            "aux_l1a": np.full(n, np.nan),
        }
    )


def test_refine_fills_trocar_smooths_and_drops_aux():
    T, js, axes = _pivot_sequence(60, 2)
    table = _table(js, axes, noise=0.5)
    cfg = Config(camera=CAM)
    out = refine_sequence(table, cfg, smoothing="offline")
    assert not any(c.startswith("aux_") for c in out.columns)
    trocar = np.stack([out[c] for c in ("trocar_x_mm", "trocar_y_mm", "trocar_z_mm")], 1)
    assert np.all(np.linalg.norm(trocar - T, axis=1) < 2.0)
    raw = np.stack([table[c] for c in ("end_x_mm", "end_y_mm", "end_z_mm")], 1)
    sm = np.stack([out[c] for c in ("end_x_mm", "end_y_mm", "end_z_mm")], 1)
    assert np.median(np.linalg.norm(sm - js, axis=1)) < 0.7 * np.median(
        np.linalg.norm(raw - js, axis=1)
    )
    none = refine_sequence(table, cfg, smoothing="none")
    assert np.allclose(none["end_x_mm"], table["end_x_mm"])
    q = np.stack([out[c] for c in ("qw", "qx", "qy", "qz")], 1)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0)


def test_online_filter_is_causal_offline_is_zero_phase():
    t = np.arange(80) / 25.0
    y = np.stack([np.sin(2 * t), np.cos(3 * t)], 1) * 20
    y_noisy = y + np.random.default_rng(3).normal(0, 0.3, y.shape)
    on = filter_series(t, y_noisy, "online", 3000.0, 0.05)
    changed = y_noisy.copy()
    changed[50:] += 100.0
    on2 = filter_series(t, changed, "online", 3000.0, 0.05)
    assert np.allclose(on[:50], on2[:50])  # the past does not see the future
    off = filter_series(t, y_noisy, "offline", 3000.0, 0.05)
    off2 = filter_series(t, changed, "offline", 3000.0, 0.05)
    assert not np.allclose(off[:50], off2[:50])
    # zero phase: on a ramp the smoother has no lag, the causal filter little
    ramp = np.stack([t * 50.0], 1)
    assert np.max(np.abs(filter_series(t, ramp, "offline", 3000.0, 0.05) - ramp)) < 1e-4
    # a gap splits the track; NaN rows stay NaN
    gap = y_noisy.copy()
    gap[30:40] = np.nan
    res = filter_series(t, gap, "offline", 3000.0, 0.05)
    assert np.all(np.isnan(res[30:40])) and np.all(np.isfinite(res[:30]))


def test_refine_rejects_unknown_smoothing():
    from mistool.errors import ConfigError

    with pytest.raises(ConfigError, match="smoothing"):
        refine_sequence(TrackTable(), Config(), smoothing="kalman")


def test_piece_cut_by_an_occluder_has_no_joint():
    """An occluder cuts the tool in two; the proximal piece alone (as a merged-mask
    tracker sees it) ends at the cut, which must not be taken for the joint."""
    J, a = np.array([15.0, 5.0, 90.0]), unit([1.0, 0.25, 0.3])
    labels, _ = render(J, a)
    jx, jy = (K @ J)[:2] / J[2]
    cv2.circle(labels, (int(jx - 150), int(jy - 38)), 45, 0, -1)
    n, comp = cv2.connectedComponents((labels == 160).astype(np.uint8))
    assert n == 3  # background + two shaft pieces
    sizes = [(comp == k).sum() for k in (1, 2)]
    # the piece that does not touch the clasper is the proximal one
    near_clasper = cv2.dilate((labels == 70).astype(np.uint8), np.ones((3, 3), np.uint8))
    prox = next(k for k in (1, 2) if not np.any(near_clasper[comp == k]))
    assert sizes[prox - 1] > 500
    obs = SimpleNamespace(label=None, parts={"shaft": part_obs(comp == prox)})
    row = measure_instance(obs, SHAPE, CAM, 2 * R, 10.0)["shaft"]
    assert math.isnan(row["end_x_mm"])
    # its axis is still right
    if np.isfinite(row["axis_x"]):
        assert angle_deg(vec(row, "axis"), a) < 2.0


def test_two_tools_merged_into_one_instance():
    """Two tools touching (merged masks): the larger shaft is measured, the clasper,
    which could be either tool's, is left empty."""
    Ja, aa = np.array([-5.0, 0.0, 80.0]), unit([-1.0, 0.2, 0.3])  # larger (nearer)
    Jb, ab = np.array([12.0, 30.0, 120.0]), unit([1.0, 0.3, 0.4])
    la, tipa = render(Ja, aa)
    lb, tipb = render(Jb, ab)
    labels = np.where(la > 0, la, lb)
    pa = (K @ tipa)[:2] / tipa[2]
    pb = (K @ tipb)[:2] / tipb[2]
    cv2.line(labels, tuple(int(v) for v in pa), tuple(int(v) for v in pb), 70, 3)
    obs = observe(labels)
    n, _ = cv2.connectedComponents((labels > 0).astype(np.uint8))
    assert n == 2  # one connected instrument region
    out = measure_instance(obs, SHAPE, CAM, 2 * R, 10.0)
    assert np.linalg.norm(vec(out["shaft"], "end") - Ja) < 0.5
    assert angle_deg(vec(out["shaft"], "axis"), aa) < 0.5
    assert math.isnan(out["clasper"]["end_x_mm"])


def test_two_shafts_overlapping_are_not_a_cylinder():
    """Two shafts crossing in one region (a V, not a cylinder): no confident answer."""
    la, _ = render(np.array([-5.0, 0.0, 80.0]), unit([-1.0, 0.2, 0.3]))
    lb, _ = render(np.array([12.0, 6.0, 120.0]), unit([1.0, 0.3, 0.4]))
    labels = np.where(la > 0, la, lb)
    assert cv2.connectedComponents((labels == 160).astype(np.uint8))[0] == 2
    row = measure_instance(observe(labels), SHAPE, CAM, 2 * R, 10.0)["shaft"]
    assert math.isnan(row["end_x_mm"]) and math.isnan(row["axis_x"])


def test_robust_line_fit_ignores_outliers():
    from mistool.pose.silhouette import fit_line_robust

    rng = np.random.default_rng(4)
    x = np.linspace(0.0, 300.0, 600)
    y = 0.3 * x + 5.0 + rng.uniform(-0.5, 0.5, x.size)  # quantisation-like noise
    y[::7] += rng.uniform(3.0, 15.0, y[::7].size)  # a notch / another edge
    line, inl, sigma = fit_line_robust(np.stack([x, y], 1), x)
    n = np.array([-0.3, 1.0]) / math.hypot(0.3, 1.0)
    if line[:2] @ n < 0:
        line = -line
    assert np.allclose(line[:2], n, atol=1e-3)
    assert abs(line[2] - (-5.0 * n[1])) < 0.1  # offset within 0.1 px
    assert sigma < 0.4
    assert not np.isin(np.arange(0, 600, 7), inl).any()
