"""The Python API: track() over folders/arrays, the frame-by-frame Tracker, ordering,
flat memory (bounded frames in flight), warnings, empty input."""

from __future__ import annotations

import subprocess
import sys
import warnings
import weakref
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

import mistool
from mistool import parallel
from mistool.api import MistoolWarning, Tracker, run, track
from mistool.config import Config, config_from_dict
from mistool.errors import ConfigError, MistoolError
from mistool.model import COLUMN_NAMES, TrackTable

H, W = 120, 160


def _frame(i: int, *, two: bool = False) -> np.ndarray:
    """Axis-aligned shaft [x0, x0+50) x [50, 60) and clasper right of it; x0 = 10 + 2i."""
    img = np.zeros((H, W), np.uint8)
    x0 = 10 + 2 * i
    img[50:60, x0 : x0 + 50] = 160
    img[48:62, x0 + 50 : x0 + 62] = 70
    if two:  # a second, separate instrument, vertical, moving down
        img[5 + i : 45 + i, 130:138] = 160
    return img


def _compare(a: TrackTable, b: TrackTable) -> None:
    assert a.columns == b.columns and a.num_rows == b.num_rows
    for c in a.columns:
        if a[c].dtype == object:
            assert a[c].tolist() == b[c].tolist(), c
        else:
            np.testing.assert_array_equal(a[c], b[c], err_msg=c)


def test_public_names() -> None:
    assert mistool.track is track and mistool.Tracker is Tracker
    assert mistool.Config is Config and issubclass(mistool.MistoolError, Exception)
    assert {"load_config", "TrackTable", "RotatedBox"} <= set(dir(mistool))


def test_track_arrays_rows_and_columns() -> None:
    frames = [_frame(i) for i in range(6)]
    table = track(frames, Config(fps=5.0))
    assert table.columns[:18] == COLUMN_NAMES[:18]
    assert table.num_rows == 12
    assert table["frame"].tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 5, 5]
    assert table["part"].tolist()[:2] == ["shaft", "clasper"]
    assert len(set(table["instrument"].tolist())) == 1
    shaft = table[table["part"] == "shaft"]
    np.testing.assert_allclose(shaft["time_s"], np.arange(6) / 5.0)
    # pixel centres x0 .. x0+49 and 50 .. 59: centre (x0 + 24.5, 54.5)
    np.testing.assert_allclose(shaft["cx_px"], 10 + 2 * np.arange(6) + 24.5, atol=0.5)
    np.testing.assert_allclose(shaft["cy_px"], 54.5, atol=0.5)
    assert np.all((shaft["angle_deg"] < 0.5) | (shaft["angle_deg"] > 179.5))
    np.testing.assert_array_equal(shaft["area_px"], 500.0)
    corners = np.stack([shaft[f"{a}{k}_px"] for k in range(1, 5) for a in "xy"], axis=1)
    np.testing.assert_allclose(
        corners.reshape(-1, 4, 2).mean(axis=1),
        np.stack([shaft["cx_px"], shaft["cy_px"]], axis=1),
        atol=1e-6,
    )
    assert np.isnan(shaft["dx_px"][0])  # first frame: no motion
    np.testing.assert_allclose(shaft["dx_px"][1:], 2.0, atol=0.5)
    assert np.isnan(table["end_x_mm"]).all()  # no camera


def test_folder_equals_arrays_and_workers_keep_order(tmp_path: Path) -> None:
    frames = [_frame(i, two=True) for i in range(20)]
    for i, img in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"m{i}.png"), img)
    (tmp_path / "mistool.toml").write_text("fps = 20.0\n")
    by_folder = track(tmp_path, workers=2)
    by_arrays = track(frames, Config(fps=20.0), workers=1)
    _compare(by_folder, by_arrays)
    assert len(set(by_folder["instrument"].tolist())) == 2
    _compare(track(str(tmp_path), config=tmp_path / "mistool.toml", workers=3), by_folder)


def test_frames_in_flight_are_bounded() -> None:
    """Memory stays flat: the pipeline never holds more than a few frames at once."""
    alive: list[weakref.ref] = []
    peak = 0

    def frames() -> Iterator[np.ndarray]:
        nonlocal peak
        for i in range(800):
            img = _frame(i % 20)
            alive.append(weakref.ref(img))
            peak = max(peak, sum(r() is not None for r in alive))
            yield img

    table = track(frames(), Config(), workers=2)
    assert table.num_rows == 1600
    # batches in flight (2 per worker) plus the batch being filled, plus the one being read
    bound = (parallel.IN_FLIGHT_PER_WORKER * 2 + 1) * parallel.LOCAL_BATCH_FRAMES + 1
    assert peak <= bound < 800, peak


