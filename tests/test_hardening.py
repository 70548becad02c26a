"""Issue 12, case by case: outputs never replace inputs or non-regular files, resources
are bounded before work, every failure is one escaped line, odd input is said, and the
viewer answers its own page only (real HTTP and websocket clients)."""

from __future__ import annotations

import errno
import http.client
import os
import re
import socket
import stat
import struct
import subprocess
import sys
import threading
import time
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool import sequence as seqmod
from mistool.cli import main, printable, quiet_native_stderr
from mistool.config import MAX_CONFIG_BYTES, config_from_dict, load_config
from mistool.errors import ConfigError, InputPathError, InputWarning, MaskFormatError, TableError
from mistool.export import atomic_write, check_output, check_table_limits, read_csv
from mistool.model import TrackTable

H, W = 96, 128
ROOT = Path(__file__).resolve().parents[1]
CAMERA = "[camera]\nfx = 580.0\nfy = 580.0\ncx = 64.0\ncy = 48.0\n"


def _frame(shift: int = 0) -> np.ndarray:
    img = np.zeros((H, W), np.uint8)
    img[40:52, 10 + shift : 70 + shift] = 160
    img[38:54, 70 + shift : 86 + shift] = 70
    return img


def _seq(root: Path, n: int = 3, toml: str | None = "fps = 25.0\n", name: str = "seq") -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    for i in range(n):
        assert cv2.imwrite(str(folder / f"{i:06d}.png"), _frame(i))
    if toml is not None:
        (folder / "mistool.toml").write_text(toml, encoding="utf-8")
    return folder


def _snapshot(folder: Path) -> dict[str, tuple[int, int, bytes | str]]:
    out = {}
    for p in sorted(folder.rglob("*")):
        st = p.lstat()
        body: bytes | str = b""
        if stat.S_ISREG(st.st_mode):
            body = p.read_bytes()
        elif stat.S_ISLNK(st.st_mode):
            body = os.readlink(p)
        out[str(p)] = (stat.S_IFMT(st.st_mode), stat.S_IMODE(st.st_mode), body)
    return out


def _one_error(capsys: pytest.CaptureFixture, code: int, *needles: str) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if not ln.startswith("mistool: warning:")]
    assert code == 1, err
    assert len(lines) == 1 and lines[0].startswith("mistool: error: "), err
    assert "internal error" not in lines[0] and "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def _png(w: int, h: int, idat: bytes = b"\0" * 16) -> bytes:
    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = struct.pack(">I", zlib.crc32(kind + body))
        return struct.pack(">I", len(body)) + kind + body + crc

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(idat))
        + chunk(b"IEND", b"")
    )


# --- outputs ---------------------------------------------------------------------------


def _link(seq: Path, tmp: Path) -> Path:
    (tmp / "link.csv").symlink_to(seq / "000000.png")
    return tmp / "link.csv"


def _hard(seq: Path, tmp: Path) -> Path:
    os.link(seq / "000000.png", tmp / "hard.csv")
    return tmp / "hard.csv"


@pytest.mark.parametrize(
    "make_out",
    [
        pytest.param(lambda seq, tmp: seq / "000001.png", id="a frame"),
        pytest.param(lambda seq, tmp: seq / "mistool.toml", id="mistool.toml"),
        pytest.param(_link, id="symlink to a frame"),
        pytest.param(_hard, id="hard link to a frame"),
        pytest.param(lambda seq, tmp: seq, id="the sequence folder"),
    ],
)
def test_track_refuses_an_output_that_is_an_input(
    tmp_path: Path, capsys: pytest.CaptureFixture, make_out
) -> None:
    seq = _seq(tmp_path)
    out = make_out(seq, tmp_path)
    before = _snapshot(tmp_path)
    code = main(["track", str(seq), "-o", str(out), "-q"])
    _one_error(capsys, code, str(out))
    assert _snapshot(tmp_path) == before


