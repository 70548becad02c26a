"""The viewer without a browser: replay geometry, overlay pixels, timeline, CLI, export.

The browser tests are in ``test_viewer_browser.py``.
"""

from __future__ import annotations

import io
import math
import os
import socket
import threading
import time
from contextlib import redirect_stdout
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.cli import main
from mistool.config import Camera, Config, config_from_dict
from mistool.errors import InputPathError, MistoolError, TableError
from mistool.model import TrackTable
from mistool.viewer import ReplayViewer, build_replay, export_html, load_sequence
from mistool.viewer.app import parts_markdown
from mistool.viewer.overlay import FrameStore, OverlayRenderer
from mistool.viewer.replay import (
    METRIC_UNITS_PER_MM,
    NO_POSE,
    PAPER_UNITS_PER_PX,
    R_WORLD_CAMERA,
    Replay,
    config_parts,
    euler_from_quat,
    quat_z_to,
    scene_extent,
)

CAMERA = Camera(fx=600.0, fy=600.0, cx=359.5, cy=287.5)


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return r @ v


@pytest.mark.parametrize(
    "d", [(0, 0, 1), (0, 0, -1), (1, 0, 0), (0, 1, 0), (0.6, -0.8, 0.0), (0.3, 0.4, -0.866)]
)
def test_quat_z_to_rotates_z_onto_direction(d: tuple[float, ...]) -> None:
    d = np.asarray(d, float) / np.linalg.norm(d)
    q = quat_z_to(d)
    assert np.isclose(np.linalg.norm(q), 1.0)
    np.testing.assert_allclose(_rotate(q, np.array([0.0, 0.0, 1.0])), d, atol=1e-9)


def test_euler_from_quat_recovers_a_yaw() -> None:
    q = np.array([math.cos(math.radians(15)), 0.0, 0.0, math.sin(math.radians(15))])
    np.testing.assert_allclose(euler_from_quat(q), [0.0, 0.0, 30.0], atol=1e-9)


def _metric_table() -> TrackTable:
    """One instrument, frames 0 and 2 (frame 1 absent), shaft and clasper in mm."""
    rows = []
    for f in (0, 2):
        joint = np.array([10.0 + f, 5.0, 80.0])
        shaft_start = joint - np.array([0.0, 0.0, 40.0])
        tip = joint + np.array([0.0, 10.0, 0.0])
        rows.append(
            dict(
                frame=f,
                instrument="a",
                part="shaft",
                cx_px=300,
                cy_px=200,
                length_px=200,
                width_px=40,
                angle_deg=0.0,
                start_x_mm=shaft_start[0],
                start_y_mm=shaft_start[1],
                start_z_mm=shaft_start[2],
                end_x_mm=joint[0],
                end_y_mm=joint[1],
                end_z_mm=joint[2],
                axis_x=0.0,
                axis_y=0.0,
                axis_z=1.0,
            )
        )
        # The clasper's own start is off the joint: the viewer attaches it anyway.
        rows.append(
            dict(
                frame=f,
                instrument="a",
                part="clasper",
                cx_px=400,
                cy_px=220,
                length_px=60,
                width_px=20,
                angle_deg=90.0,
                start_x_mm=joint[0] + 3,
                start_y_mm=joint[1],
                start_z_mm=joint[2],
                end_x_mm=tip[0],
                end_y_mm=tip[1],
                end_z_mm=tip[2],
                axis_x=0.0,
                axis_y=1.0,
                axis_z=0.0,
            )
        )
    return TrackTable({k: [r[k] for r in rows] for k in rows[0]})


def test_metric_cylinders_are_linked_in_millimetres() -> None:
    config = Config(camera=CAMERA, shaft_diameter_mm=8.0)
    replay = build_replay(_metric_table(), config, num_frames=3)
    assert replay.default_mode == "metric"
    g = replay.modes["metric"]
    s = METRIC_UNITS_PER_MM
    joint_w = R_WORLD_CAMERA @ np.array([12.0, 5.0, 80.0]) * s
    # Shaft: from start to joint, 40 mm long, radius 4 mm.
    assert g.visible[2, 0, 0] and g.visible[2, 0, 1]
    assert np.isclose(g.length[2, 0, 0], 40.0 * s)
    assert np.isclose(g.radius[2, 0, 0], 4.0 * s)
    shaft_end = g.centre[2, 0, 0] + 0.5 * g.length[2, 0, 0] * _rotate(g.wxyz[2, 0, 0], [0, 0, 1])
    np.testing.assert_allclose(shaft_end, joint_w, atol=1e-9)
    # Clasper: its base is the shaft's end (joint), its end the tip.
    clasp_base = g.centre[2, 0, 1] - 0.5 * g.length[2, 0, 1] * _rotate(g.wxyz[2, 0, 1], [0, 0, 1])
    np.testing.assert_allclose(clasp_base, joint_w, atol=1e-9)
    assert np.isclose(g.length[2, 0, 1], 10.0 * s)
    # Camera y (down) is world -z: the tip 10 mm "down" in the image is lower in the world.
    np.testing.assert_allclose(g.tip[2, 0], joint_w + np.array([0.0, 0.0, -10.0 * s]))
    # Frame 1 has no rows: nothing drawn, no trail point.
    assert not g.visible[1].any() and np.isnan(g.tip[1]).all()
    # The metric position series is the part's end in mm.
    np.testing.assert_allclose(replay.series["metric/position"][0, 0, 1], [10.0, 15.0, 80.0])


