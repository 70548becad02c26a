"""Lens distortion: the point mapping, [camera] parsing, and 3D on distorted lenses
against exact truth (mistool synth renders through the lens exactly)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.api import track
from mistool.config import Camera, config_from_dict
from mistool.errors import ConfigError
from mistool.evaluation import evaluate
from mistool.lens import distort_points, fit_camera, undistort_image, undistort_points
from mistool.model import TrackTable
from mistool.synth import Corruptions, SceneOptions, synthesize

CAM = dict(fx=600.0, fy=610.0, cx=359.5, cy=287.5)
BARREL = (-0.24, 0.055, 0.0, 0.0, 0.0)  # ~16% barrel at the corners of 720x576, f = 600
FISHEYE = (0.02, -0.01, 0.0, 0.0)

LENSES = [
    ("pinhole 4", (-0.2, 0.04, 0.001, -0.0005), "pinhole"),
    ("pinhole 5", BARREL, "pinhole"),
    ("rational 8", (-0.2, 0.04, 0.001, -0.0005, 0.0, 0.01, 0.0, 0.002), "pinhole"),
    ("prism 12", (-0.2, 0.04, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.001, 0.0, -0.001, 0.0), "pinhole"),
    ("tilt 14", (-0.2, 0.04, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0.002, -0.001), "pinhole"),
    ("fisheye", FISHEYE, "fisheye"),
]


def _grid() -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, 719, 25), np.linspace(0, 575, 21))
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.mark.parametrize("name,dist,model", LENSES, ids=[x[0] for x in LENSES])
def test_undistort_inverts_opencv_projection(name, dist, model):
    """undistort_points is the exact inverse of OpenCV's own forward model
    (cv2.projectPoints / cv2.fisheye.distortPoints) over the whole image, corners
    included, and distort_points is that forward model."""
    cam = Camera(**CAM, distortion=tuple(map(float, dist)), model=model)
    pts = _grid()
    ideal = undistort_points(pts, cam)
    # OpenCV's forward model, independently of mistool.lens
    K, D = cam_k(cam), np.array(dist, dtype=np.float64)
    xn = (ideal - K[:2, 2]) / np.array([cam.fx, cam.fy])
    if model == "fisheye":
        back = cv2.fisheye.distortPoints(xn.reshape(-1, 1, 2), K, D).reshape(-1, 2)
    else:
        obj = np.concatenate([xn, np.ones((len(xn), 1))], axis=1)
        back = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), K, D)[0].reshape(-1, 2)
    assert np.abs(back - pts).max() < 1e-6
    assert np.abs(distort_points(ideal, cam) - pts).max() < 1e-6
    # a real lens: the corner moves by many pixels
    assert np.abs(ideal - pts).max() > 5.0


def cam_k(cam: Camera) -> np.ndarray:
    return np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])


def test_ideal_lens_is_identity_and_image_untouched():
    cam = Camera(**CAM)
    pts = _grid()
    assert not cam.distorted and np.array_equal(undistort_points(pts, cam), pts)
    img = np.zeros((10, 12, 3), np.uint8)
    assert undistort_image(img, cam) is img and undistort_image(img, None) is img


def test_undistort_image_straightens_a_line():
    """A straight line of the ideal image, drawn through the lens, is straight again in
    the undistorted image (the maps the viewer uses)."""
    cam = Camera(**CAM, distortion=BARREL)
    ideal = np.stack([np.linspace(40, 680, 400), np.full(400, 60.0)], axis=1)
    bent = distort_points(ideal, cam)
    img = np.zeros((576, 720), np.uint8)
    cv2.polylines(img, [np.round(bent).astype(np.int32)], False, 255, 3)
    assert np.ptp(bent[:, 1]) > 10  # visibly bent by the lens
    und = undistort_image(img, cam)
    ys, xs = np.nonzero(und[:, 150:570] > 127)
    assert abs(float(np.median(ys)) - 60.0) < 1.0 and np.ptp(ys) <= 6


@pytest.mark.parametrize(
    "camera,match",
    [
        ({**CAM, "distortion": [0.1, 0.2, 0.3]}, "3 values; the pinhole model takes 4 or 5"),
        ({**CAM, "distortion": [0.1] * 5, "model": "fisheye"}, "the fisheye model takes 4"),
        ({**CAM, "distortion": "0.1"}, "must be a list of numbers"),
        ({**CAM, "distortion": [0.1, "a", 0, 0]}, r"camera.distortion\[1\] must be a number"),
        ({**CAM, "model": "kannala"}, "not a lens model; choose one of pinhole, fisheye"),
        ({**CAM, "k1": 0.1}, "unknown key.*k1"),
    ],
)
def test_camera_table_errors(camera, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict({"camera": camera}, Path("seq/mistool.toml"))


def test_camera_table_lens():
    cfg = config_from_dict({"camera": {**CAM, "distortion": list(BARREL)}})
    assert cfg.camera is not None and cfg.camera.distortion == BARREL and cfg.camera.distorted
    fish = config_from_dict({"camera": {**CAM, "model": "fisheye"}})
    assert fish.camera is not None and fish.camera.distortion == (0.0,) * 4
    assert fish.camera.distorted  # the fisheye model bends lines even with zero terms
    zero = config_from_dict({"camera": {**CAM, "distortion": [0, 0, 0, 0, 0]}})
    assert zero.camera is not None and not zero.camera.distorted


def test_fit_camera_scaling_and_mismatch():
    cam = Camera(1000.0, 1000.0, 959.5, 539.5, BARREL, image_wh=(1920, 1080))
    same, note = fit_camera(cam, (1920, 1080))
    assert same is cam and note is None
    half, note = fit_camera(cam, (960, 540), "camera.yaml")
    assert half.fx == 500.0 and half.cx == 479.5 and half.cy == 269.5
    assert half.distortion == BARREL and half.image_wh == (960, 540)
    assert note is not None and "scaled by 0.5" in note and "camera.yaml" in note
    with pytest.raises(ConfigError, match="1920x1080 px.*720x576 px, which is not a uniform"):
        fit_camera(cam, (720, 576), "camera.yaml")


# --- 3D against exact truth -----------------------------------------------------------

MILD = Corruptions(jitter_px=1.0, holes=3.0, speckle=10.0)


def _tag(table: TrackTable, seed: int) -> TrackTable:
    """Offset frames and prefix names so that sequences stack into one table."""
    names = np.array([f"{seed}:{i}" for i in table["instrument"]], dtype=object)
    return table.with_columns(frame=table["frame"] + seed * 1000, instrument=names)


def _errors(seqs: list, config=None) -> dict[str, float]:
    """Median errors over several (synth result) sequences, tracked with ``config``
    (None: each sequence's own mistool.toml)."""
    tables = [_tag(track(r.path, config), k) for k, r in enumerate(seqs)]
    truth = TrackTable.concat([_tag(r.truth, k) for k, r in enumerate(seqs)])
    parts = evaluate({"m": TrackTable.concat(tables)}, truth).methods[0].parts
    return {
        "j": parts["shaft"]["end_mm"]["median"],
        "axis": parts["shaft"]["axis_deg"]["median"],
        "tip": parts["clasper"]["end_mm"]["median"],
        "cov": parts["shaft"]["metric_coverage"],
    }


@pytest.mark.parametrize(
    "dist,model", [(BARREL, "pinhole"), (FISHEYE, "fisheye")], ids=["barrel16", "fisheye"]
)
def test_3d_on_a_distorted_lens_meets_the_targets(tmp_path, dist, model):
    """Masks rendered exactly through a strongly distorted lens (mild noise; two seeded
    scenes of 20 frames: the tip's error varies more from scene to scene than with the
    lens, e.g. one 30-frame scene measured 1.82 mm undistorted, 2.04 mm fisheye): with the
    lens model the 3D meets the issue's targets; assuming an ideal pinhole it does not."""
    seqs = [
        synthesize(
            tmp_path / f"s{seed}",
            frames=20,
            instruments=2,
            seed=seed,
            corruptions=MILD,
            scene=SceneOptions(distortion=dist, lens_model=model),
        )
        for seed in (1, 2)
    ]
    cam = seqs[0].config.camera
    assert cam is not None and cam.distortion == dist
    got = _errors(seqs)
    assert got["cov"] >= 0.9
    assert got["j"] <= 1.0 and got["axis"] <= 1.5 and got["tip"] <= 2.0, got
    pinhole = replace(seqs[0].config, camera=replace(cam, distortion=(), model="pinhole"))
    naive = _errors(seqs, pinhole)
    assert naive["axis"] > 3.0 * max(got["axis"], 0.5), (got, naive)


def test_synth_lens_option_errors(tmp_path):
    with pytest.raises(ConfigError, match="the fisheye model takes 4"):
        synthesize(
            tmp_path / "x",
            frames=1,
            scene=SceneOptions(distortion=(0.1,) * 5, lens_model="fisheye"),
        )
    with pytest.raises(ConfigError, match="lens model 'wide' is not one of"):
        synthesize(tmp_path / "y", frames=1, scene=SceneOptions(lens_model="wide"))
