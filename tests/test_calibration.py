"""Calibration files (OpenCV FileStorage YAML/XML/JSON, ROS camera_info YAML): the same
camera, and the same 3D, as the equivalent [camera] table; sizes checked against masks."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.api import track
from mistool.calibration import read_calibration
from mistool.cli import main
from mistool.config import Camera, load_config
from mistool.errors import ConfigError, InputWarning
from mistool.export import read_csv
from mistool.synth import Corruptions, SceneOptions, synthesize

BARREL = (-0.24, 0.055, 0.001, -0.0005, 0.0)
K = np.array([[600.0, 0.0, 359.5], [0.0, 600.0, 287.5], [0.0, 0.0, 1.0]])
CAMERA = Camera(600.0, 600.0, 359.5, 287.5, BARREL, "pinhole", (720, 576))

ROS = """image_width: {w}
image_height: {h}
camera_name: endoscope
camera_matrix:
  rows: 3
  cols: 3
  data: [{fx}, 0, {cx}, 0, {fy}, {cy}, 0, 0, 1]
distortion_model: {model}
distortion_coefficients:
  rows: 1
  cols: {n}
  data: [{d}]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [{fx}, 0, {cx}, 0, 0, {fy}, {cy}, 0, 0, 0, 1, 0]
"""


def write_opencv(
    path: Path, k: np.ndarray = K, dist=BARREL, wh=(720, 576), model: str | None = None
) -> Path:
    """A calibration file as OpenCV's calibration tools write it (cv2.FileStorage)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", wh[0])
    fs.write("image_height", wh[1])
    fs.write("camera_matrix", k)
    fs.write("distortion_coefficients", np.array(dist, dtype=np.float64).reshape(1, -1))
    if model is not None:
        fs.write("distortion_model", model)
    fs.release()
    return path


def write_ros(path: Path, k=K, dist=BARREL, wh=(720, 576), model="plumb_bob") -> Path:
    path.write_text(
        ROS.format(
            w=wh[0],
            h=wh[1],
            fx=k[0, 0],
            fy=k[1, 1],
            cx=k[0, 2],
            cy=k[1, 2],
            model=model,
            n=len(dist),
            d=", ".join(repr(float(v)) for v in dist),
        ),
        encoding="utf-8",
    )
    return path


@pytest.mark.parametrize("ext", ["yml", "xml", "json"])
def test_opencv_filestorage_formats(tmp_path, ext):
    cam = read_calibration(write_opencv(tmp_path / f"camera.{ext}"))
    assert cam == CAMERA


def test_ros_camera_info(tmp_path):
    assert read_calibration(write_ros(tmp_path / "camera.yaml")) == CAMERA
    fish = read_calibration(
        write_ros(tmp_path / "f.yaml", dist=(0.1, 0.0, 0.0, 0.0), model="equidistant")
    )
    assert fish.model == "fisheye" and fish.distortion == (0.1, 0.0, 0.0, 0.0)
    fish2 = read_calibration(write_opencv(tmp_path / "f.yml", dist=(0.1, 0, 0, 0), model="fisheye"))
    assert fish2.model == "fisheye"


@pytest.mark.parametrize(
    "content,match",
    [
        ("image_width: 10\n", "no camera matrix"),
        ("{{{ :::", "cannot parse"),
        ("camera_matrix:\n  rows: 2\n  cols: 2\n  data: [1, 0, 0, 1]\n", "must be 3x3"),
        (
            "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 3, 10, 0, 500, 10, 0, 0, 1]\n",
            "skew",
        ),
        (
            "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 0, 10, 0, 500, 10, 0, 0, 1]\n"
            "distortion_coefficients:\n  rows: 1\n  cols: 3\n  data: [0.1, 0.2, 0.3]\n",
            "3 values; the pinhole model takes 4 or 5",
        ),
        (
            "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [500, 0, 10, 0, 500, 10, 0, 0, 1]\n"
            "distortion_model: kannala\n",
            "not a known lens model",
        ),
    ],
)
def test_bad_calibration_files(tmp_path, content, match):
    p = tmp_path / "camera.yaml"
    p.write_text(content, encoding="utf-8")
    with pytest.raises(ConfigError, match=match):
        read_calibration(p)
    with pytest.raises(ConfigError, match="no such calibration file"):
        read_calibration(tmp_path / "missing.yaml")