def test_without_camera_or_metric_values_paper_mode_is_the_default() -> None:
    table = _metric_table()
    paper = {
        "paper_x_px": table["cx_px"],
        "paper_y_px": table["cy_px"],
        "paper_z": np.zeros(table.num_rows),
        "paper_roll_deg": np.zeros(table.num_rows),
        "paper_pitch_deg": np.zeros(table.num_rows),
        "paper_yaw_deg": np.zeros(table.num_rows),
    }
    replay = build_replay(table.with_columns(**paper), Config())
    assert list(replay.modes) == ["paper"] and replay.default_mode == "paper"


NAN = math.nan


@pytest.mark.parametrize(
    ("pose_status", "clasper_end_x", "camera", "panel"),
    [
        # The table says why (mistool's own tables): its reason is shown.
        (["ok", "ok"], 11.0, True, "shaft ✓ · clasper ✓"),
        (["ok", "tip not found"], NAN, True, "shaft ✓ · clasper: _tip not found_"),
        # The column is there but empty (a ground-truth table, another tool's table):
        # the metric pose decides, as without the column.
        (["", ""], 11.0, True, "shaft ✓ · clasper ✓"),
        (["", ""], NAN, True, f"shaft ✓ · clasper: _{NO_POSE}_"),
        ([NAN, None], 11.0, True, "shaft ✓ · clasper ✓"),
        (None, 11.0, True, "shaft ✓ · clasper ✓"),
        (None, NAN, True, f"shaft ✓ · clasper: _{NO_POSE}_"),
        # Without a camera there is no metric pose at all, and the panel says why.
        (["", ""], 11.0, False, "shaft: _no camera_ · clasper: _no camera_"),
    ],
)
def test_parts_panel_tells_whether_each_part_has_a_metric_pose(
    pose_status: list | None, clasper_end_x: float, camera: bool, panel: str
) -> None:
    table = _metric_table()
    table = table[np.asarray(table["frame"]) == 0]
    end_x = np.asarray(table["end_x_mm"], float).copy()
    end_x[1] = clasper_end_x
    table = table.with_columns(end_x_mm=end_x)
    if pose_status is not None:
        table = table.with_columns(pose_status=np.array(pose_status, dtype=object))
    if not camera:
        table = table.with_columns(paper_x_px=table["cx_px"], paper_y_px=table["cy_px"])
    config = Config(camera=CAMERA if camera else None, shaft_diameter_mm=8.0)
    replay = build_replay(table, config, image_wh=(720, 576))
    text = parts_markdown(replay, 0)
    assert f"**a**: {panel}  \n" in text, text
    if camera:  # a part is "✓" exactly where its cylinder is drawn
        shown = [s == "ok" for _, _, s, _ in replay.frame_status(0)]
        assert shown == list(replay.modes["metric"].visible[0, 0])


