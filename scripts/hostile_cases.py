#!/usr/bin/env python3
"""Hostile-input review of the ``mistool`` command line: every case of issue 12, run as a
real subprocess, each judged *clean* or not; prints one line per case and ``clean/total``.

A case is clean when mistool does what a careful tool does:

- ``error``: exit code 1, exactly one ``mistool: error: <where>: <what>`` line on stderr
  (``mistool: warning:`` lines allowed), no traceback, no "internal error", the case's
  input files unchanged (type, mode, bytes) and no output file left behind;
- ``ok``: exit code 0, no traceback, plus the case's own check (e.g. permissions kept);
- ``warn``: as ``ok`` and a ``mistool: warning:`` line matching the case's pattern;
- viewer cases: a real HTTP / websocket client against a running ``mistool serve``.

Run: ``python scripts/hostile_cases.py [-k SUBSTRING] [-v] [-j JOBS]``. Cases run as root
create a character device with ``mknod`` (never touching ``/dev``); without root that case
uses a FIFO instead. Nothing outside a temporary folder is written.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import http.client
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_masks"
PY = sys.executable
#: The command line run for ``mistool`` (the checkout's own code, whatever is installed).
MISTOOL = [PY, "-P", "-c", "import sys; from mistool.cli import main; sys.exit(main())"]
#: The checkout whose mistool is run (``--against`` another one for a "before" figure).
CODE = ROOT
#: First sample frame used (both instruments are in view from here on).
FIRST = 100
#: Seconds after which a case counts as hung (a FIFO read forever, a giant decode).
TIMEOUT_S = 60.0


@dataclass
class Run:
    """What one mistool process did."""

    rc: int | None
    stdout: str
    stderr: str
    seconds: float


@dataclass
class Case:
    """One hostile case: ``setup(d)`` builds its files in the empty folder ``d`` and returns
    the command line (after ``mistool``); ``expect`` says what a clean outcome is."""

    name: str
    setup: Callable[[Path], list[str]]
    expect: str = "error"  # error | ok | warn | custom
    outputs: tuple[str, ...] = ()  # paths (relative to d) that must not be created
    check: Callable[[Path, Run], bool] | None = None
    warning: str = ""  # regex a warning line must match (expect == "warn")
    shell: str = ""  # run through bash: '{cmd}' is replaced by the quoted command
    probe: Callable[[Path], tuple[bool, str]] | None = None  # custom: whole-case runner
    timeout: float = TIMEOUT_S
    extra_env: dict[str, str] = field(default_factory=dict)


# --- fixtures ------------------------------------------------------------------------


def seq(d: Path, n: int = 4, toml: str | None = None, name: str = "seq") -> Path:
    """A small sequence folder: the first ``n`` sample frames and mistool.toml."""
    s = d / name
    s.mkdir()
    for i, f in enumerate(sorted(SAMPLE.glob("*.png"))[FIRST : FIRST + n]):
        shutil.copy(f, s / f"{i:06d}.png")
    if toml is None:  # the sample's config without its source video
        text = (SAMPLE / "mistool.toml").read_text()
        (s / "mistool.toml").write_text(re.sub(r"(?m)^source\s*=.*\n", "", text))
    else:
        (s / "mistool.toml").write_text(toml)
    return s


def toml_seq(d: Path, text: str) -> list[str]:
    """A sequence whose mistool.toml is ``text``; the command tracks it."""
    s = seq(d, toml=text)
    return ["track", str(s), "-o", str(d / "out.csv")]


def png_header(w: int, h: int, pad: int = 0) -> bytes:
    """A PNG whose IHDR claims ``w x h`` 8-bit grey pixels, with one tiny IDAT."""
    import struct
    import zlib

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (
            struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\0" * 16 + os.urandom(pad), 9) if pad else zlib.compress(b"\0" * 16)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def mask_video(path: Path, n: int = 20, size: tuple[int, int] | None = None) -> Path:
    """A mask video (MJPG .avi) of the first ``n`` sample frames (resized to ``size``)."""
    import cv2

    files = sorted(SAMPLE.glob("*.png"))[FIRST : FIRST + n]
    first = cv2.imread(str(files[0]), cv2.IMREAD_GRAYSCALE)
    wh = size or (first.shape[1], first.shape[0])
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, wh, False)
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        w.write(cv2.resize(img, wh, interpolation=cv2.INTER_NEAREST))
    w.release()
    return path


def table_csv(d: Path) -> Path:
    """A motion table of the 4-frame sequence (tracked once per case)."""
    s = d / "seq" if (d / "seq").exists() else seq(d)
    out = d / "table.csv"
    subprocess.run(
        [*MISTOOL, "track", str(s), "-o", str(out), "-q"],
        check=True,
        env=_env(),
        capture_output=True,
    )
    return out


# --- running and judging ---------------------------------------------------------------


def _env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(CODE), XDG_CACHE_HOME=str(Path(tempfile.gettempdir())))
    env.pop("MISTOOL_DEBUG", None)
    env.update(extra or {})
    return env


def snapshot(d: Path, skip: set[Path]) -> dict[str, tuple]:
    """Type, mode and content digest of every entry under ``d`` (symlinks not followed)."""
    out: dict[str, tuple] = {}
    for dirpath, dirnames, filenames in os.walk(d):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            if p in skip:
                continue
            st = p.lstat()
            digest = ""
            if stat.S_ISREG(st.st_mode):
                digest = hashlib.sha256(p.read_bytes()).hexdigest()
            elif stat.S_ISLNK(st.st_mode):
                digest = os.readlink(p)
            out[str(p.relative_to(d))] = (stat.S_IFMT(st.st_mode), stat.S_IMODE(st.st_mode), digest)
    return out


def run_mistool(args: list[str], cwd: Path, shell: str, timeout: float, env: dict) -> Run:
    cmd = [*MISTOOL, *args]
    if shell:
        import shlex

        cmd = ["bash", "-c", shell.replace("{cmd}", shlex.join(cmd))]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(
            cmd,
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
            errors="replace",
            stdin=subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired as exc:
        err = exc.stderr.decode(errors="replace") if isinstance(exc.stderr, bytes) else ""
        return Run(None, "", err, time.perf_counter() - t0)
    return Run(p.returncode, p.stdout, p.stderr, time.perf_counter() - t0)


def one_line_error(run: Run) -> tuple[bool, str]:
    """Whether stderr is one ``mistool: error:`` line (warnings allowed) and rc == 1."""
    if run.rc is None:
        return False, f"hung (> {TIMEOUT_S:.0f} s)"
    if "Traceback" in run.stderr:
        return False, "traceback: " + run.stderr.strip().splitlines()[-1][:120]
    lines = [ln for ln in run.stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("mistool: error: ")]
    others = [ln for ln in lines if not ln.startswith(("mistool: error: ", "mistool: warning: "))]
    if run.rc != 1:
        return False, f"exit {run.rc}: {(lines or [''])[-1][:120]}"
    if len(errors) != 1 or others:
        return False, f"{len(errors)} error line(s), {len(others)} other line(s): {lines[:3]}"
    if "internal error" in errors[0]:
        return False, errors[0][:140]
    return True, errors[0][:140]


def judge(case: Case) -> tuple[bool, str]:
    """Run one case in a fresh folder; (clean, short reason)."""
    with tempfile.TemporaryDirectory(prefix="hostile_") as tmp:
        d = Path(tmp)
        try:
            if case.probe is not None:
                return case.probe(d)
            args = case.setup(d)
            outs = {d / o for o in case.outputs}
            before = snapshot(d, outs)
            run = run_mistool(args, d, case.shell, case.timeout, _env(case.extra_env))
            after = snapshot(d, outs)
            if case.expect != "error":  # the command's own output may appear
                before = {k: v for k, v in before.items() if not k.startswith("out.")}
                after = {k: v for k, v in after.items() if not k.startswith("out.")}
            return _verdict(case, d, run, before, after, outs)
        finally:
            for p in d.rglob("*"):  # a case may leave a folder without write permission
                if p.is_dir() and not p.is_symlink():
                    os.chmod(p, 0o755)


def _verdict(
    case: Case, d: Path, run: Run, before: dict, after: dict, outs: set[Path]
) -> tuple[bool, str]:
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    if case.expect == "error":
        ok, why = one_line_error(run)
        if ok and changed:
            return False, f"files changed: {changed[:3]}"
        left = [str(o.relative_to(d)) for o in outs if os.path.lexists(o)]
        if ok and left:
            return False, f"output left behind: {left}"
        if ok and case.check is not None and not case.check(d, run):
            return False, "case check failed: " + why
        return ok, why
    if run.rc is None:
        return False, "hung"
    if "Traceback" in run.stderr:
        return False, "traceback: " + run.stderr.strip().splitlines()[-1][:120]
    if run.rc != 0:
        return False, f"exit {run.rc}: {run.stderr.strip()[-160:]}"
    if changed:
        return False, f"input files changed: {changed[:3]}"
    if case.expect == "warn":
        warns = [ln for ln in run.stderr.splitlines() if ln.startswith("mistool: warning: ")]
        if not any(re.search(case.warning, w, re.I) for w in warns):
            return False, f"no warning matching {case.warning!r}"
    if case.check is not None and not case.check(d, run):
        return False, "case check failed"
    return True, "ok"


# --- viewer probes -----------------------------------------------------------------------


class Server:
    """``mistool serve`` of a small table in a subprocess; the URL it printed."""

    def __init__(self, d: Path, *extra: str) -> None:
        s = seq(d)
        poses = table_csv(d)
        self.proc = subprocess.Popen(
            [*MISTOOL, "serve", str(s), "--poses", str(poses), "--port", "0", "-q", *extra],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(),
        )
        self.lines: list[str] = []
        self.url = ""
        deadline = time.monotonic() + TIMEOUT_S
        assert self.proc.stdout is not None
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                break
            self.lines.append(line)
            m = re.search(r"(http://\S+)", line)
            if m and line.startswith("open"):
                self.url = m.group(1)
                break
        m = re.match(r"http://([^/:]+):(\d+)", self.url)
        self.host, self.port = (m.group(1), int(m.group(2))) if m else ("", 0)

    def stop(self) -> str:
        self.proc.terminate()
        try:
            _, err = self.proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _, err = self.proc.communicate()
        return err


def http_status(port: int, host_header: str, path: str = "/", headers: dict | None = None) -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.putrequest("GET", path, skip_host=True)
        conn.putheader("Host", host_header)
        for k, v in (headers or {}).items():
            conn.putheader(k, v)
        conn.endheaders()
        return conn.getresponse().status
    finally:
        conn.close()


def ws_status(
    port: int, host_header: str, origin: str | None, path: str = "/", headers: dict | None = None
) -> int:
    """Status of a websocket upgrade request (101 = accepted)."""
    import base64

    key = base64.b64encode(os.urandom(16)).decode()
    lines = [
        f"GET {path} HTTP/1.1",
        f"Host: {host_header}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {key}",
        "Sec-WebSocket-Version: 13",
        "Sec-WebSocket-Protocol: viser-v1.1.1",
    ]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        status = s.recv(4096).split(b"\r\n", 1)[0].decode(errors="replace")
    return int(status.split()[1]) if len(status.split()) > 1 else 0


def probe(
    check: Callable[[Server], tuple[bool, str]], *extra: str
) -> Callable[[Path], tuple[bool, str]]:
    def run(d: Path) -> tuple[bool, str]:
        server = Server(d, *extra)
        try:
            if not server.port:
                return False, f"server did not start: {''.join(server.lines)[-200:]}"
            return check(server)
        finally:
            server.stop()

    return run


def _own(s: Server) -> str:
    return f"{s.host}:{s.port}"


def p_foreign_origin(s: Server) -> tuple[bool, str]:
    st = ws_status(s.port, _own(s), "http://evil.example")
    return st not in (101,), f"websocket with Origin evil.example -> {st}"


def p_null_origin(s: Server) -> tuple[bool, str]:
    st = ws_status(s.port, _own(s), "null")
    return st != 101, f"websocket with Origin null -> {st}"


def p_own_origin(s: Server) -> tuple[bool, str]:
    st = ws_status(s.port, _own(s), f"http://{_own(s)}")
    return st == 101, f"websocket with its own Origin -> {st}"


def p_foreign_host_http(s: Server) -> tuple[bool, str]:
    st = http_status(s.port, f"evil.example:{s.port}")
    return st in (400, 403, 421), f"GET with Host evil.example -> {st}"


def p_foreign_host_ws(s: Server) -> tuple[bool, str]:
    st = ws_status(s.port, f"evil.example:{s.port}", f"http://evil.example:{s.port}")
    return st != 101, f"websocket with Host+Origin evil.example (DNS rebinding) -> {st}"


def p_own_host_http(s: Server) -> tuple[bool, str]:
    a, b = http_status(s.port, _own(s)), http_status(s.port, f"localhost:{s.port}")
    return (a, b) == (200, 200), f"GET own Host -> {a}, localhost -> {b}"


def p_traversal(s: Server) -> tuple[bool, str]:
    st = http_status(s.port, _own(s), "/../../etc/passwd")
    st2 = http_status(s.port, _own(s), "/%2e%2e/%2e%2e/etc/passwd")
    return st == 404 and st2 == 404, f"path traversal -> {st}, {st2}"


def p_remote_token(s: Server) -> tuple[bool, str]:
    """--host 0.0.0.0: a token in the printed URL, no access without it (the warning is
    the next case)."""
    m = re.search(r"token=([0-9a-f]+)", s.url)
    no_token = http_status(s.port, f"127.0.0.1:{s.port}")
    ws_no_token = ws_status(s.port, f"127.0.0.1:{s.port}", f"http://127.0.0.1:{s.port}")
    with_token = http_status(s.port, f"127.0.0.1:{s.port}", f"/?token={m.group(1)}") if m else 0
    ok = bool(m) and no_token in (401, 403) and ws_no_token != 101 and with_token == 200
    return ok, (
        f"url {s.url!r}; without token GET {no_token}, ws {ws_no_token}; with token {with_token}"
    )


def p_remote_warning(d: Path) -> tuple[bool, str]:
    server = Server(d, "--host", "0.0.0.0")
    try:
        ok_start = bool(server.port)
    finally:
        err = server.stop()
    out = "".join(server.lines) + err
    return ok_start and bool(
        re.search(r"warning.*(other machines|network|0\.0\.0\.0)", out, re.I)
    ), (out.strip().splitlines()[0][:140] if out.strip() else "no output")


def p_busy_port(d: Path) -> tuple[bool, str]:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        server = Server.__new__(Server)
        s = seq(d)
        poses = table_csv(d)
        proc = subprocess.Popen(
            [*MISTOOL, "serve", str(s), "--poses", str(poses), "--port", str(port), "-q"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(),
        )
        server.proc = proc
        line = ""
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline and not line.startswith("open"):
            line = proc.stdout.readline() if proc.stdout else ""
            if not line:
                break
        err = server.stop()
    said = re.search(rf"warning: .*port {port}.*busy", err + line, re.I)
    return bool(said), f"busy port {port}: {(err.strip() or line.strip())[:140]}"


# --- the cases -----------------------------------------------------------------------------


def _track_out(d: Path, out: str, *more: str) -> list[str]:
    s = seq(d)
    return ["track", str(s), "-o", out.format(seq=s, d=d), *more]


def _mode(path: str, mode: int) -> Callable[[Path, Run], bool]:
    return lambda d, r: stat.S_IMODE((d / path).stat().st_mode) == mode


def _chardev(d: Path) -> str:
    p = d / "nulldev"
    if os.geteuid() == 0:
        os.mknod(p, 0o666 | stat.S_IFCHR, os.makedev(1, 3))  # like /dev/null
    else:
        os.mkfifo(p)
    return str(p)


def _still_chardev(d: Path, r: Run) -> bool:
    m = (d / "nulldev").lstat().st_mode
    return stat.S_ISCHR(m) or stat.S_ISFIFO(m)


def _fifo(d: Path) -> str:
    os.mkfifo(d / "fifo.csv")
    return str(d / "fifo.csv")


def _socket(d: Path) -> str:
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(d / "sock.csv"))
    s.close()
    return str(d / "sock.csv")


def _existing_0600(d: Path) -> list[str]:
    args = _track_out(d, "{d}/out.csv")
    (d / "out.csv").write_text("old\n")
    os.chmod(d / "out.csv", 0o600)
    return args


def _umask_077(d: Path) -> list[str]:
    return _track_out(d, "{d}/out.csv")


def _link_to_frame(d: Path) -> list[str]:
    s = seq(d)
    (d / "link.csv").symlink_to(s / "000000.png")
    return ["track", str(s), "-o", str(d / "link.csv")]


def _hardlink_to_frame(d: Path) -> list[str]:
    s = seq(d)
    os.link(s / "000000.png", d / "hard.csv")
    return ["track", str(s), "-o", str(d / "hard.csv")]


def _source_out(d: Path) -> list[str]:
    s = seq(d, toml='fps = 25.0\nsource = "../video.avi"\n')
    mask_video(d / "video.avi", 4)
    return ["track", str(s), "-o", str(d / "video.avi")]


def _export_onto_frame(d: Path) -> list[str]:
    s = seq(d)
    return ["export-html", str(s), "--poses", str(table_csv(d)), "-o", str(s / "000001.png"), "-q"]


CALIBRATION = (
    "image_width: 720\nimage_height: 576\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
    "  data: [600, 0, 359.5, 0, 600, 287.5, 0, 0, 1]\n"
)


def _calibration_out(d: Path) -> list[str]:
    s = seq(d)
    (d / "camera.yaml").write_text(CALIBRATION)
    (d / "out.csv").symlink_to(d / "camera.yaml")
    return ["track", str(s), "--calibration", str(d / "camera.yaml"), "-o", str(d / "out.csv")]


def _table_command_out(d: Path, command: str) -> list[str]:
    s = seq(d)
    t = table_csv(d)
    return {
        "export-html": ["export-html", str(s), "--poses", str(t), "-o", str(t), "-q"],
        "report": ["report", str(t), "-o", str(t), "-q"],
        "skill": ["skill", str(t), "-o", str(t), "-q"],
        "eval": ["eval", str(t), str(t), "--json", str(t)],
    }[command]


def _export_missing_folder(d: Path) -> list[str]:
    s = seq(d)
    (s / "000003.png").write_bytes(b"not a png")  # tracking would fail on this frame
    return ["export-html", str(s), "--no-cache", "-o", str(d / "nope" / "r.html"), "-q"]


def _export_missing_check(d: Path, r: Run) -> bool:
    """The output folder is reported, not the corrupt frame: checked before the work."""
    return "nope" in r.stderr and "000003.png" not in r.stderr


def _symlink_loop_frames(d: Path) -> list[str]:
    s = seq(d)
    (s / "a.png").symlink_to(s / "b.png")
    (s / "b.png").symlink_to(s / "a.png")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _symlink_self(d: Path) -> list[str]:
    s = seq(d)
    (s / "000009.png").symlink_to(s / "000009.png")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _bomb(d: Path, w: int, h: int, n: int = 1, pad: int = 0) -> list[str]:
    s = seq(d)
    for i in range(n):
        (s / f"00000{i}.png").write_bytes(png_header(w, h, pad))
    return ["track", str(s), "-o", str(d / "out.csv")]


def _nl_name(d: Path) -> list[str]:
    s = seq(d)
    (s / "000001.png").rename(s / "0000\nmistool: error: forged.png")
    (s / "0000\nmistool: error: forged.png").write_bytes(b"not a png")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _esc_name(d: Path) -> list[str]:
    s = seq(d)
    (s / "000001.png").rename(s / "00\x1b[31m01.png")
    (s / "00\x1b[31m01.png").write_bytes(b"not a png")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _no_escape_chars(d: Path, r: Run) -> bool:
    return "\x1b" not in r.stderr and r.stderr.count("\n") <= 1


def _bad_utf8_name(d: Path) -> list[str]:
    s = seq(d)
    bad = os.fsencode(str(s)) + b"/00\xff01.png"
    with open(bad, "wb") as f:
        f.write(b"not a png")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _fifo_toml(d: Path) -> list[str]:
    s = seq(d)
    (s / "mistool.toml").unlink()
    os.mkfifo(s / "mistool.toml")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _big_toml(d: Path) -> list[str]:
    return toml_seq(d, "fps = 25.0\n" + "# padding\n" * 2_000_000)


def _dir_toml(d: Path) -> list[str]:
    s = seq(d)
    (s / "mistool.toml").unlink()
    (s / "mistool.toml").mkdir()
    return ["track", str(s), "-o", str(d / "out.csv")]


def _dangling_toml(d: Path) -> list[str]:
    s = seq(d)
    (s / "mistool.toml").unlink()
    (s / "mistool.toml").symlink_to(d / "gone.toml")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _loop_toml(d: Path) -> list[str]:
    s = seq(d)
    (s / "mistool.toml").unlink()
    (s / "mistool.toml").symlink_to(s / "mistool.toml")
    return ["track", str(s), "-o", str(d / "out.csv")]


def _frame_table(d: Path, frame: str) -> list[str]:
    s = seq(d)
    t = table_csv(d)
    lines = t.read_text().splitlines()
    cells = lines[1].split(",")
    cells[0] = frame
    t.write_text("\n".join([lines[0], ",".join(cells), *lines[2:]]) + "\n")
    return ["export-html", str(s), "--poses", str(t), "-o", str(d / "out.html"), "-q"]


def _truncated_video(d: Path) -> list[str]:
    v = mask_video(d / "masks.avi", 20)
    data = v.read_bytes()
    v.write_bytes(data[: len(data) // 2])
    return ["track", str(v), "-o", str(d / "out.csv"), "-q"]


def _garbage_video(d: Path) -> list[str]:
    v = mask_video(d / "masks.avi", 20)
    data = bytearray(v.read_bytes())
    rnd = os.urandom(len(data) // 3)
    start = len(data) // 3
    data[start : start + len(rnd)] = rnd
    v.write_bytes(bytes(data))
    return ["track", str(v), "-o", str(d / "out.csv"), "-q"]


def _source_short(d: Path) -> list[str]:
    s = seq(d, n=8, toml='fps = 25.0\nsource = "../src.avi"\n')
    mask_video(d / "src.avi", 4)
    return ["export-html", str(s), "--no-cache", "-o", str(d / "out.html"), "-q"]


def _source_size(d: Path) -> list[str]:
    s = seq(d, n=4, toml='fps = 25.0\nsource = "../src.avi"\n')
    mask_video(d / "src.avi", 4, size=(320, 240))
    return ["export-html", str(s), "--no-cache", "-o", str(d / "out.html"), "-q"]


def _source_bad_jpegs(d: Path) -> list[str]:
    s = seq(d, n=4, toml='fps = 25.0\nsource = "../rgb"\n')
    (d / "rgb").mkdir()
    for i in range(4):
        (d / "rgb" / f"{i:06d}.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    return ["export-html", str(s), "--no-cache", "-o", str(d / "out.html"), "-q"]


def _mask_bad_jpegs(d: Path) -> list[str]:
    s = d / "seq"
    s.mkdir()
    for i in range(4):
        (s / f"{i:06d}.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    return ["track", str(s), "-o", str(d / "out.csv")]


def p_enospc(d: Path) -> tuple[bool, str]:
    """Disk full: the output goes to a 4 kB tmpfs (root only; else a FIFO-free fallback
    is not possible and the case reports so)."""
    if os.geteuid() != 0:
        return False, "needs root to mount a small tmpfs"
    full = d / "full"
    full.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4k", "tmpfs", str(full)], check=True)
    try:
        (full / "old.csv").write_text("x" * 100)
        args = _track_out(d, str(full / "out.csv"))
        run = run_mistool(args, d, "", TIMEOUT_S, _env())
        ok, why = one_line_error(run)
        left = sorted(p.name for p in full.iterdir())
        if ok and left != ["old.csv"]:
            return False, f"left on the full disk: {left}"
        return ok, why
    finally:
        subprocess.run(["umount", str(full)], check=False)


def _stdout_ok(d: Path, r: Run) -> bool:
    return r.stdout.startswith("frame,")


CAMERA = "[camera]\nfx = 580.0\nfy = 580.0\ncx = 359.5\ncy = 287.5\n"

CASES: list[Case] = [
    # --- data loss ---
    Case("output is a frame", lambda d: _track_out(d, "{seq}/000000.png")),
    Case("output is mistool.toml", lambda d: _track_out(d, "{seq}/mistool.toml")),
    Case("output is the sequence folder", lambda d: _track_out(d, "{seq}")),
    Case("output is a symlink to a frame", _link_to_frame),
    Case("output is a hard link to a frame", _hardlink_to_frame),
    Case("output is the source video", _source_out),
    Case("export-html onto a frame", _export_onto_frame),
    Case(
        "output is a character device", lambda d: _track_out(d, _chardev(d)), check=_still_chardev
    ),
    Case("output is a FIFO", lambda d: _track_out(d, _fifo(d)), timeout=30),
    Case("output is a socket", lambda d: _track_out(d, _socket(d))),
    Case("output is a folder", lambda d: (d / "outdir").mkdir() or _track_out(d, "{d}/outdir")),
    Case("output folder missing", lambda d: _track_out(d, "{d}/nope/out.csv")),
    Case("output via /proc/self/fd/1", lambda d: _track_out(d, "/proc/self/fd/1")),
    Case("existing output 0600 kept", _existing_0600, expect="ok", check=_mode("out.csv", 0o600)),
    Case(
        "new output follows umask 077",
        _umask_077,
        expect="ok",
        check=_mode("out.csv", 0o600),
        shell="umask 077; {cmd}",
    ),
    Case(
        "export-html: missing folder before work",
        _export_missing_folder,
        outputs=("nope",),
        check=_export_missing_check,
    ),
    Case("-o - to stdout", lambda d: _track_out(d, "-", "-q"), expect="ok", check=_stdout_ok),
    Case(
        "-o - into a closed pipe",
        lambda d: _track_out(d, "-", "-q"),
        shell="{cmd} | true; exit ${{PIPESTATUS[0]}}".replace("{{", "{").replace("}}", "}"),
    ),
    Case("-o - with stdout closed", lambda d: _track_out(d, "-", "-q"), shell="{cmd} >&-"),
    Case("disk full (ENOSPC, 4 kB tmpfs)", lambda d: [], expect="custom", probe=p_enospc),
    # --- resources ---
    Case("PNG header claims 100000x100000", lambda d: _bomb(d, 100000, 100000)),
    Case("4 PNGs claim 32000x32000", lambda d: _bomb(d, 32000, 32000, 4, pad=1 << 20), timeout=30),
    Case("PNG header claims 0x0", lambda d: _bomb(d, 0, 0)),
    Case("PNG header claims 2^31x1", lambda d: _bomb(d, 2**31 - 1, 1)),
    Case("table frame = 2000000000", lambda d: _frame_table(d, "2000000000"), timeout=30),
    Case("table frame = -1", lambda d: _frame_table(d, "-1")),
    Case("table frame = 1e300", lambda d: _frame_table(d, "1e300")),
    Case("table frame = nan", lambda d: _frame_table(d, "nan")),
    Case("FIFO mistool.toml", _fifo_toml, timeout=30),
    Case("20 MB mistool.toml", _big_toml),
    Case("mistool.toml is a folder", _dir_toml),
    Case("dangling mistool.toml symlink", _dangling_toml),
    Case("mistool.toml symlink loop", _loop_toml),
    # --- tracebacks -> one line ---
    Case("symlink loop among frames", _symlink_loop_frames),
    Case("frame symlinked to itself", _symlink_self),
    Case(
        "invalid UTF-8 in mistool.toml",
        lambda d: (
            seq(d).joinpath("mistool.toml").write_bytes(b'fps = 25\nname = "\xff\xfe"\n'),
            ["track", str(d / "seq"), "-o", str(d / "out.csv")],
        )[1],
    ),
    Case(
        "5000-deep array in mistool.toml",
        lambda d: toml_seq(d, "fps = " + "[" * 5000 + "]" * 5000 + "\n"),
    ),
    Case('labels = ["endovis15"]', lambda d: toml_seq(d, 'labels = ["endovis15"]\n')),
    Case("labels = 5", lambda d: toml_seq(d, "labels = 5\n")),
    Case("labels = {a = 1}", lambda d: toml_seq(d, "labels = {a = 1}\n")),
    Case("source = 5", lambda d: toml_seq(d, "source = 5\n")),
    Case("parts = 5", lambda d: toml_seq(d, "parts = 5\n")),
    Case("parts.shaft = [1, 2, 3]", lambda d: toml_seq(d, "[parts]\nshaft = [1, 2, 3]\n")),
    Case("parts.shaft = 1.5", lambda d: toml_seq(d, "[parts]\nshaft = 1.5\n")),
    Case("instrument = 5", lambda d: toml_seq(d, "instrument = 5\n")),
    Case(
        "instrument name = [1]", lambda d: toml_seq(d, "[[instrument]]\nname = [1]\nshaft = 160\n")
    ),
    Case(
        "min_area_px = 2^62",
        lambda d: toml_seq(d, "min_area_px = 4611686018427387904\n"),
        expect="ok",
    ),
    Case("min_area_px = 1.5", lambda d: toml_seq(d, "min_area_px = 1.5\n")),
    Case("output is a link to the calibration file", _calibration_out),
    Case("export-html onto its --poses table", lambda d: _table_command_out(d, "export-html")),
    Case("report onto its input table", lambda d: _table_command_out(d, "report")),
    Case("skill onto its input table", lambda d: _table_command_out(d, "skill")),
    Case("eval --json onto its input table", lambda d: _table_command_out(d, "eval")),
    Case("camera = 5", lambda d: toml_seq(d, "camera = 5\n")),
    Case(
        'camera fx = "580"',
        lambda d: toml_seq(d, '[camera]\nfx = "580"\nfy = 580.0\ncx = 1.0\ncy = 1.0\n'),
    ),
    Case("fps = 1e308", lambda d: toml_seq(d, "fps = 1e308\n")),
    Case("fps = 1e-308", lambda d: toml_seq(d, "fps = 1e-308\n")),
    Case("fps = inf", lambda d: toml_seq(d, "fps = inf\n")),
    Case("fps = nan", lambda d: toml_seq(d, "fps = nan\n")),
    Case("fps = -25", lambda d: toml_seq(d, "fps = -25.0\n")),
    Case("fps = true", lambda d: toml_seq(d, "fps = true\n")),
    Case('fps = "25"', lambda d: toml_seq(d, 'fps = "25"\n')),
    Case(
        "camera fx = 1e308",
        lambda d: toml_seq(d, "[camera]\nfx = 1e308\nfy = 580.0\ncx = 359.5\ncy = 287.5\n"),
    ),
    Case(
        "camera fx = 1e-308",
        lambda d: toml_seq(d, "[camera]\nfx = 1e-308\nfy = 580.0\ncx = 359.5\ncy = 287.5\n"),
    ),
    Case(
        "camera fy = 1e-308",
        lambda d: toml_seq(d, "[camera]\nfx = 580.0\nfy = 1e-308\ncx = 359.5\ncy = 287.5\n"),
    ),
    Case(
        "camera cx = 1e308",
        lambda d: toml_seq(d, "[camera]\nfx = 580.0\nfy = 580.0\ncx = 1e308\ncy = 287.5\n"),
    ),
    Case(
        "shaft_diameter_mm = 1e308",
        lambda d: toml_seq(
            d,
            "shaft_diameter_mm = 1e308\n[camera]\nfx = 580.0\nfy = 580.0\ncx = 359.5\ncy = 287.5\n",
        ),
    ),
    Case(
        "shaft_diameter_mm = 1e-308",
        lambda d: toml_seq(
            d,
            "shaft_diameter_mm = 1e-308\n" + CAMERA,
        ),
    ),
    Case(
        "clasper_length_mm = 1e308",
        lambda d: toml_seq(
            d,
            "clasper_length_mm = 1e308\n[camera]\nfx = 580.0\nfy = 580.0\ncx = 359.5\ncy = 287.5\n",
        ),
    ),
    Case(
        "instrument shaft_diameter_mm = 1e-308",
        lambda d: toml_seq(
            d,
            CAMERA + "[[instrument]]\nshaft = 160\nclasper = 70\nshaft_diameter_mm = 1e-308\n",
        ),
    ),
    Case("--fps inf", lambda d: _track_out(d, "{d}/out.csv", "--fps", "inf")),
    Case("--fps nan", lambda d: _track_out(d, "{d}/out.csv", "--fps", "nan")),
    Case("--fps 1e308", lambda d: _track_out(d, "{d}/out.csv", "--fps", "1e308")),
    Case("--fps 1e-308", lambda d: _track_out(d, "{d}/out.csv", "--fps", "1e-308")),
    Case(
        "--min-area 2^70",
        lambda d: _track_out(d, "{d}/out.csv", "--min-area", str(2**70)),
        expect="ok",
    ),
    Case(
        "--workers 100000",
        lambda d: _track_out(d, "{d}/out.csv", "--workers", "100000"),
        expect="ok",
    ),
    Case("newline in a frame name", _nl_name, check=_no_escape_chars),
    Case("escape sequence in a frame name", _esc_name, check=_no_escape_chars),
    Case("invalid UTF-8 in a frame name", _bad_utf8_name),
    Case(
        "corrupt frame",
        lambda d: (
            seq(d).joinpath("000002.png").write_bytes(b"\x89PNG\r\n\x1a\ngarbage"),
            ["track", str(d / "seq"), "-o", str(d / "out.csv")],
        )[1],
    ),
    Case(
        "truncated frame",
        lambda d: (
            lambda s: (
                s.joinpath("000002.png").write_bytes(s.joinpath("000002.png").read_bytes()[:200]),
                ["track", str(s), "-o", str(d / "out.csv")],
            )[1]
        )(seq(d)),
    ),
    Case("frame of another size", lambda d: _bomb(d, 64, 48, 1)),
    Case("missing sequence", lambda d: ["track", str(d / "nope"), "-o", str(d / "out.csv")]),
    Case(
        "eval: truth is not a CSV",
        lambda d: (
            (d / "t.csv").write_bytes(b"\xff\xfe\x00"),
            ["eval", str(table_csv(d)), str(d / "t.csv")],
        )[1],
    ),
    # --- say what is odd ---
    Case(
        "overlapping [parts] ranges",
        lambda d: toml_seq(d, "[parts]\nshaft = [60, 80]\nclasper = 70\n"),
    ),
    Case(
        "overlapping instrument ranges",
        lambda d: toml_seq(
            d,
            "[[instrument]]\nshaft = [100, 200]\nclasper = 70\n"
            "[[instrument]]\nshaft = 160\nclasper = 30\n",
        ),
    ),
    Case(
        "truncated mask video",
        _truncated_video,
        expect="warn",
        warning=r"ended|early|fewer|truncat",
    ),
    Case(
        "garbage in a mask video",
        _garbage_video,
        expect="warn",
        warning=r"ended|early|fewer|corrupt|garbage|decod",
    ),
    Case("source has fewer frames", _source_short, expect="warn", warning=r"source.*frame"),
    Case("source has another size", _source_size, expect="warn", warning=r"source.*(size|px)"),
    Case("source folder of undecodable JPEGs", _source_bad_jpegs),
    Case("mask folder of undecodable JPEGs", _mask_bad_jpegs),
    # --- viewer ---
    Case(
        "ws with Origin evil.example", lambda d: [], expect="custom", probe=probe(p_foreign_origin)
    ),
    Case("ws with Origin null", lambda d: [], expect="custom", probe=probe(p_null_origin)),
    Case("ws with own Origin accepted", lambda d: [], expect="custom", probe=probe(p_own_origin)),
    Case(
        "GET with Host evil.example",
        lambda d: [],
        expect="custom",
        probe=probe(p_foreign_host_http),
    ),
    Case(
        "ws with Host evil.example (rebinding)",
        lambda d: [],
        expect="custom",
        probe=probe(p_foreign_host_ws),
    ),
    Case(
        "GET with own Host / localhost", lambda d: [], expect="custom", probe=probe(p_own_host_http)
    ),
    Case("path traversal URLs", lambda d: [], expect="custom", probe=probe(p_traversal)),
    Case(
        "--host 0.0.0.0 needs a token",
        lambda d: [],
        expect="custom",
        probe=probe(p_remote_token, "--host", "0.0.0.0"),
    ),
    Case("--host 0.0.0.0 warns", lambda d: [], expect="custom", probe=p_remote_warning),
    Case("busy port is reported", lambda d: [], expect="custom", probe=p_busy_port),
]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-k", default="", help="only cases whose name contains this")
    ap.add_argument("-v", action="store_true", help="print every case, not only the failures")
    ap.add_argument("-j", type=int, default=2, help="cases run in parallel (default 2)")
    ap.add_argument("--against", type=Path, help="run another checkout's mistool (e.g. main)")
    args = ap.parse_args()
    global CODE
    CODE = args.against.resolve() if args.against else ROOT
    cases = [c for c in CASES if args.k.lower() in c.name.lower()]
    with concurrent.futures.ThreadPoolExecutor(args.j) as pool:
        results = list(pool.map(_safe_judge, cases))
    clean = 0
    for case, (ok, why) in zip(cases, results, strict=True):
        clean += ok
        if args.v or not ok:
            print(f"{'clean' if ok else 'NOT  '}  {case.name}: {why}")
    print(f"hostile cases: {clean}/{len(cases)} clean")
    return 0


def _safe_judge(case: Case) -> tuple[bool, str]:
    try:
        return judge(case)
    except Exception as exc:  # noqa: BLE001 - a case's own setup failing is reported, not fatal
        return False, f"case setup failed: {type(exc).__name__}: {exc}"


if __name__ == "__main__":
    sys.exit(main())