def test_track_refuses_the_source_video_as_output(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = _seq(tmp_path, toml='source = "../video.avi"\n')
    (tmp_path / "video.avi").write_bytes(b"not really a video")
    before = _snapshot(tmp_path)
    code = main(["track", str(seq), "-o", str(tmp_path / "video.avi"), "-q"])
    _one_error(capsys, code, "is an input", "video.avi")
    assert _snapshot(tmp_path) == before


CALIBRATION = (
    "image_width: 128\nimage_height: 96\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
    "  data: [500, 0, 64, 0, 500, 48, 0, 0, 1]\n"
)


def test_track_refuses_a_link_to_the_calibration_file(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = _seq(tmp_path)
    (tmp_path / "camera.yaml").write_text(CALIBRATION)
    (tmp_path / "out.csv").symlink_to(tmp_path / "camera.yaml")
    before = _snapshot(tmp_path)
    args = ["--calibration", str(tmp_path / "camera.yaml"), "-o", str(tmp_path / "out.csv")]
    code = main(["track", str(seq), *args, "-q"])
    _one_error(capsys, code, "is an input", "camera.yaml")
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("command", ["export-html", "report", "skill"])
def test_table_commands_refuse_their_input_table_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture, command: str
) -> None:
    seq = _seq(tmp_path)
    table = tmp_path / "t.csv"
    assert main(["track", str(seq), "-o", str(table), "-q"]) == 0
    link = tmp_path / "out.html"
    link.symlink_to(table)
    argv = {
        "export-html": ["export-html", str(seq), "--poses", str(table), "-o", str(link)],
        "report": ["report", str(table), "-o", str(link)],
        "skill": ["skill", str(table), "-o", str(table)],
    }[command]
    capsys.readouterr()
    before = _snapshot(tmp_path)
    _one_error(capsys, main([*argv, "-q"]), "is an input")
    assert _snapshot(tmp_path) == before


def test_export_html_refuses_a_frame_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mistool.viewer as viewer

    seq = _seq(tmp_path)
    monkeypatch.setattr(viewer, "load_sequence", lambda *a, **k: pytest.fail("did the work"))
    before = _snapshot(tmp_path)
    code = main(["export-html", str(seq), "-o", str(seq / "000001.png"), "-q"])
    _one_error(capsys, code, "is an input")
    assert _snapshot(tmp_path) == before
    code = main(["export-html", str(seq), "-o", str(tmp_path / "nope" / "r.html"), "-q"])
    _one_error(capsys, code, "does not exist")


def _fifo(tmp: Path) -> Path:
    os.mkfifo(tmp / "out.csv")
    return tmp / "out.csv"


def _socket_file(tmp: Path) -> Path:
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(tmp / "out.csv"))
    s.close()
    return tmp / "out.csv"


@pytest.mark.parametrize(
    ("make_out", "kind"),
    [(_fifo, "FIFO"), (_socket_file, "socket"), (lambda tmp: tmp, "folder")],
    ids=["FIFO", "socket", "folder"],
)
def test_track_refuses_non_regular_outputs(
    tmp_path: Path, capsys: pytest.CaptureFixture, make_out, kind: str
) -> None:
    seq = _seq(tmp_path)
    out = make_out(tmp_path)
    before = _snapshot(tmp_path)
    code = main(["track", str(seq), "-o", str(out), "-q"])
    _one_error(capsys, code, kind)
    assert _snapshot(tmp_path) == before


def test_devices_and_stdout_links_are_never_replaced() -> None:
    """/dev/null (a device) and /dev/stdout (a link to a pipe/tty/file descriptor) are
    refused by the check every writer runs first; nothing is opened."""
    with pytest.raises(InputPathError, match="character device"):
        check_output("/dev/null")
    with pytest.raises(InputPathError, match="character device"):
        with atomic_write("/dev/null") as f:
            f.write("x")
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def test_symlink_loop_as_output_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "a.csv").symlink_to(tmp_path / "b.csv")
    (tmp_path / "b.csv").symlink_to(tmp_path / "a.csv")
    with pytest.raises(InputPathError, match="symlink loop"):
        check_output(tmp_path / "a.csv")


def test_an_output_named_by_an_inputs_link_is_refused_whether_or_not_it_exists(
    tmp_path: Path,
) -> None:
    """check_output compares inodes of inputs that exist and resolves only those that
    cannot be stat'ed: an input that is a dangling link to the output's name, a link or
    a hard link to an existing output, all refused; an unrelated input, and a link to
    another file, are not."""
    out, other = tmp_path / "out.csv", tmp_path / "other.csv"
    other.write_text("x\n")
    dangling = tmp_path / "dangling.png"
    dangling.symlink_to(out)  # names the output, which does not exist yet
    with pytest.raises(InputPathError, match="is an input"):
        check_output(out, [other, dangling])
    assert check_output(out, [other]) == out.resolve()
    out.write_text("old\n")
    link, hard = tmp_path / "link.png", tmp_path / "hard.png"
    link.symlink_to(out)
    os.link(out, hard)
    for source in (dangling, link, hard, out):
        with pytest.raises(InputPathError, match="is an input"):
            check_output(out, [other, source])
    for source in (link, hard, out):  # listed inputs: looked at once the output exists
        with pytest.raises(InputPathError, match="is an input"):
            check_output(out, [other], existing=[other, source])
    other_link = tmp_path / "other_link.png"
    other_link.symlink_to(other)
    assert check_output(out, [other, other_link, tmp_path / "gone.png"]) == out.resolve()
    assert out.read_text() == "old\n"