def test_a_wrist_posed_by_its_joint_and_axis_is_drawn() -> None:
    """mistool.pose gives a wrist its proximal end (the joint J) and axis, no distal end,
    and pose_status "ok": the panel said "wrist ✓" and no wrist was drawn."""
    table = _metric_table()
    table = table[np.asarray(table["frame"]) == 2]
    joint, tip = np.array([12.0, 5.0, 80.0]), np.array([12.0, 15.0, 80.0])
    wrist = {c: [table[c][1]] for c in table.columns}
    wrist.update(part=["wrist"], end_x_mm=[NAN], end_y_mm=[NAN], end_z_mm=[NAN])
    wrist.update({f"start_{a}_mm": [v] for a, v in zip("xyz", joint, strict=True)})
    rows = {c: np.concatenate([table[c], wrist[c]]) for c in table.columns}
    rows["pose_status"] = np.array(["ok"] * 3, dtype=object)
    config = Config(camera=CAMERA, shaft_diameter_mm=8.0, clasper_length_mm=8.0)
    replay = build_replay(TrackTable(rows), config, image_wh=(720, 576))
    assert replay.parts == ("shaft", "wrist", "clasper")
    assert "wrist ✓" in parts_markdown(replay, 2)
    g, s = replay.modes["metric"], METRIC_UNITS_PER_MM
    assert g.visible[2, 0].all()
    # The wrist: from the joint, half the clasper's length (4 mm) along its axis; the
    # clasper from there to the tip.
    up = _rotate(g.wxyz[2, 0, 1], [0, 0, 1])
    base = g.centre[2, 0, 1] - 0.5 * g.length[2, 0, 1] * up
    np.testing.assert_allclose(base, R_WORLD_CAMERA @ joint * s, atol=1e-9)
    assert np.isclose(g.length[2, 0, 1], 4.0 * s)
    w_end = R_WORLD_CAMERA @ (joint + [0.0, 4.0, 0.0]) * s
    clasp_base = g.centre[2, 0, 2] - 0.5 * g.length[2, 0, 2] * _rotate(g.wxyz[2, 0, 2], [0, 0, 1])
    np.testing.assert_allclose(clasp_base, w_end, atol=1e-9)
    np.testing.assert_allclose(g.tip[2, 0], R_WORLD_CAMERA @ tip * s, atol=1e-9)
    # A tip nearer than the nominal length: the wrist stops half way to it.
    near = dict(rows, end_y_mm=np.array([5.0, 9.0, NAN]))
    g = build_replay(TrackTable(near), config, image_wh=(720, 576)).modes["metric"]
    assert np.isclose(g.length[2, 0, 1], 2.0 * s) and np.isclose(g.length[2, 0, 2], 2.0 * s)


def test_paper_cylinders_follow_the_papers_scene() -> None:
    """Base at the paper's (x, y, z), length = box length, radius = half the box width,
    axis = +x turned by the yaw, clasper base on the shaft's end (the paper, Section 4)."""
    table = TrackTable(
        {
            "frame": [0, 0],
            "instrument": ["1", "1"],
            "part": ["shaft", "clasper"],
            "cx_px": [100.0, 100.0],
            "cy_px": [50.0, 250.0],
            "length_px": [200.0, 60.0],
            "width_px": [40.0, 20.0],
            "angle_deg": [90.0, 0.0],
            "paper_x_px": [100.0, 999.0],
            "paper_y_px": [50.0, 999.0],
            "paper_z": [0.0, 0.0],
            "paper_roll_deg": [90.0, 0.0],
            "paper_pitch_deg": [0.0, 0.0],
            "paper_yaw_deg": [90.0, 0.0],
        }
    )
    config = Config(camera=CAMERA)  # no metric columns: paper only
    replay = build_replay(table, config, image_wh=(720, 576))
    g = replay.modes["paper"]
    s = PAPER_UNITS_PER_PX

    def world(x: float, y: float) -> np.ndarray:  # pixel plane at depth fy
        return R_WORLD_CAMERA @ np.array([x - 360.0, y - 288.0, CAMERA.fy]) * s

    axis0 = _rotate(g.wxyz[0, 0, 0], np.array([0.0, 0.0, 1.0]))
    base0 = g.centre[0, 0, 0] - 0.5 * g.length[0, 0, 0] * axis0
    np.testing.assert_allclose(base0, world(100.0, 50.0), atol=1e-9)
    np.testing.assert_allclose(axis0, R_WORLD_CAMERA @ np.array([0.0, 1.0, 0.0]), atol=1e-9)
    assert np.isclose(g.length[0, 0, 0], 200.0 * s) and np.isclose(g.radius[0, 0, 0], 20 * s)
    axis1 = _rotate(g.wxyz[0, 0, 1], np.array([0.0, 0.0, 1.0]))
    base1 = g.centre[0, 0, 1] - 0.5 * g.length[0, 0, 1] * axis1
    np.testing.assert_allclose(base1, world(100.0, 250.0), atol=1e-9)  # the shaft's end
    np.testing.assert_allclose(axis1, R_WORLD_CAMERA @ np.array([1.0, 0.0, 0.0]), atol=1e-9)
    assert np.isclose(g.radius[0, 0, 1], 10 * s)