def test_toml_calibration_key_is_relative_and_exclusive(tmp_path):
    (tmp_path / "cam").mkdir()
    write_ros(tmp_path / "cam" / "camera.yaml")
    toml = tmp_path / "mistool.toml"
    toml.write_text('calibration = "cam/camera.yaml"\n', encoding="utf-8")
    cfg = load_config(toml)
    assert cfg.camera == CAMERA and cfg.calibration == tmp_path / "cam" / "camera.yaml"
    toml.write_text(
        'calibration = "cam/camera.yaml"\n[camera]\nfx = 1.0\nfy = 1.0\ncx = 0\ncy = 0\n',
        encoding="utf-8",
    )
    with pytest.raises(ConfigError, match="either \\[camera\\] or calibration"):
        load_config(toml)


@pytest.fixture(scope="module")
def distorted(tmp_path_factory):
    """A short sequence rendered exactly through a distorted lens; its mistool.toml has
    the equivalent [camera] table."""
    out = tmp_path_factory.mktemp("cal") / "seq"
    return synthesize(
        out,
        frames=12,
        instruments=1,
        seed=5,
        corruptions=Corruptions(jitter_px=1.0),
        scene=SceneOptions(distortion=BARREL),
    )


def _strip_camera(seq: Path, extra: str = "") -> None:
    toml = seq / "mistool.toml"
    text = toml.read_text(encoding="utf-8").split("[camera]")[0]
    toml.write_text(text + extra, encoding="utf-8")


def test_same_3d_from_a_calibration_file_as_from_camera_table(distorted, tmp_path):
    """[camera] (synth's), calibration = FILE (OpenCV YAML, ROS) and --calibration give
    the same metric columns, to the last digit."""
    ref = track(distorted.path)
    assert np.isfinite(ref["end_x_mm"]).sum() >= 12
    import shutil

    cols = ["end_x_mm", "end_y_mm", "end_z_mm", "axis_x", "axis_y", "axis_z", "quality"]
    for name, writer in (("camera.yml", write_opencv), ("camera.yaml", write_ros)):
        seq = tmp_path / name.replace(".", "_")
        shutil.copytree(distorted.path, seq)
        writer(seq / name)
        _strip_camera(seq, f'calibration = "{name}"\n')
        got = track(seq)
        for c in cols:
            np.testing.assert_array_equal(got[c], ref[c])
    # on the command line, for a folder whose mistool.toml has no camera at all
    seq = tmp_path / "cli"
    shutil.copytree(distorted.path, seq)
    _strip_camera(seq)
    cal = write_opencv(tmp_path / "cli_camera.xml")
    assert (
        main(["track", str(seq), "-o", str(tmp_path / "m.csv"), "--calibration", str(cal), "-q"])
        == 0
    )
    got = read_csv(tmp_path / "m.csv")
    np.testing.assert_allclose(got["end_z_mm"], ref["end_z_mm"], atol=1e-6)


def test_calibration_of_another_size(distorted, tmp_path, capsys):
    """A calibration at twice the masks' size is scaled (and says so); one of another
    aspect ratio is an error naming both sizes."""
    ref = track(distorted.path)
    big = K.copy()
    big[0, 0] = big[1, 1] = 1200.0
    big[0, 2], big[1, 2] = 2 * (359.5 + 0.5) - 0.5, 2 * (287.5 + 0.5) - 0.5
    cal = write_opencv(tmp_path / "big.yml", k=big, wh=(1440, 1152))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = track(
            distorted.path, load_config(distorted.path).with_overrides(camera=read_calibration(cal))
        )
    notes = [str(w.message) for w in caught if issubclass(w.category, InputWarning)]
    assert any("1440x1152" in n and "720x576" in n and "scaled by 0.5" in n for n in notes)
    np.testing.assert_allclose(got["end_z_mm"], ref["end_z_mm"], atol=1e-6)
    out = tmp_path / "m.csv"
    assert (
        main(["track", str(distorted.path), "-o", str(out), "--calibration", str(cal), "-q"]) == 0
    )
    assert "scaled by 0.5" in capsys.readouterr().err
    odd = write_opencv(tmp_path / "odd.yml", wh=(1920, 1080))
    assert main(["track", str(distorted.path), "-o", str(out), "--calibration", str(odd)]) == 1
    err = capsys.readouterr().err
    assert (
        err.startswith("mistool: error: ") and "1920x1080" in err and "not a uniform scaling" in err
    )
    assert err.count("\n") == 1