def test_empty_and_single_frame() -> None:
    empty = track([np.zeros((H, W), np.uint8)] * 3, Config())
    assert empty.num_rows == 0 and empty.columns[:4] == COLUMN_NAMES[:4]
    assert empty["cx_px"].dtype == np.float64
    result = run([_frame(0)], Config())
    assert result.num_frames == 1 and result.shape == (H, W) and result.table.num_rows == 2
    assert result.instruments and result.parts == ("shaft", "clasper")


def test_unknown_values_warn_once() -> None:
    frames = [_frame(i) for i in range(4)]
    frames[1][0:5, 0:5] = 33
    frames[3][0:5, 0:5] = 34
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        track(frames, Config())
    msgs = [str(w.message) for w in caught if issubclass(w.category, MistoolWarning)]
    assert len(msgs) == 1 and "33, 34" in msgs[0]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"smoothing": "kalman"}, "smoothing = 'kalman'"),
        ({"workers": 0}, "workers = 0"),
        ({"config": 3}, "config: expected a Config"),
    ],
)
def test_bad_arguments(kwargs: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        track([_frame(0)], **kwargs)


def test_size_change_in_arrays() -> None:
    with pytest.raises(MistoolError, match="frame 2: frame size changed"):
        track([_frame(0), _frame(1), np.zeros((H, W + 1), np.uint8)], Config())


def test_tracker_matches_track() -> None:
    frames = [_frame(i, two=True) for i in range(8)]
    frames[3][:, 120:] = 0  # the second instrument leaves for a frame
    cfg = Config(fps=8.0)
    tracker = Tracker(cfg, smoothing="none")
    per_frame = [tracker.update(f) for f in frames]
    assert tracker.num_frames == 8
    empty = tracker.update(np.zeros((H, W), np.uint8))  # nothing in view: same columns
    assert empty.num_rows == 0 and empty.columns == per_frame[0].columns
    frames.append(np.zeros((H, W), np.uint8))
    whole = track(frames, cfg, smoothing="none")
    _compare(tracker.table(), whole)
    stitched = TrackTable.concat([*per_frame, empty]).sorted()
    for col in ("frame", "cx_px", "angle_deg", "dx_px", "dy_px", "dz", "dyaw_deg"):
        np.testing.assert_array_equal(stitched[col], whole[col], err_msg=col)
    assert stitched["instrument"].tolist() == whole["instrument"].tolist()


def test_tracker_rejects_size_change() -> None:
    tracker = Tracker(config_from_dict({}))
    tracker.update(_frame(0))
    with pytest.raises(MistoolError, match="frame 1: frame size changed"):
        tracker.update(np.zeros((10, 10), np.uint8))


def test_import_does_not_pull_viser() -> None:
    code = (
        "import sys, mistool, mistool.api, mistool.cli.track; mistool.track; "
        "assert 'viser' not in sys.modules, 'viser imported'"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_mask_video_tracks_like_the_png_frames(tmp_path: Path) -> None:
    frames = [_frame(i) for i in range(10)]
    path = tmp_path / "Segmentation.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (W, H), False)
    for img in frames:
        writer.write(img)
    writer.release()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the codec's smear is not "unknown label values"
        video = track(path, workers=2)
    exact = track(frames, Config())
    assert video["part"].tolist() == exact["part"].tolist()  # lossy, but every part found
    np.testing.assert_allclose(video["cx_px"], exact["cx_px"], atol=1.0)
    np.testing.assert_allclose(video["cy_px"], exact["cy_px"], atol=1.0)


def test_progress_bar_does_not_change_results(capsys: pytest.CaptureFixture) -> None:
    frames = [_frame(i) for i in range(5)]
    _compare(track(frames, Config(), progress=True), track(frames, Config()))
    assert capsys.readouterr().out == ""  # the bar goes to stderr only


def _write_format(folder: Path, frames: list[np.ndarray], fmt: str) -> None:
    """Write label frames in one pixel format, with the mistool.toml that reads them."""
    folder.mkdir()
    toml = ""
    for i, img in enumerate(frames):
        path = folder / f"f{i}.png"
        if fmt == "grey8":
            cv2.imwrite(str(path), img)
        elif fmt == "grey-as-rgb":
            cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        elif fmt == "grey16":
            cv2.imwrite(str(path), img.astype(np.uint16) * 300)
            toml = "[parts]\nshaft = 48000\nclasper = 21000\n"
        elif fmt == "palette":
            pil = pytest.importorskip("PIL.Image")
            im = pil.fromarray(img, mode="P")
            pal = np.zeros((256, 3), np.uint8)
            pal[160] = (200, 30, 30)
            pal[70] = (30, 200, 30)
            im.putpalette(pal.ravel().tolist())
            im.save(path)
        elif fmt == "colour":
            bgr = np.zeros(img.shape + (3,), np.uint8)
            bgr[img == 160] = (0, 0, 255)  # red shaft
            bgr[img == 70] = (255, 128, 0)  # blue-ish clasper: #0080ff
            cv2.imwrite(str(path), bgr)
            toml = '[parts]\nshaft = "#ff0000"\nclasper = "#0080ff"\n'
    (folder / "mistool.toml").write_text(toml)


@pytest.mark.parametrize("fmt", ["grey-as-rgb", "grey16", "palette", "colour"])
def test_pixel_formats_give_the_same_table(tmp_path: Path, fmt: str) -> None:
    frames = [_frame(i, two=True) for i in range(4)]
    _write_format(tmp_path / "grey8", frames, "grey8")
    _write_format(tmp_path / fmt, frames, fmt)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no unknown values in any format
        _compare(track(tmp_path / fmt), track(tmp_path / "grey8"))


def test_metric_columns_with_a_camera(tmp_path: Path) -> None:
    """With [camera] the metric pose fills end_*/axis_*; metric=False leaves them empty."""
    from mistool.resources import sample_masks_dir

    sample = sample_masks_dir()
    for name in sorted(p.name for p in sample.glob("*.png"))[100:112]:  # tools in view
        (tmp_path / name).write_bytes((sample / name).read_bytes())
    (tmp_path / "mistool.toml").write_text((sample / "mistool.toml").read_text())
    result = run(tmp_path)
    assert result.metric and result.config.camera is not None
    axis = np.stack([result.table[c] for c in ("axis_x", "axis_y", "axis_z")], axis=1)
    ok = np.isfinite(axis).all(axis=1)
    assert ok.mean() > 0.5
    np.testing.assert_allclose(np.linalg.norm(axis[ok], axis=1), 1.0, atol=1e-6)
    assert np.all(result.table["end_z_mm"][ok] > 0)  # in front of the camera
    plain = run(tmp_path, metric=False)
    assert not plain.metric and np.isnan(plain.table["end_x_mm"]).all()
    np.testing.assert_array_equal(plain.table["cx_px"], result.table["cx_px"])


def test_benchmark_script_runs() -> None:
    """scripts/bench_track.py works (smoke test on a few frames; no timing asserted)."""
    script = Path(__file__).resolve().parents[1] / "scripts" / "bench_track.py"
    proc = subprocess.run(
        [sys.executable, str(script), "--frames", "4", "--runs", "1"],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    assert "ratio imread-unchanged / api:" in proc.stdout


def test_a_frame_kept_whole_with_nothing_waiting_goes_on_at_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``identified`` with a pool: a frame whose instances the identity step keeps and
    whose pose came with it, while no earlier frame waits, is yielded as it is, without
    a pending entry (one per frame, the caller's cost); a frame after one that waits
    for its pose still waits its turn: the frames come out in order."""
    from types import SimpleNamespace

    from mistool import api

    made: list[int] = []
    pending = api._Pending

    def counted(index: int, *args: object) -> object:
        made.append(index)
        return pending(index, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(api, "_Pending", counted)

    class Tracker:
        def resolve(self, index: int, instances: list, runs: object) -> tuple[list, list]:
            return instances, [str(k + 1) for k in range(len(instances))]

    busy = SimpleNamespace(result=lambda: [np.zeros((0, 3, 1))], done=lambda: False)
    pool = SimpleNamespace(workers=1, batch_frames=1, submit=lambda *a: busy)
    seq = SimpleNamespace(config=Config(), check_shape=lambda *a: None)
    empty = np.zeros(0, np.int64)
    frames = [
        parallel.FrameResult([], np.zeros((0, 3, 1)), empty, (4, 4), deferred=k == 2)
        for k in range(5)
    ]
    out = list(
        api.identified(
            enumerate(zip("abcde", frames, strict=True)),  # type: ignore[arg-type]
            seq,  # type: ignore[arg-type]
            Tracker(),  # type: ignore[arg-type]
            True,
            pool,  # type: ignore[arg-type]
        )
    )
    assert [index for index, _, _ in out] == [0, 1, 2, 3, 4]
    assert out[0][2] is frames[0] and out[1][2] is frames[1]
    assert made == [2, 3, 4]  # the deferred frame and those after it while it waited