@pytest.mark.parametrize(
    "columns, message",
    [
        ({"frame": [], "instrument": [], "part": []}, "missing column 'cx_px'"),
        (
            {
                "frame": [0],
                "instrument": ["a"],
                "part": ["blade"],
                "cx_px": [1.0],
                "cy_px": [1.0],
                "length_px": [2.0],
                "width_px": [1.0],
            },
            "unknown part",
        ),
        (
            {
                "frame": [0],
                "instrument": ["a"],
                "part": ["shaft"],
                "cx_px": [1.0],
                "cy_px": [1.0],
                "length_px": [2.0],
                "width_px": [1.0],
            },
            "nothing to show",
        ),
    ],
)
def test_bad_tables_raise_one_line_errors(columns: dict, message: str) -> None:
    with pytest.raises(TableError, match=message) as info:
        build_replay(TrackTable(columns), Config())
    assert "\n" not in str(info.value)


# --- a synthetic sequence shared by the tests below ----------------------------------
@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from mistool.synth import synthesize

    out = tmp_path_factory.mktemp("viewer") / "seq"
    synthesize(out, frames=40, instruments=2, seed=3)
    return out


@pytest.fixture(scope="module")
def sequence(synth_dir: Path):
    return load_sequence(synth_dir, poses=synth_dir / "truth.csv")


def _busy_frame(replay) -> int:
    g = replay.modes[replay.default_mode]
    counts = g.visible.reshape(replay.num_frames, -1).sum(axis=1)
    return int(np.argmax(counts))


def test_parts_panel_of_a_ground_truth_table_shows_its_poses(sequence) -> None:
    """truth.csv has every metric pose and an empty ``pose_status`` column: the panel said
    "no pose" beside the drawn cylinders."""
    replay = sequence.replay
    g = replay.modes["metric"]
    for frame in range(replay.num_frames):
        status = np.array([s for _, _, s, _ in replay.frame_status(frame)])
        drawn = g.visible[frame].reshape(-1)
        assert ((status == "ok") == drawn).all(), (frame, status, drawn)
    k = _busy_frame(replay)
    text = parts_markdown(replay, k)
    assert NO_POSE not in text and text.count("shaft ✓") == len(replay.instruments), text


def test_overlay_colours_each_instrument_part_and_draws_boxes(sequence) -> None:
    replay = sequence.replay
    k = _busy_frame(replay)
    renderer = OverlayRenderer(replay, sequence.frames)
    img = renderer.render(k, opacity=1.0, boxes=False)
    w, h = renderer.size_wh
    assert img.shape == (h, w, 3) and img.dtype == np.uint8
    colours = img.reshape(-1, 3)
    for i in range(len(replay.instruments)):
        for part in replay.parts:
            c = np.array(replay.part_colour(i, part))
            if replay.modes[replay.default_mode].visible[k, i, replay.parts.index(part)]:
                assert (np.abs(colours.astype(int) - c).sum(axis=1) == 0).sum() > 20, (
                    replay.instruments[i],
                    part,
                )
    # Opacity 0 shows no mask; boxes add outline pixels.
    plain = renderer.render(k, opacity=0.0, boxes=False)
    assert len(np.unique(plain.reshape(-1, 3), axis=0)) == 1
    boxed = renderer.render(k, opacity=0.0, boxes=True)
    assert (boxed != plain).any(axis=2).sum() > 100


@pytest.mark.parametrize("kind", ["folder", "video"])
def test_overlay_blends_over_the_source_video(
    kind: str, synth_dir: Path, sequence, tmp_path: Path
) -> None:
    red = np.full((576, 720, 3), (0, 0, 255), np.uint8)  # BGR
    if kind == "folder":
        src = tmp_path / "rgb"
        src.mkdir()
        for i in range(sequence.replay.num_frames):
            cv2.imwrite(str(src / f"f{i}.png"), red)
    else:
        src = tmp_path / "Video.avi"
        writer = cv2.VideoWriter(str(src), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (720, 576))
        for _ in range(5):
            writer.write(red)
        writer.release()
    config = config_from_dict(
        {"source": str(src), "camera": {"fx": 600.0, "fy": 600.0, "cx": 359.5, "cy": 287.5}}
    )
    frames = FrameStore(synth_dir, config)
    assert frames.has_source and frames.has_masks
    img = OverlayRenderer(sequence.replay, frames).render(0, opacity=0.5, boxes=False)
    # Background pixels are the source (BGR red -> RGB red; the video is lossy).
    assert (np.abs(img.astype(int) - (255, 0, 0)).sum(axis=2) <= 12).mean() > 0.5
    again = OverlayRenderer(sequence.replay, frames).render(3, opacity=0.5, boxes=False)
    assert (np.abs(again.astype(int) - (255, 0, 0)).sum(axis=2) <= 12).mean() > 0.5
    frames.close()


