"""``mistool track`` in-process: outputs, option overrides, warnings, and a table of bad
inputs that must each give one error line and no output file."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool.cli import main
from mistool.model import COLUMN_NAMES, CONTRACT_COLUMNS

H, W = 96, 128


def _frame(shift: int = 0, *, shaft: int = 160, clasper: int = 70) -> np.ndarray:
    """One instrument: an axis-aligned shaft with a clasper at its right end."""
    img = np.zeros((H, W), np.uint8)
    img[40:52, 10 + shift : 70 + shift] = shaft
    img[38:54, 70 + shift : 86 + shift] = clasper
    return img


def _folder(
    root: Path, frames: list[np.ndarray], toml: str | None = None, name: str = "seq"
) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    for i, img in enumerate(frames):
        assert cv2.imwrite(str(folder / f"frame{i}.png"), img)
    if toml is not None:
        (folder / "mistool.toml").write_text(toml, encoding="utf-8")
    return folder


def _read(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as f:
        return list(csv.DictReader(f))


def test_track_writes_every_column(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    seq = _folder(tmp_path, [_frame(i) for i in range(12)], "fps = 10.0\n")
    out = tmp_path / "out.csv"
    assert main(["track", str(seq), "-o", str(out)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("mistool: 12 frame(s), 1 instrument(s)")
    assert "frames/s" in err[0] and str(out) in err[0]
    header = out.read_text(encoding="utf-8").splitlines()[0].split(",")
    assert tuple(header[: len(COLUMN_NAMES)]) == COLUMN_NAMES
    assert set(CONTRACT_COLUMNS) <= set(header)
    rows = _read(out)
    assert len(rows) == 24  # 12 frames x (shaft, clasper)
    assert [r["part"] for r in rows[:2]] == ["shaft", "clasper"]
    shaft = [r for r in rows if r["part"] == "shaft"]
    assert [float(r["time_s"]) for r in shaft[:3]] == [0.0, 0.1, 0.2]  # frame / fps
    assert float(shaft[0]["cx_px"]) == pytest.approx(39.5, abs=0.5)
    assert shaft[0]["dx_px"] == "" and float(shaft[1]["dx_px"]) == pytest.approx(1.0, abs=0.5)
    assert shaft[0]["end_x_mm"] == ""  # no camera: metric cells empty, never 0


def test_default_output_goes_to_the_current_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    seq = _folder(tmp_path / "data", [_frame(), _frame(1)], name="my seq é")
    before = sorted(os.listdir(seq))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main(["track", str(seq), "--quiet"]) == 0
    assert capsys.readouterr().err == ""  # --quiet: nothing on stderr
    assert (work / "my seq é_motion.csv").is_file()
    assert sorted(os.listdir(seq)) == before  # the input folder is never written to
    monkeypatch.chdir(seq)  # run from inside the input folder: output goes beside it
    assert main(["track", ".", "--quiet"]) == 0
    assert sorted(os.listdir(seq)) == before
    assert (seq.parent / "my seq é_motion.csv").is_file()


def test_options_override_the_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    frames = [_frame(i, shaft=10, clasper=30) for i in range(3)]
    seq = _folder(tmp_path, frames, 'fps = 10.0\nlabels = "endovis15"\n')
    out = tmp_path / "o.csv"
    assert (
        main(
            [
                "track",
                str(seq),
                "-o",
                str(out),
                "--fps",
                "2",
                "--labels",
                "endovis17",
                "--workers",
                "1",
                "--smoothing",
                "none",
                "--no-metric",
            ]
        )
        == 0
    )
    rows = _read(out)
    assert {r["part"] for r in rows} == {"shaft", "clasper"}
    assert [float(r["time_s"]) for r in rows if r["part"] == "shaft"] == [0.0, 0.5, 1.0]


def test_stdout_output(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    seq = _folder(tmp_path, [_frame()])
    assert main(["track", str(seq), "-o", "-"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[0].startswith("frame,time_s,instrument,part,") and len(lines) == 3
    assert "-> stdout" in captured.err


def test_unknown_values_warn_once(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    frames = []
    for i in range(5):
        img = _frame(i)
        img[0:10, 0:10] = 99 + (i % 2)  # values the config does not know
        frames.append(img)
    seq = _folder(tmp_path, frames)
    out = tmp_path / "o.csv"
    assert main(["track", str(seq), "-o", str(out)]) == 0
    warn = [x for x in capsys.readouterr().err.splitlines() if x.startswith("mistool: warn")]
    assert len(warn) == 1 and "99, 100" in warn[0]
    assert len(_read(out)) == 10


def _specks_and_pixels(root: Path) -> Path:
    frames = [_frame(i) for i in range(3)]
    frames[1][90, 5] = 160  # a one-pixel speck (below min_area_px)
    frames[2][5:8, 100:103] = 70
    return _folder(root, frames, "min_area_px = 0\n")


NOT_ERRORS: list[tuple[str, Callable[[Path], Path], int]] = [
    (
        "part absent in some frames",
        lambda r: _folder(r, [_frame(), _frame(1, clasper=0), _frame(2)]),
        5,
    ),
    ("tool absent in every frame", lambda r: _folder(r, [np.zeros((H, W), np.uint8)] * 3), 0),
    ("single frame", lambda r: _folder(r, [_frame()]), 2),
    ("stray specks", lambda r: _folder(r, [_frame() | _speck(i) for i in range(2)]), 4),
    ("one-pixel parts and min_area 0", _specks_and_pixels, 8),
    ("shaft hugging the border", lambda r: _folder(r, [_border(i) for i in range(3)]), 3),
    ("odd folder name", lambda r: _folder(r, [_frame()], name="dossier été (1) #2"), 2),
]


def _speck(i: int) -> np.ndarray:
    img = np.zeros((H, W), np.uint8)
    img[80 + i, 100] = 160
    return img


def _border(i: int) -> np.ndarray:
    img = np.zeros((H, W), np.uint8)
    img[0 : 10 + i, 0:W] = 160
    return img


@pytest.mark.parametrize("case, make, rows", NOT_ERRORS, ids=[c[0] for c in NOT_ERRORS])
def test_not_errors(
    tmp_path: Path,
    capsys: pytest.CaptureFixture,
    case: str,
    make: Callable[[Path], Path],
    rows: int,
) -> None:
    seq = make(tmp_path)
    out = tmp_path / "o.csv"
    assert main(["track", str(seq), "-o", str(out)]) == 0, capsys.readouterr().err
    got = _read(out)
    assert len(got) == rows
    if "one-pixel" in case:
        assert min(float(r["area_px"]) for r in got) == 1.0
    assert out.read_text().splitlines()[0].startswith("frame,time_s,instrument,part,")


def _png_bytes(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


def _bad_folder(root: Path, files: dict[str, bytes | str]) -> Path:
    folder = root / "bad seq"
    folder.mkdir()
    for name, data in files.items():
        path = folder / name
        if isinstance(data, str):
            path.write_text(data, encoding="utf-8")
        else:
            path.write_bytes(data)
    return folder


_OK = _png_bytes(_frame())
_TRUNC = _png_bytes(_frame())[:60]
_CAM = "[camera]\nfx = {fx}\nfy = 500.0\ncx = 64.0\ncy = 48.0\n"

BAD_INPUTS: list[tuple[str, Callable[[Path], list[str]], str]] = [
    ("missing path", lambda r: [str(r / "nope")], "nope: no such file or folder"),
    ("empty folder", lambda r: [str(_bad_folder(r, {}))], "no label images"),
    ("only non-images", lambda r: [str(_bad_folder(r, {"a.txt": "x"}))], "no label images"),
    (
        "corrupt image",
        lambda r: [str(_bad_folder(r, {"0.png": _OK, "1.png": b"\x89PNG\r\n" + bytes(200)}))],
        "1.png: cannot decode",
    ),
    (
        "truncated image",
        lambda r: [str(_bad_folder(r, {"0.png": _OK, "1.png": _TRUNC}))],
        "1.png: cannot decode",
    ),
    (
        "text file named .png",
        lambda r: [str(_bad_folder(r, {"0.png": "hello"}))],
        "0.png: cannot decode",
    ),
    (
        "frame size changes",
        lambda r: [
            str(_bad_folder(r, {"0.png": _OK, "1.png": _png_bytes(np.zeros((H + 1, W), np.uint8))}))
        ],
        "1.png: frame size changed",
    ),
    (
        "toml syntax",
        lambda r: [str(_bad_folder(r, {"0.png": _OK, "mistool.toml": "fps ="}))],
        "mistool.toml: invalid TOML",
    ),
    (
        "toml unknown key",
        lambda r: [str(_bad_folder(r, {"0.png": _OK, "mistool.toml": "speed = 3"}))],
        "mistool.toml: unknown key(s) speed",
    ),
    (
        "toml wrong type",
        lambda r: [str(_bad_folder(r, {"0.png": _OK, "mistool.toml": 'fps = "x"'}))],
        "fps must be a number",
    ),
    (
        "toml reversed range",
        lambda r: [
            str(_bad_folder(r, {"0.png": _OK, "mistool.toml": "[parts]\nshaft = [170, 150]"}))
        ],
        "reversed range",
    ),
    (
        "toml focal <= 0",
        lambda r: [str(_bad_folder(r, {"0.png": _OK, "mistool.toml": _CAM.format(fx=0)}))],
        "camera.fx must be > 0",
    ),
    (
        "unreadable video",
        lambda r: [str(_bad_folder(r, {"Segmentation.avi": b"RIFF" * 50}) / "Segmentation.avi")],
        "cannot read as a video",
    ),
    (
        "not a sequence",
        lambda r: [str(_bad_folder(r, {"a.txt": "x"}) / "a.txt")],
        "not a folder of label images or a mask video",
    ),
    (
        "bad --fps",
        lambda r: [str(_bad_folder(r, {"0.png": _OK})), "--fps", "0"],
        "--fps must be a number in",
    ),
    (
        "bad --min-area",
        lambda r: [str(_bad_folder(r, {"0.png": _OK})), "--min-area", "-3"],
        "--min-area must be >= 0",
    ),
    (
        "missing output folder",
        lambda r: [str(_bad_folder(r, {"0.png": _OK})), "-o", str(r / "no" / "x.csv")],
        "does not exist",
    ),
    (
        "output is a folder",
        lambda r: [str(_bad_folder(r, {"0.png": _OK})), "-o", str(r / "bad seq")],
        "is a folder",
    ),
]


@pytest.mark.parametrize("case, make_args, message", BAD_INPUTS, ids=[c[0] for c in BAD_INPUTS])
def test_bad_input(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture,
    case: str,
    make_args: Callable[[Path], list[str]],
    message: str,
) -> None:
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    args = make_args(tmp_path)
    if "-o" not in args:
        args += ["-o", str(work / "out.csv")]
    code = main(["track", *args])
    err = capsys.readouterr().err
    assert code != 0
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("mistool: error: ") and message in lines[0]
    assert "Traceback" not in err
    assert os.listdir(work) == []  # no output, no temporary file


_MAIN = "import sys; from mistool.cli import main; sys.exit(main())"


def test_corrupt_image_stderr_is_one_line_in_a_real_process(tmp_path: Path) -> None:
    """OpenCV's own C-level warnings must not reach stderr (capsys cannot see them)."""
    seq = _bad_folder(tmp_path, {"0.png": _OK, "1.png": _TRUNC})
    proc = subprocess.run(
        [sys.executable, "-c", _MAIN, "track", str(seq), "-o", str(tmp_path / "o.csv")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1
    assert proc.stderr.splitlines() == [
        f"mistool: error: {seq / '1.png'}: cannot decode as an image (corrupt, truncated or "
        "not an image file)"
    ]
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize(
    "argv, needles",
    [
        (["--help"], ["track", "mistool.toml", "COMMAND --help"]),
        (
            ["track", "--help"],
            [
                "mistool.toml",
                "frame2.png before",
                "cx_px",
                "examples:",
                "[camera]",
                "_motion.csv",
                "--smoothing",
                "--workers",
            ],
        ),
    ],
)
def test_help_explains(argv: list[str], needles: list[str], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 0
    text = capsys.readouterr().out
    for needle in needles:
        assert needle in text
