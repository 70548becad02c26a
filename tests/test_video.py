"""export-video: decode the written file and check frame count, size and content."""

from __future__ import annotations

from pathlib import Path

import av
import cv2
import numpy as np
import pytest

from mistool.annotations import Bookmark, save_annotations
from mistool.cli import main
from mistool.video import BAR_HEIGHT, PANEL_HEIGHT, h264_available, instrument_bgr

FRAMES, FPS = 40, 10.0


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from mistool.synth import synthesize
    from mistool.synth.writer import SceneOptions

    out = tmp_path_factory.mktemp("video") / "seq"
    scene = SceneOptions(width=360, height=288, focal_px=300.0)
    synthesize(out, frames=FRAMES, instruments=2, seed=3, fps=FPS, scene=scene)
    return out


def decode(path: Path) -> tuple[str, list[np.ndarray]]:
    with av.open(str(path)) as c:
        name = c.streams.video[0].codec_context.name
        return name, [f.to_ndarray(format="bgr24") for f in c.decode(video=0)]


def colour_pixels(img: np.ndarray, bgr: tuple[int, int, int], tol: int = 40) -> int:
    return int(np.all(np.abs(img.astype(int) - bgr) < tol, axis=2).sum())


def test_video_frames_size_and_content(sequence: Path, tmp_path: Path) -> None:
    marks = tmp_path / "marks.json"
    save_annotations(marks, [Bookmark(10, "grasp", "event")])
    out = tmp_path / "replay.mp4"
    args = ["export-video", str(sequence), "-o", str(out), "-q"]
    assert main([*args, "--poses", str(sequence / "truth.csv"), "--annotations", str(marks)]) == 0
    codec, frames = decode(out)
    assert codec == ("h264" if h264_available() else "mpeg4")
    assert len(frames) == FRAMES
    panel_w = 2 * round(360 * PANEL_HEIGHT / 288 / 2)
    assert frames[0].shape == (PANEL_HEIGHT + BAR_HEIGHT, 2 * panel_w, 3)
    with av.open(str(out)) as c:
        assert float(c.streams.video[0].average_rate) == FPS
    busy = [k for k in range(FRAMES) if colour_pixels(frames[k], instrument_bgr(0)) > 200]
    assert len(busy) > FRAMES // 2  # the first tool is drawn in its colour
    for k in busy[:3]:
        left, right = frames[k][:PANEL_HEIGHT, :panel_w], frames[k][:PANEL_HEIGHT, panel_w:]
        assert colour_pixels(left, instrument_bgr(0)) > 50  # 3D view
        assert colour_pixels(right, instrument_bgr(0)) > 50  # mask overlay
    # the caption: the bookmark's yellow box from frame 10 for 2 s (20 frames), not before
    caption = [colour_pixels(f[PANEL_HEIGHT:, -200:], (0, 190, 255)) > 300 for f in frames]
    assert caption == [10 <= k <= 30 for k in range(FRAMES)]
    # the frame counter changes every frame
    counter = [f[PANEL_HEIGHT : PANEL_HEIGHT + 30, :300].astype(int) for f in frames[:3]]
    assert np.abs(counter[1] - counter[0]).sum() > 0 and np.abs(counter[2] - counter[1]).sum() > 0


def test_mp4v_fallback_and_max_frames(sequence: Path, tmp_path: Path) -> None:
    out = tmp_path / "replay.mp4"
    args = ["export-video", str(sequence), "-o", str(out), "-q", "--codec", "mp4v"]
    assert main([*args, "--poses", str(sequence / "truth.csv"), "--max-frames", "7"]) == 0
    cap = cv2.VideoCapture(str(out))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    assert n == 7
    assert decode(out)[0] == "mpeg4"


def test_bad_input_leaves_nothing(sequence: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "missing" / "replay.mp4"
    poses = ["--poses", str(sequence / "truth.csv"), "-q"]
    assert main(["export-video", str(sequence), "-o", str(out), *poses]) == 1
    assert "does not exist" in capsys.readouterr().err
    table_only = tmp_path / "t.csv"
    table_only.write_text((sequence / "truth.csv").read_text())
    assert main(["export-video", str(table_only), "-o", str(tmp_path / "x.mp4"), "-q"]) == 1
    assert "needs the mask sequence" in capsys.readouterr().err
    assert (
        main(
            [
                "export-video",
                str(sequence),
                "-o",
                str(tmp_path / "y.mp4"),
                *poses,
                "--max-frames",
                "0",
            ]
        )
        == 1
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.csv"]


def test_never_writes_over_an_input(sequence: Path, tmp_path: Path, capsys) -> None:
    first = sorted(sequence.glob("*.png"))[0]
    before = first.read_bytes()
    poses = ["--poses", str(sequence / "truth.csv"), "-q"]
    assert main(["export-video", str(sequence), "-o", str(first), *poses]) == 1
    assert capsys.readouterr().err.startswith("mistool: error: ")
    assert first.read_bytes() == before