def test_listed_frames_are_told_apart_from_the_output_by_inode_links_by_stat(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A folder's listing (``os.DirEntry`` objects) given as ``existing``: a frame that is
    not a symlink is compared by the inode number that came with the listing (no
    ``stat``); a symlink or a hard link to the existing output is still refused."""
    out = tmp_path / "out.csv"
    out.write_text("old\n")
    seq = tmp_path / "seq"
    seq.mkdir()
    for i in range(5):
        (seq / f"{i:03d}.png").write_bytes(b"x")
    (seq / "005.png").symlink_to(out)
    os.link(out, seq / "006.png")
    entries = {e.name: e for e in os.scandir(seq)}
    plain = [entries[f"{i:03d}.png"] for i in range(5)]
    stated: list[str] = []
    real_stat = os.stat

    def counting_stat(path: object, *args: object, **kwargs: object) -> os.stat_result:
        if os.fspath(path).startswith(os.fspath(seq)):  # type: ignore[call-overload]
            stated.append(os.fspath(path))  # type: ignore[call-overload]
        return real_stat(path, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "stat", counting_stat)
    assert check_output(out, [], existing=plain) == out.resolve()
    assert stated == []
    for name in ("005.png", "006.png"):
        with pytest.raises(InputPathError, match="is an input"):
            check_output(out, [], existing=[*plain, entries[name]])
    monkeypatch.undo()
    assert out.read_text() == "old\n"


def test_existing_output_keeps_its_mode_and_new_ones_follow_the_umask(tmp_path: Path) -> None:
    old = tmp_path / "old.csv"
    old.write_text("old\n")
    os.chmod(old, 0o600)
    with atomic_write(old) as f:
        f.write("new\n")
    assert old.read_text() == "new\n" and stat.S_IMODE(old.stat().st_mode) == 0o600
    previous = os.umask(0o077)
    try:
        with atomic_write(tmp_path / "new.csv") as f:
            f.write("x\n")
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "new.csv").stat().st_mode) == 0o600


def test_writing_through_a_symlink_keeps_the_link(tmp_path: Path) -> None:
    (tmp_path / "real.csv").write_text("old\n")
    (tmp_path / "link.csv").symlink_to("real.csv")
    with atomic_write(tmp_path / "link.csv") as f:
        f.write("new\n")
    assert (tmp_path / "link.csv").is_symlink()
    assert (tmp_path / "real.csv").read_text() == "new\n"


def test_disk_full_is_one_line_and_keeps_the_old_output(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """ENOSPC simulated at fsync (the point a full disk surfaces for buffered writes);
    scripts/hostile_cases.py also runs it on a real 4 kB tmpfs when root."""
    seq = _seq(tmp_path)
    out = tmp_path / "out.csv"
    out.write_text("previous\n")

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)
    code = main(["track", str(seq), "-o", str(out), "-q"])
    _one_error(capsys, code, "No space left on device")
    assert out.read_text() == "previous\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv", "seq"]


def _start_cli(args: list[str], shell: str) -> subprocess.Popen:
    """``mistool ARGS`` (this checkout's code) in bash, with ``shell`` around it."""
    import shlex

    cmd = shlex.join(
        [sys.executable, "-P", "-c", "import sys; from mistool.cli import main; sys.exit(main())"]
        + args
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("MISTOOL_DEBUG", None)
    return subprocess.Popen(
        ["bash", "-c", shell.replace("{cmd}", cmd)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def test_dash_output_into_a_closed_pipe_or_closed_stdout_is_one_line(tmp_path: Path) -> None:
    """Real processes (both at once): the reader of the pipe exits before the table is
    written, and stdout closed from the start (checked before tracking)."""
    seq = _seq(tmp_path)
    args = ["track", str(seq), "-o", "-", "-q"]
    piped = _start_cli(args, "{cmd} | true; exit ${PIPESTATUS[0]}")
    closed = _start_cli(args, "{cmd} >&-")
    for proc, what in ((piped, "closed the pipe"), (closed, "standard output is closed")):
        _, err = proc.communicate(timeout=300)
        lines = err.splitlines()
        assert proc.returncode == 1, err
        assert len(lines) == 1 and lines[0].startswith("mistool: error: "), err
        assert what in lines[0]


def test_dash_output_writes_the_table_to_stdout(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = _seq(tmp_path)
    assert main(["track", str(seq), "-o", "-", "-q"]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("frame,") and out.count("\n") == 7 and err == ""


# --- resources ---------------------------------------------------------------------------


def test_pixel_limit_is_checked_from_the_header_before_decoding(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(_png(100_000, 100_000))
    assert len(bomb.read_bytes()) < 80  # the 74-byte PNG
    monkeypatch.setattr(cv2, "imdecode", lambda *a: pytest.fail("decoded"))
    monkeypatch.setattr(seqmod, "decode_png", lambda *a: pytest.fail("decoded"))
    with pytest.raises(MaskFormatError, match=r"100000x100000 .* more than the limit"):
        seqmod.read_label_image(bomb)
    bomb.write_bytes(_png(0, 0))
    with pytest.raises(MaskFormatError, match="0x0"):
        seqmod.read_label_image(bomb)


def test_pixel_limit_is_overridable_in_mistool_toml(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = _seq(tmp_path, toml="max_pixels = 1000\n")
    code = main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q"])
    _one_error(capsys, code, f"{W}x{H}", "max_pixels")
    (seq / "mistool.toml").write_text(f"max_pixels = {W * H}\n")
    assert main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q"]) == 0
    with pytest.raises(ConfigError, match="max_pixels"):
        config_from_dict({"max_pixels": 0})


@pytest.mark.parametrize("ext", [".jpg", ".bmp", ".pgm", ".png"])
def test_header_size_reads_common_formats(tmp_path: Path, ext: str) -> None:
    img = np.zeros((37, 53), np.uint8)
    assert cv2.imwrite(str(tmp_path / f"a{ext}"), img)
    assert seqmod.header_size((tmp_path / f"a{ext}").read_bytes()) == (53, 37)


def test_mask_video_frame_size_is_limited(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    video = tmp_path / "masks.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25, (W, H), False)
    for i in range(3):
        writer.write(_frame(i))
    writer.release()
    (tmp_path / "mistool.toml").write_text("max_pixels = 100\n")
    code = main(["track", str(video), "-o", str(tmp_path / "o.csv"), "-q"])
    _one_error(capsys, code, "masks.avi", "max_pixels")


def _table(frames: list[int]) -> TrackTable:
    n = len(frames)
    return TrackTable(
        {
            "frame": np.array(frames, np.int64),
            "instrument": ["1"] * n,
            "part": ["shaft"] * n,
        }
    )


def test_motion_table_frame_numbers_are_limited() -> None:
    check_table_limits(_table([0, 5, 1_000_000]), "t.csv")
    with pytest.raises(TableError, match="2000000000 is beyond the limit"):
        check_table_limits(_table([0, 2_000_000_000]), "t.csv")
    with pytest.raises(TableError, match="negative"):
        check_table_limits(_table([-1, 3]), "t.csv")


def test_viewer_refuses_a_table_with_frame_2e9(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = _seq(tmp_path)
    table = tmp_path / "t.csv"
    assert main(["track", str(seq), "-o", str(table), "-q"]) == 0
    lines = table.read_text().splitlines()
    lines[1] = "2000000000" + lines[1][lines[1].index(",") :]
    table.write_text("\n".join(lines) + "\n")
    code = main(["export-html", str(seq), "--poses", str(table), "-o", str(tmp_path / "r.html")])
    _one_error(capsys, code, "2000000000", "limit")
    lines[1] = "1e300" + lines[1][lines[1].index(",") :]
    table.write_text("\n".join(lines) + "\n")
    with pytest.raises(TableError, match="expected an integer"):
        read_csv(table)


def test_mistool_toml_read_is_bounded(tmp_path: Path) -> None:
    seq = _seq(tmp_path, toml=None)
    os.mkfifo(seq / "mistool.toml")  # would block forever if opened for a plain read
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config(seq)
    (seq / "mistool.toml").unlink()
    (seq / "mistool.toml").write_text("fps = 25.0\n" + "#" * MAX_CONFIG_BYTES)
    with pytest.raises(ConfigError, match="at most"):
        load_config(seq)
    (seq / "mistool.toml").unlink()
    (seq / "mistool.toml").symlink_to(tmp_path / "gone.toml")
    with pytest.raises(ConfigError, match="dangling symlink"):
        load_config(seq)
    (seq / "mistool.toml").unlink()
    (seq / "mistool.toml").symlink_to(seq / "mistool.toml")
    with pytest.raises(ConfigError, match="symlink loop"):
        load_config(seq)


# --- one line for every error -------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (b'fps = 25\nname = "\xff\xfe"\n', "not UTF-8"),
        (b"fps = " + b"[" * 5000 + b"]" * 5000 + b"\n", "nested too deeply"),
        (b'labels = ["endovis15"]\n', "is not a preset"),
        (b"labels = {a = 1}\n", "is not a preset"),
        (b"fps = 1e308\n", "fps must be a number in"),
        (b"fps = 1e-308\n", "fps must be a number in"),
        (b"shaft_diameter_mm = 1e308\n", "shaft_diameter_mm must be a number in"),
        (b"shaft_diameter_mm = 1e-308\n", "shaft_diameter_mm must be a number in"),
        (b"clasper_length_mm = 1e308\n", "clasper_length_mm must be a number in"),
        (b"[[instrument]]\nshaft = 160\nshaft_diameter_mm = 1e-308\n", "shaft_diameter_mm"),
        (CAMERA.replace("fx = 580.0", "fx = 1e308").encode(), "camera.fx"),
        (CAMERA.replace("fx = 580.0", "fx = 1e-308").encode(), "camera.fx"),
        (CAMERA.replace("cx = 64.0", "cx = 1e308").encode(), "camera.cx"),
        (b"[parts]\nshaft = [60, 80]\nclasper = 70\n", "overlap"),
        (
            b"[[instrument]]\nshaft = [100, 200]\nclasper = 70\n"
            b"[[instrument]]\nshaft = 160\nclasper = 30\n",
            "overlap",
        ),
    ],
)
def test_bad_mistool_toml_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, text: bytes, message: str
) -> None:
    seq = _seq(tmp_path, toml=None)
    (seq / "mistool.toml").write_bytes(text)
    before = _snapshot(tmp_path)
    code = main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q"])
    _one_error(capsys, code, "mistool.toml", message)
    assert _snapshot(tmp_path) == before


@pytest.mark.parametrize("fps", ["inf", "-inf", "nan", "1e308", "1e-308", "0"])
def test_fps_option_out_of_range_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, fps: str
) -> None:
    seq = _seq(tmp_path)
    code = main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q", f"--fps={fps}"])
    _one_error(capsys, code, "--fps must be a number in")
    assert not (tmp_path / "o.csv").exists()


def test_symlink_loops_among_frames_are_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = _seq(tmp_path)
    (seq / "a.png").symlink_to(seq / "b.png")
    (seq / "b.png").symlink_to(seq / "a.png")
    code = main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q"])
    _one_error(capsys, code, "symlink loop")


def test_non_printable_characters_in_paths_are_escaped(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    seq = _seq(tmp_path)
    (seq / "0000\nmistool: error: forged\x1b[31m.png").write_bytes(b"not a png")
    code = main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q"])
    line = _one_error(capsys, code, "\\nmistool: error: forged\\x1b[31m.png")
    assert "\x1b" not in line
    assert printable("a\udcffb\u200b") == "a\\xffb\\u200b"


def test_internal_errors_are_one_line_and_debug_shows_the_traceback(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mistool.sequence

    def bug(*args: object, **kwargs: object) -> None:
        raise TypeError("a bug")

    monkeypatch.setattr(mistool.sequence, "resolve", bug)
    monkeypatch.delenv("MISTOOL_DEBUG", raising=False)
    assert main(["track", str(tmp_path), "-q"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mistool: error: internal error: TypeError: a bug (a bug in mistool")
    assert err.count("\n") == 1 and "--debug" in err and "Traceback" not in err
    assert main(["track", str(tmp_path), "-q", "--debug"]) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().splitlines()[-1].startswith("mistool: error:")
    monkeypatch.setenv("MISTOOL_DEBUG", "1")
    assert main(["track", str(tmp_path), "-q"]) == 1
    assert "Traceback" in capsys.readouterr().err


def test_codec_log_lines_are_filtered_at_the_file_descriptor(
    capfd: pytest.CaptureFixture,
) -> None:
    with quiet_native_stderr():
        os.write(2, b"libpng error: bad adaptive filter value\n")
        os.write(2, b"[ WARN:0@1.2] global loadsave.cpp:1 imread_ something\n")
        os.write(2, b"[mjpeg @ 0x55d0c0a0] overread 8\n")
        os.write(2, b"mistool: warning: kept\n")
    assert capfd.readouterr().err == "mistool: warning: kept\n"


def test_the_stderr_filter_does_not_wait_for_other_processes_holding_it(
    capfd: pytest.CaptureFixture,
) -> None:
    """Worker processes and multiprocessing's fork server inherit the filter's pipe as
    their stderr and keep it open after the command is done: the filter passes what they
    wrote and stops without waiting for them (it waited 5 s after every
    ``mistool track --workers 2``)."""
    from mistool.cli import PUMP_THREAD

    with quiet_native_stderr():
        holder = subprocess.Popen(
            [sys.executable, "-c", "import os, time; os.write(2, b'held\\n'); time.sleep(60)"]
        )
        seen = ""
        while holder.poll() is None and "held" not in seen:  # through the filter
            seen += capfd.readouterr().err
            time.sleep(0.01)
    try:
        alive = [t for t in threading.enumerate() if t.name == PUMP_THREAD]
        assert holder.poll() is None, "the holder exited: nothing was tested"
        assert not alive, "the filter still waits for the pipe's end of file"
    finally:
        holder.kill()
        holder.wait()


def test_progress_bar_reaches_a_terminal(tmp_path: Path) -> None:
    """Python's stderr is not routed through the codecs' filter: on a terminal,
    ``mistool track`` shows its progress bar (it was held back: the filter's pipe is not
    a terminal, so no bar was ever drawn)."""
    import fcntl
    import termios

    from mistool.synth import synthesize

    short = tmp_path / "short"
    synthesize(short, frames=30, instruments=1, seed=0)
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "mistool.toml").write_bytes((short / "mistool.toml").read_bytes())
    frames = sorted(short.glob("*.png"))
    # a run of a second or more (the bar shows after 0.5 s; 600 frames took 0.4 s once
    # numba's start and kernel loading got faster, and no bar was drawn)
    count = 4000
    for k in range(count):
        (seq / f"{k:05d}.png").symlink_to(frames[k % len(frames)])
    main_fd, term_fd = os.openpty()
    fcntl.ioctl(term_fd, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    code = "import sys; from mistool.cli import main; sys.exit(main(sys.argv[1:]))"
    args = ["track", str(seq), "-o", str(tmp_path / "o.csv"), "--workers", "1"]
    child = subprocess.Popen([sys.executable, "-c", code, *args], stderr=term_fd)
    os.close(term_fd)
    seen = b""
    while True:
        try:
            chunk = os.read(main_fd, 4096)
        except OSError:  # the terminal's last writer is gone
            break
        if not chunk:
            break
        seen += chunk
    os.close(main_fd)
    assert child.wait() == 0
    text = seen.decode(errors="replace")
    assert "frame/s]" in text and "\r" in text, text[-500:]
    assert text.rstrip().splitlines()[-1].lstrip("\r").startswith(f"mistool: {count} frame(s)")


def test_corrupt_png_prints_only_mistool_s_line(
    tmp_path: Path, capfd: pytest.CaptureFixture
) -> None:
    """libpng's own 'libpng error' lines (written by C code to file descriptor 2) do not
    reach the terminal; mistool's line does. With --debug they are shown."""
    seq = _seq(tmp_path)
    (seq / "000001.png").write_bytes(_png(W, H, b"\x07" * 10))  # bad filter bytes
    assert main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q", "--workers", "1"]) == 1
    assert capfd.readouterr().err.splitlines() == [
        f"mistool: error: {seq / '000001.png'}: cannot decode as an image "
        "(corrupt, truncated or not an image file)"
    ]
    main(["track", str(seq), "-o", str(tmp_path / "o.csv"), "-q", "--debug", "--workers", "1"])
    assert "libpng error" in capfd.readouterr().err


# --- say what is odd -----------------------------------------------------------------


def _video(path: Path, n: int, size: tuple[int, int] = (W, H)) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, size, False)
    for i in range(n):
        writer.write(cv2.resize(_frame(i % 20), size, interpolation=cv2.INTER_NEAREST))
    writer.release()
    return path


def test_a_truncated_mask_video_warns(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    video = _video(tmp_path / "masks.avi", 30)
    data = video.read_bytes()
    video.write_bytes(data[: len(data) // 2])
    assert main(["track", str(video), "-o", str(tmp_path / "o.csv"), "-q"]) == 0
    err = capsys.readouterr().err
    assert re.search(r"mistool: warning: .*masks\.avi: the video ended after \d+ of the 30", err)


def test_a_mask_video_with_garbage_frames_warns(tmp_path: Path) -> None:
    """A frame decoded as noise (most pixels no label value) is named; clean frames of
    the same video (with their codec smear) are not."""
    path = tmp_path / "masks.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (W, H), False)
    noise = np.random.default_rng(0).integers(0, 256, (H, W), dtype=np.uint8)
    for i in range(8):
        writer.write(noise if i == 5 else _frame(i))
    writer.release()
    with pytest.warns(InputWarning, match=r"1 frame\(s\) look corrupt \(#5:"):
        frames = list(seqmod.open_sequence(path))
    assert len(frames) == 8


def test_source_that_disagrees_with_the_masks_warns(tmp_path: Path) -> None:
    _video(tmp_path / "short.avi", 2)
    _video(tmp_path / "small.avi", 3, size=(64, 48))
    config = config_from_dict({"source": "short.avi"}, tmp_path / "mistool.toml")
    with pytest.warns(InputWarning, match="source has 2 frame"):
        seqmod.check_source(config, 3, (H, W))
    config = config_from_dict({"source": "small.avi"}, tmp_path / "mistool.toml")
    with pytest.warns(InputWarning, match="64x48 px, the masks 128x96"):
        seqmod.check_source(config, 3, (H, W))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert seqmod.check_source(config, 3, (48, 64)) == []


def test_a_source_folder_of_undecodable_jpegs_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "rgb").mkdir()
    for i in range(3):
        (tmp_path / "rgb" / f"{i}.jpg").write_bytes(b"\xff\xd8 not a jpeg")
    config = config_from_dict({"source": "rgb"}, tmp_path / "mistool.toml")
    with pytest.raises(MaskFormatError, match="source frame does not decode"):
        seqmod.check_source(config, 3, (H, W))


def test_overlapping_part_ranges_are_an_error() -> None:
    with pytest.raises(ConfigError, match="overlap"):
        config_from_dict({"parts": {"shaft": [60, 80]}})  # the preset's clasper is 70
    config_from_dict({"parts": {"shaft": [150, 170], "clasper": [60, 80]}})


# --- the viewer answers its own page only --------------------------------------------


@pytest.fixture(scope="module")
def servers():
    """A loopback server and one that requires a token, both real viser servers."""
    from mistool.viewer.app import quiet_server
    from mistool.viewer.guard import AccessPolicy

    plain = quiet_server("127.0.0.1", 0)
    tokened = quiet_server("127.0.0.1", 0, AccessPolicy.for_host("127.0.0.1", token="s3cret"))
    yield plain, tokened
    for server in (plain, tokened):
        server.stop()


def _http(port: int, host: str, path: str = "/", headers: dict | None = None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.putrequest("GET", path, skip_host=True)
        conn.putheader("Host", host)
        for k, v in (headers or {}).items():
            conn.putheader(k, v)
        conn.endheaders()
        response = conn.getresponse()
        response.read()
        return response.status, response.getheader("Set-Cookie")
    finally:
        conn.close()


def _raw_ws(port: int, host: str, origin: str) -> int:
    """The status of a websocket upgrade sent byte by byte with a chosen Host (the
    websockets client always sends its own Host)."""
    import base64

    key = base64.b64encode(os.urandom(16)).decode()
    request = (
        f"GET / HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
        f"Sec-WebSocket-Protocol: viser-v1.1.1\r\nOrigin: {origin}\r\n\r\n"
    )
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(request.encode())
        return int(s.recv(4096).split(b" ", 2)[1])


def _ws(port: int, origin: str | None, headers: dict | None = None) -> int:
    """Connect with the websockets client; returns 101 or the refusal's status."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    extra = dict(headers or {})
    try:
        with connect(
            f"ws://127.0.0.1:{port}",
            origin=origin,  # type: ignore[arg-type]
            additional_headers=extra,
            subprotocols=["viser-v1.1.1"],  # type: ignore[list-item]
            open_timeout=10,
        ):
            return 101
    except InvalidStatus as exc:
        return exc.response.status_code


def test_viewer_refuses_foreign_origins_and_hosts(servers) -> None:
    plain, _ = servers
    port = plain.get_port()
    own = f"127.0.0.1:{port}"
    assert _ws(port, "http://evil.example") == 403
    assert _ws(port, "null") == 403
    assert _raw_ws(port, f"evil.example:{port}", f"http://evil.example:{port}") == 403
    assert _raw_ws(port, own, f"http://{own}") == 101  # the raw client itself works
    assert _ws(port, f"http://{own}") == 101
    assert _raw_ws(port, f"localhost:{port}", f"http://localhost:{port}") == 101
    assert _ws(port, None) == 101  # not a browser page
    assert _http(port, f"evil.example:{port}")[0] == 403
    assert _http(port, own)[0] == 200 and _http(port, f"localhost:{port}")[0] == 200
    assert _http(port, own, "/%2e%2e/%2e%2e/etc/passwd")[0] == 404


def test_viewer_with_a_token_needs_it_and_sets_a_cookie(servers) -> None:
    _, tokened = servers
    port = tokened.get_port()
    own = f"127.0.0.1:{port}"
    assert _http(port, own)[0] == 403
    assert _http(port, own, "/?token=wrong")[0] == 403
    status, cookie = _http(port, own, "/?token=s3cret")
    assert status == 200 and cookie is not None and "HttpOnly" in cookie
    name_value = cookie.split(";", 1)[0]
    assert _http(port, own, "/", {"Cookie": name_value})[0] == 200
    assert _ws(port, f"http://{own}") == 403
    assert _ws(port, f"http://{own}", headers={"Cookie": name_value}) == 101
    assert _ws(port, None, headers={"Authorization": "token s3cret"}) == 101
    assert _ws(port, "http://evil.example", headers={"Cookie": name_value}) == 403


def test_access_policy_table() -> None:
    from mistool.viewer.guard import AccessPolicy

    local = AccessPolicy.for_host("127.0.0.1")
    assert local.token is None
    assert local.host_allowed("127.0.0.1:8080") and local.host_allowed("[::1]:8080")
    assert not local.host_allowed("192.168.1.5:8080") and not local.host_allowed(None)
    anywhere = AccessPolicy.for_host("0.0.0.0", ["http://box.lan:8080"])
    assert anywhere.token is not None and len(anywhere.token) == 48
    assert anywhere.host_allowed("192.168.1.5:8080") and anywhere.host_allowed("box.lan:8080")
    assert not anywhere.host_allowed("evil.example:8080")
    assert anywhere.origin_allowed("http://box.lan:8080", "192.168.1.5:8080")
    assert not anywhere.origin_allowed("http://box.lan.evil.example", "box.lan:8080")
    assert AccessPolicy.for_host("0.0.0.0").token != anywhere.token  # per run


def test_serve_warns_about_a_busy_port_and_a_remote_host(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    from mistool.cli import build_parser
    from mistool.cli.serve import run

    seq = _seq(tmp_path)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        args = build_parser().parse_args(
            ["serve", str(seq), "--port", str(port), "-q", "--no-cache", "--host", "0.0.0.0"]
        )
        ready, stop = threading.Event(), threading.Event()
        result: list[int] = []
        thread = threading.Thread(target=lambda: result.append(run(args, ready=ready, stop=stop)))
        thread.start()
        assert ready.wait(120)
        stop.set()
        thread.join(60)
    out, err = capsys.readouterr()
    assert result == [0]
    assert f"mistool: warning: port {port} is busy; serving on port" in err
    assert "mistool: warning: --host 0.0.0.0 serves beyond this machine" in err
    urls = re.findall(r"open (http://\S+)", out)
    assert len(urls) == 1 and re.search(r"/\?token=[0-9a-f]{48}$", urls[0])


def test_a_real_browser_gets_in_with_the_token_and_not_without(tmp_path: Path) -> None:
    """Debian's chromium: the printed URL (with its token) opens the viewer, the page's
    websocket carries the cookie set by that first response; the bare URL gets 403."""
    if not Path("/usr/bin/chromium").exists() and not os.environ.get("CI"):
        pytest.fail("chromium is needed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    from mistool.viewer import ReplayViewer, load_sequence
    from mistool.viewer.guard import AccessPolicy

    sequence = load_sequence(_seq(tmp_path, n=3))
    viewer = ReplayViewer(
        sequence, port=0, access=AccessPolicy.for_host("127.0.0.1", token="t0ken")
    )
    try:
        assert viewer.url.endswith("/?token=t0ken")
        with sync_playwright() as p:
            browser = p.chromium.launch(
                executable_path="/usr/bin/chromium", args=["--no-sandbox", "--disable-gpu"]
            )
            try:
                page = browser.new_page()
                bare = page.goto(viewer.url.split("?")[0])
                assert bare is not None and bare.status == 403
                page = browser.new_page()
                page.goto(viewer.url)
                page.get_by_role("slider").first.wait_for(timeout=30000)  # GUI over the ws
                assert len(viewer.server.get_clients()) >= 1
            finally:
                browser.close()
    finally:
        viewer.close()


def test_ctrl_c_inside_a_c_extensions_import_is_an_interruption() -> None:
    """A Ctrl+C landing while a pybind11 module initialises (scipy's, imported at a run's
    first assignment of several tracks) surfaces as "ImportError: initialization failed";
    it was reported as an internal error with exit 1 (a fresh-clone CI run of
    test_ctrl_c_on_the_command_line_stops_every_worker). Any error after a Ctrl+C is
    the interruption: one line, exit 130."""
    code = (
        "import os, signal, sys, time\n"
        "import mistool.cli.synth as synth\n"
        "def run(args):\n"
        "    try:\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "        time.sleep(5)\n"
        "    except KeyboardInterrupt:\n"
        "        raise ImportError('initialization failed') from None\n"
        "synth.run = run\n"
        "from mistool.cli import main\n"
        "sys.exit(main(['synth', 'x']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 130 and out.stderr == "mistool: interrupted\n", out.stderr
