"""The viewer on a distorted lens: the frustum (and the endoscope view) show the
undistorted frame, the 2D overlay panel the original one."""

from __future__ import annotations

import cv2
import numpy as np

from mistool.config import Camera
from mistool.lens import distort_points, undistort_view
from mistool.synth import SceneOptions, synthesize
from mistool.viewer import ReplayViewer, load_sequence

BARREL = (-0.24, 0.055, 0.0, 0.0, 0.0)


def test_undistort_view_scales_to_a_smaller_display_copy():
    """A half-size copy of the camera's image is undistorted with half the intrinsics: a
    straight line of the ideal image, bent by the lens, is straight again."""
    cam = Camera(600.0, 600.0, 359.5, 287.5, BARREL)
    ideal = np.stack([np.linspace(40, 680, 400), np.full(400, 60.0)], axis=1)
    img = np.zeros((576, 720, 3), np.uint8)
    cv2.polylines(
        img, [np.round(distort_points(ideal, cam)).astype(np.int32)], False, (255,) * 3, 3
    )
    half = cv2.resize(img, (360, 288), interpolation=cv2.INTER_AREA)
    und = undistort_view(half, cam, (720, 576))
    ys, _ = np.nonzero(und[:, 75:285, 0] > 100)
    assert abs(float(np.median(ys)) - (60.0 + 0.5) / 2 + 0.5) < 1.0 and np.ptp(ys) <= 4
    assert undistort_view(half, Camera(600.0, 600.0, 359.5, 287.5), (720, 576)) is half


def test_frustum_shows_the_undistorted_frame(tmp_path):
    out = tmp_path / "seq"
    synthesize(out, frames=6, instruments=1, seed=1, scene=SceneOptions(distortion=BARREL))
    sequence = load_sequence(out, poses=out / "truth.csv")
    viewer = ReplayViewer(sequence, port=0)
    try:
        k = 5
        viewer.timeline.seek(k)
        assert viewer.timeline.wait_shown(k) and viewer.wait_overlay(k)
        panel = viewer.image._image  # the 2D overlay: the original frame
        frustum = viewer.scene.frustum._image
        cam = sequence.replay.config.camera
        assert cam is not None and cam.distorted
        assert frustum.shape == panel.shape and not np.array_equal(frustum, panel)
        assert np.array_equal(frustum, undistort_view(panel, cam, sequence.replay.image_wh))
    finally:
        viewer.close()


def test_export_html_and_serve_take_calibration(tmp_path, capsys):
    """--calibration on export-html (and serve: same loader): a file of another aspect
    ratio than the masks is a one-line error before any work."""
    from mistool.cli import main

    out = tmp_path / "seq"
    synthesize(out, frames=2, instruments=1, seed=1)
    fs = cv2.FileStorage(str(tmp_path / "odd.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 1920)
    fs.write("image_height", 1080)
    fs.write("camera_matrix", np.array([[1000.0, 0, 959.5], [0, 1000.0, 539.5], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[-0.2, 0.05, 0.0, 0.0, 0.0]]))
    fs.release()
    for cmd in (["export-html", str(out), "-o", str(tmp_path / "r.html")], ["serve", str(out)]):
        assert main([*cmd, "--calibration", str(tmp_path / "odd.yml")]) == 1
        err = capsys.readouterr().err
        assert err.startswith("mistool: error: ") and "not a uniform scaling" in err
        assert err.count("\n") == 1