def test_load_sequence_reports_problems_before_serving(tmp_path: Path) -> None:
    with pytest.raises(InputPathError, match="no such file"):
        load_sequence(tmp_path / "missing")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputPathError, match="no label images"):
        load_sequence(empty)
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,instrument\n0,a\n")
    with pytest.raises(TableError, match="part"):
        load_sequence(empty, poses=bad)


def test_viewer_draws_frames_and_timeline_coalesces_scrubbing(sequence) -> None:
    viewer = ReplayViewer(sequence, port=0)
    try:
        names = set(viewer.server.scene._handle_from_node_name)  # viser's own scene registry
        for inst in sequence.replay.instruments:
            for part in ("shaft", "clasper"):
                assert f"/instruments/{inst}/{part}" in names
        assert "/endoscope" in names and "/grid" in names
        tl = viewer.timeline
        for k in range(sequence.replay.num_frames):  # rapid scrubbing
            tl.request(k)
        last = sequence.replay.num_frames - 1
        assert tl.wait_shown(last)
        assert tl.frames_drawn < sequence.replay.num_frames + 1  # no backlog drawn
        tl.step(1)  # loops to 0
        assert tl.wait_shown(0) and int(tl.slider.value) == 0
        tl.speed.value = "4x"
        tl.set_playing(True)
        time.sleep(0.5)
        tl.set_playing(False)
        # 4x of 25 fps over 0.5 s is 50 frames; allow for a slow, shared machine.
        assert tl.frames_drawn >= 10 and not tl.draw_errors
        k = _busy_frame(sequence.replay)
        tl.seek(k)
        assert tl.wait_shown(k)
        assert viewer.wait_overlay(k), "the overlay of the frame shown never arrived"
        cyl = viewer.scene.parts[0, 0]
        assert cyl.visible == bool(viewer.replay.modes[viewer.scene.mode].visible[k, 0, 0])
    finally:
        viewer.close()


def test_cli_serve_prints_the_port_it_really_got(synth_dir: Path) -> None:
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    busy = blocker.getsockname()[1]
    from mistool.cli import build_parser
    from mistool.cli.serve import run

    args = build_parser().parse_args(
        ["serve", str(synth_dir), "--poses", str(synth_dir / "truth.csv"), "--port", str(busy)]
    )
    ready, stop = threading.Event(), threading.Event()
    out = io.StringIO()
    result: list[int] = []

    def serve() -> None:
        with redirect_stdout(out):
            result.append(run(args, ready=ready, stop=stop))

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        assert ready.wait(30)
        url = next(line for line in out.getvalue().splitlines() if "http://" in line)
        port = int(url.split("http://")[1].split()[0].rsplit(":", 1)[1])
        assert port != busy
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass
    finally:
        stop.set()
        thread.join(30)
        blocker.close()
    assert result == [0]


@pytest.mark.parametrize(
    "argv, needle",
    [
        (["serve", "{tmp}/nope"], "no such file"),
        (["serve", "{seq}", "--poses", "{tmp}/nope.csv"], "no such file"),
        (["serve", "{seq}", "--port", "70000"], "--port 70000"),
        (
            ["serve", "{seq}", "--poses", "{seq}/truth.csv", "--host", "no-such-host.invalid"],
            "--host no-such-host.invalid",
        ),
        (
            ["serve", "{seq}", "--poses", "{seq}/truth.csv", "--host", "192.0.2.1"],
            "--host 192.0.2.1",
        ),
        (
            [
                "export-html",
                "{seq}",
                "--poses",
                "{seq}/truth.csv",
                "--stride",
                "0",
                "-o",
                "{tmp}/x.html",
            ],
            "--stride 0",
        ),
    ],
)
def test_cli_bad_input_is_one_line_error(
    argv: list[str], needle: str, synth_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    argv = [a.format(tmp=tmp_path, seq=synth_dir) for a in argv]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("mistool: error:") and needle in err and "\n" not in err
    assert not (tmp_path / "x.html").exists()


def test_export_html_is_standalone(sequence, tmp_path: Path) -> None:
    out = tmp_path / "replay.html"
    summary = export_html(sequence, out, max_frames=10)
    assert summary.frames == 10 and out.stat().st_size == summary.bytes
    html = out.read_text(encoding="utf-8")
    assert "window.__VISER_EMBED_DATA__=" in html
    # Offline: no script or stylesheet is fetched from elsewhere.
    assert '<script src="http' not in html and '<link rel="stylesheet" href="http' not in html
    with pytest.raises(MistoolError, match="--mode"):
        export_html(sequence, tmp_path / "y.html", mode="nonsense")
    assert not (tmp_path / "y.html").exists()


def test_export_html_jpeg_quality_reaches_the_images(sequence, tmp_path: Path) -> None:
    # The option used to set an attribute viser never reads: both files came out the same.
    # Frames 0, 10, 20, 30: the overlays show instruments (the first frames are nearly blank).
    def size(images: bool, quality: int) -> int:
        out = tmp_path / "x.html"
        return export_html(sequence, out, stride=10, images=images, jpeg_quality=quality).bytes

    base = size(False, 95)
    low, high = size(True, 5) - base, size(True, 95) - base
    assert 0 < low < 0.5 * high


def test_serve_reuses_the_tracked_table_until_the_sequence_changes(
    synth_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import shutil

    from mistool import background

    seq = tmp_path / "seq"
    shutil.copytree(synth_dir, seq)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    calls: list[Path] = []
    real = background.track_into

    def counting(spec, stop=None):
        calls.append(spec.sequence)
        return real(spec, stop)

    monkeypatch.setattr(background, "track_into", counting)
    first = load_sequence(seq, cache=True)
    again = load_sequence(seq, cache=True)
    assert len(calls) == 1, "the unchanged sequence was tracked twice"
    np.testing.assert_allclose(
        again.replay.modes["metric"].centre, first.replay.modes["metric"].centre, atol=1e-9
    )
    assert (tmp_path / "cache" / "mistool" / "tables").is_dir()
    assert not (seq / ".mistool").exists() and len(list(seq.iterdir())) == len(
        list(synth_dir.iterdir())
    ), "the sequence folder was written to"
    frame = sorted(seq.glob("*.png"))[3]
    frame.write_bytes(frame.read_bytes())  # same content, new modification time
    os.utime(frame, ns=(time.time_ns(), time.time_ns() + 10**9))
    load_sequence(seq, cache=True)
    assert len(calls) == 2, "a changed sequence must be tracked again"
    toml = seq / "mistool.toml"
    toml.write_text("min_area_px = 30\n" + toml.read_text())
    load_sequence(seq, cache=True)
    assert len(calls) == 3, "a changed config must be tracked again"
    load_sequence(seq, cache=False)
    assert len(calls) == 3  # no cache: tracked by api.run, nothing stored


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_serve_stops_cleanly_on_ctrl_c(sig: str, synth_dir: Path) -> None:
    import signal
    import subprocess
    import sys

    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from mistool.cli import main; sys.exit(main(sys.argv[1:]))",
            "serve",
            str(synth_dir),
            "--poses",
            str(synth_dir / "truth.csv"),
            "--port",
            "0",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        lines = [proc.stdout.readline() for _ in range(2)]
        assert "http://" in lines[1], lines
        proc.send_signal(getattr(signal, sig))
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped" in err and "Traceback" not in err


def test_mask_video_overlay_reads_frames_at_random(tmp_path: Path) -> None:
    from mistool.synth import synthesize

    out = tmp_path / "vid"
    synthesize(out, frames=12, instruments=1, seed=5, video="mjpg")
    seq = load_sequence(out / "masks.avi", poses=out / "truth.csv")
    assert seq.frames.has_masks and seq.frames.num_mask_frames == 12
    renderer = OverlayRenderer(seq.replay, seq.frames)
    shaft = np.array(seq.replay.part_colour(0, "shaft"))
    for k in (9, 2, 10):  # seeks backwards and forwards
        img = renderer.render(k, opacity=1.0, boxes=False).reshape(-1, 3).astype(int)
        visible = seq.replay.modes[seq.replay.default_mode].visible[k, 0, 0]
        assert ((np.abs(img - shaft).sum(axis=1) == 0).sum() > 50) == bool(visible), k
    seq.frames.close()


def test_single_frame_single_part_without_masks() -> None:
    from mistool.viewer import LoadedSequence

    table = _metric_table()
    one = table[(np.asarray(table["frame"]) == 0) & (np.asarray(table["part"]) == "shaft")]
    replay = build_replay(one, Config(camera=CAMERA))
    assert replay.num_frames == 1 and replay.parts == ("shaft",)
    viewer = ReplayViewer(
        LoadedSequence(replay=replay, frames=FrameStore(None, Config()), name="one"), port=0
    )
    try:
        assert viewer.timeline.wait_shown(0)
        viewer.timeline.step(1)  # loops onto itself
        viewer.timeline.set_playing(True)
        time.sleep(0.2)
        viewer.timeline.set_playing(False)
        viewer._set_mode("metric")
        assert viewer.overlays is None and not viewer.timeline.draw_errors
        assert viewer.scene.parts[0, 0].visible
    finally:
        viewer.close()


def test_plot_cursor_marks_the_current_time(sequence) -> None:
    viewer = ReplayViewer(sequence, port=0)
    try:
        replay = sequence.replay
        k = _busy_frame(replay)
        viewer.timeline.seek(k)
        assert viewer.timeline.wait_shown(k)
        for kind, chart in viewer.plots.charts.items():
            x, *ys, cursor = chart.data
            at = np.flatnonzero(np.isfinite(cursor))
            assert len(at) == 2 and np.allclose(x[at], k / replay.fps), kind
            assert np.all(np.diff(x) >= 0) and all(len(y) == len(x) for y in ys)
            assert len(x) <= 300 + 2
        # The position plot shows the selected part's series (metric: its end in mm).
        i = replay.instruments.index(viewer.plots.instrument.value)
        p = replay.parts.index(viewer.plots.part.value)
        x, *ys, _ = viewer.plots.charts["position"].data
        j = int(np.flatnonzero(np.isclose(x, k / replay.fps))[0])
        np.testing.assert_allclose(
            [y[j] for y in ys], replay.series["metric/position"][k, i, p], rtol=1e-9
        )
    finally:
        viewer.close()


@pytest.mark.parametrize(
    "shape, aspect, out_shape",
    [
        ((576, 720), 1280 / 800, (576, 922)),  # wider window: black bars left and right
        ((576, 720), 0.5, (1440, 720)),  # taller window: bars above and below
        ((576, 720), 1.25, (576, 720)),  # same aspect: unchanged
    ],
)
def test_endoscope_backdrop_keeps_a_centred_image_centred(shape, aspect, out_shape) -> None:
    from mistool.viewer.app import endoscope_backdrop

    h, w = shape
    img = np.full((*shape, 3), 200, np.uint8)
    out, fov = endoscope_backdrop(img, aspect, (600.0, 600.0, (w - 1) / 2, (h - 1) / 2), (w, h))
    assert out.shape[:2] == out_shape
    ys, xs = np.nonzero(out[..., 0])
    assert (ys.min() + ys.max()) / 2 == pytest.approx((out_shape[0] - 1) / 2, abs=1)
    assert (xs.min() + xs.max()) / 2 == pytest.approx((out_shape[1] - 1) / 2, abs=1)
    assert (out > 0).sum() == img.size
    # The camera's vertical field of view spans the padded height.
    assert fov == pytest.approx(2 * np.arctan(out_shape[0] / 2 / 600.0))


@pytest.mark.parametrize("aspect", [0.6, 1.25, 1.9])
def test_endoscope_backdrop_puts_rays_where_the_camera_sees_them(aspect) -> None:
    """Off-centre principal point, fx != fy, an overlay at display size: every image
    point lands, in the window, where a centred pinhole with the returned vertical field
    of view projects its ray (what viser's camera does)."""
    from mistool.viewer.app import endoscope_backdrop

    W, H = 720, 576  # the image the intrinsics refer to
    fx, fy, cx, cy = 610.0, 590.0, 330.0, 300.0
    small = (288, 360)  # the overlay's (h, w)
    img = np.zeros((*small, 3), np.uint8)
    pts = np.array([[40.0, 30.0], [600.0, 100.0], [330.0, 300.0], [700.0, 560.0]])  # (u, v)
    for u, v in pts:  # mark them in the overlay's pixels
        img[int((v + 0.5) * small[0] / H), int((u + 0.5) * small[1] / W)] = 255
    out, fov = endoscope_backdrop(img, aspect, (fx, fy, cx, cy), (W, H))
    assert out.shape[1] / out.shape[0] == pytest.approx(aspect, rel=0.01)
    # Window coordinates in [-1, 1] (x right, y down) of each ray, for that camera.
    t = np.tan(fov / 2)
    rays = np.stack([(pts[:, 0] - cx) / fx, (pts[:, 1] - cy) / fy], axis=1)
    ndc = np.stack([rays[:, 0] / (t * aspect), rays[:, 1] / t], axis=1)
    ys, xs = np.nonzero(out[..., 0] > 60)
    found = np.stack([(xs + 0.5) / out.shape[1] * 2 - 1, (ys + 0.5) / out.shape[0] * 2 - 1], 1)
    for p in ndc:
        err = np.linalg.norm(found - p, axis=1).min() * out.shape[0] / 2  # in output px
        assert err < 1.5, (p, err)


def test_scene_extent_holds_both_ends_of_a_long_cylinder() -> None:
    """Camera presets frame whole tools: a 40-unit shaft centred at (10, 30, 0) along +x
    reaches x = -10 and x = 30, far beyond its centre (its centre alone gives 0..10)."""
    cfg = Config()
    replay = Replay(
        cfg, num_frames=1, image_wh=(720, 576), instruments=("a",), parts=config_parts(cfg)
    )
    g = replay.modes[replay.default_mode]
    g.visible[0] = False
    g.visible[0, 0, 0] = True
    g.centre[0, 0, 0] = (10.0, 30.0, 0.0)
    g.wxyz[0, 0, 0] = quat_z_to(np.array([1.0, 0.0, 0.0]))
    g.length[0, 0, 0] = 40.0
    lo, hi = scene_extent(replay, replay.default_mode)
    assert lo[0] < -9.0 and hi[0] > 29.0  # 2nd/98th percentiles of the two ends
    np.testing.assert_allclose([lo[1], hi[1], lo[2], hi[2]], [0.0, 30.0, 0.0, 0.0], atol=1e-9)


def test_scrubbing_a_source_video_decodes_ahead_instead_of_seeking(tmp_path: Path) -> None:
    """Frames asked out of order set a worker decoding in order around them: the frames
    near a scrubbed one then come without a seek each (a seek decodes from a keyframe);
    frames asked in order (playback) start no worker; close() stops it."""
    video = tmp_path / "video.avi"
    n, size = 120, (64, 48)
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, size)
    for k in range(n):  # each frame's brightness says its index
        writer.write(np.full((size[1], size[0], 3), 2 * k, np.uint8))
    writer.release()
    small = (32, 24)
    frames = FrameStore(None, Config(source=video))
    try:
        for k in range(5):  # in order: no worker
            frames.source_at(k, small)
        assert frames._ahead is None or frames._ahead._thread is None
        reader = frames._source_video
        assert reader is not None and reader.seeks == 0
        first = frames.source_at(60, small)
        assert first is not None and first.shape == (24, 32, 3) and reader.seeks == 1
        ahead = frames._ahead
        assert ahead is not None
        end = time.monotonic() + 30
        while time.monotonic() < end and not all(ahead.get(k) is not None for k in range(30, n)):
            time.sleep(0.02)
        assert all(ahead.get(k) is not None for k in range(30, n)), "not decoded ahead"
        for k in np.random.default_rng(1).permutation(np.arange(30, n))[:40]:
            img = frames.source_at(int(k), small)
            assert img is not None and abs(float(img.mean()) - 2 * k) < 3, k
        assert reader.seeks == 1, "scrubbing near a decoded frame seeked again"
    finally:
        frames.close()
    assert ahead._thread is not None and not ahead._thread.is_alive()


def test_the_viewer_reads_frames_without_waiting_for_the_compiled_decoder() -> None:
    """The frame size probe (before the URL and the tracking process's fork) decodes with
    OpenCV, imports no numba and starts no thread; the first frame read starts loading
    the compiled PNG decoder in a thread and decodes with OpenCV meanwhile; every read
    gives the labels the reader gives. In a fresh interpreter (numba not loaded yet)."""
    import subprocess
    import sys

    code = """
import sys, threading, time
import numpy as np
from mistool.config import load_config
from mistool.resources import sample_masks_dir
from mistool.sequence import read_label_image
from mistool.viewer.overlay import FrameStore
seq = sample_masks_dir()
store = FrameStore(seq, load_config(seq))
threads = threading.active_count()
shape = store.mask_shape()
assert "numba" not in sys.modules and threading.active_count() == threads, "probe"
first = store.labels(0)
assert not store._gate._loaded.is_set()
deadline = time.time() + 120
while not store._gate._loaded.is_set() and time.time() < deadline:
    time.sleep(0.05)
assert store._gate._loaded.is_set() and "mistool.kernels.png" in sys.modules
later = store.labels(1)
names = sorted(p for p in seq.iterdir() if p.suffix == ".png")
for got, path in ((first, names[0]), (later, names[1])):
    assert np.array_equal(got, read_label_image(path)), path
print(shape == first.shape)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "True"
