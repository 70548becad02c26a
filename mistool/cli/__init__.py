"""The ``mistool`` command line: a thin layer over the Python API.

Each subcommand lives in its own module of this package with ``register(subparsers)``
adding its parser and setting ``func`` to a function ``(args) -> int``. ``main(argv)``
returns the exit code, so tests run the CLI in-process.

The error contract: every failure ends as one line ``mistool: error: <where>: <what>`` on
stderr and exit code 1 (argparse's own usage errors: exit 2). Non-printable characters of
the message (a newline or an escape sequence in a file name, undecodable bytes) are
escaped, so a message is always one line and cannot forge another. Input problems are
:class:`~mistool.errors.MistoolError`; the environment's (disk full, a closed pipe, out of
memory) are turned into one line here; anything else is a bug, reported as one
``internal error`` line. ``--debug`` anywhere on the command line (or ``MISTOOL_DEBUG=1``)
prints the traceback too, for bug reports. :class:`~mistool.errors.InputWarning` warnings
are printed as one ``mistool: warning: ...`` line each.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import os
import re
import select
import signal
import sys
import threading
import traceback
import warnings
from collections.abc import Iterator, Sequence
from typing import Any

from mistool import __version__
from mistool.errors import InputWarning, MistoolError

#: Environment variable that, set to anything but "" or "0", shows tracebacks.
DEBUG_ENV = "MISTOOL_DEBUG"
#: The flag that does the same; accepted anywhere before a ``--`` separator.
DEBUG_FLAG = "--debug"
#: Exit code of every failure reported by mistool itself (argparse's usage errors: 2).
EXIT_ERROR = 1

# Subcommand modules, in the order --help lists them.
_COMMANDS = (
    "track",
    "synth",
    "evaluate",
    "serve",
    "export_html",
    "skill",
    "report",
    "export_video",
    "bookmark",
)


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every subcommand registered."""
    import importlib

    parser = argparse.ArgumentParser(
        prog="mistool",
        description=(
            "Track surgical instruments from segmentation masks: per-part rotated boxes "
            "(the paper's Algorithm 1), the paper's 3D motion (Algorithm 2), metric 3D pose "
            "from the shaft's silhouette, ground-truth synthesis and evaluation, and a 3D "
            "replay viewer in the browser."
        ),
        epilog=(
            "A sequence is a folder of label images (natural sort gives frame order) or a mask "
            "video, with an optional mistool.toml beside it (fps, label values, camera, "
            "instruments). Run 'mistool COMMAND --help' for each command."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mistool {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in _COMMANDS:
        try:
            module = importlib.import_module(f"mistool.cli.{name}")
        except ModuleNotFoundError as exc:  # a subcommand not built yet
            if exc.name != f"mistool.cli.{name}":
                raise
            continue
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit code."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    debug, args_list = _debug_requested(args_list)
    parser = build_parser()
    parser.add_argument(
        DEBUG_FLAG,
        action="store_true",
        help=f"show the traceback of an error, for bug reports (also {DEBUG_ENV}=1)",
    )
    args = parser.parse_args(args_list)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    interrupted = threading.Event()
    with (
        one_line_warnings(),
        contextlib.nullcontext() if debug else quiet_native_stderr(),
        _noting_ctrl_c(interrupted),
    ):
        try:
            return int(args.func(args) or 0)
        except KeyboardInterrupt:
            print("mistool: interrupted", file=sys.stderr)
            return 130
        except BaseException as exc:  # noqa: BLE001 - the one place errors become one line
            if isinstance(exc, SystemExit):
                raise
            if interrupted.is_set() and not debug:
                # A Ctrl+C inside a C extension's import (e.g. scipy's, at a run's first
                # assignment) surfaces as that module's "ImportError: initialization
                # failed", not as KeyboardInterrupt: still the user's interruption.
                print("mistool: interrupted", file=sys.stderr)
                return 130
            return report_error(exc, debug)


@contextlib.contextmanager
def _noting_ctrl_c(interrupted: threading.Event) -> Iterator[None]:
    """Set ``interrupted`` when a Ctrl+C (SIGINT) arrives, then raise KeyboardInterrupt as
    Python's own handler does (in the main thread, when that handler is Python's)."""
    main_thread = threading.current_thread() is threading.main_thread()
    if not main_thread or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def on_sigint(signum: int, frame: Any) -> None:
        interrupted.set()
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _debug_requested(args: list[str]) -> tuple[bool, list[str]]:
    """Whether tracebacks are wanted; the arguments without the debug flag."""
    end = args.index("--") if "--" in args else len(args)
    flag = DEBUG_FLAG in args[:end]
    rest = [a for i, a in enumerate(args) if not (i < end and a == DEBUG_FLAG)]
    return flag or os.environ.get(DEBUG_ENV, "") not in ("", "0"), rest


def printable(text: str) -> str:
    """``text`` with every non-printable character escaped, so that it prints as one
    line and cannot move the cursor or forge a line: a newline becomes ``\\n``, ESC
    ``\\x1b``, a file name's undecodable byte (a surrogate escape) ``\\xff``."""
    out = []
    for ch in text:
        code = ord(ch)
        if ch.isprintable():
            out.append(ch)
        elif 0xDC80 <= code <= 0xDCFF:  # os.fsdecode's escape of an undecodable byte
            out.append(f"\\x{code - 0xDC00:02x}")
        else:
            out.append(repr(ch)[1:-1])
    return "".join(out)


def report_error(exc: BaseException, debug: bool = False) -> int:
    """Print ``exc`` as one ``mistool: error:`` line (after its traceback when
    ``debug``); returns the exit code."""
    if debug:
        traceback.print_exception(exc)
    if isinstance(exc, BrokenPipeError) or (isinstance(exc, OSError) and exc.errno == errno.EPIPE):
        _silence_stdout()
        message = "stdout: the reader closed the pipe before all output was written"
    elif isinstance(exc, MistoolError):
        message = str(exc)
    elif isinstance(exc, OSError):
        where = exc.filename if exc.filename is not None else "system"
        message = f"{os.fsdecode(where)}: {exc.strerror or exc}"
    elif isinstance(exc, MemoryError):
        message = "out of memory; the input is too large for this machine"
    else:
        message = (
            f"internal error: {type(exc).__name__}: {exc} (a bug in mistool; "
            f"run again with {DEBUG_FLAG} and report the traceback)"
        )
    _print_stderr(f"mistool: error: {printable(message)}")
    return EXIT_ERROR


def _silence_stdout() -> None:
    """After EPIPE, point stdout at /dev/null so that the interpreter's final flush does
    not print a second error."""
    with contextlib.suppress(OSError, ValueError, AttributeError):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)


def _print_stderr(line: str) -> None:
    with contextlib.suppress(OSError, ValueError, AttributeError):  # stderr closed too
        print(line, file=sys.stderr, flush=True)


#: Lines that image and video codecs print on their own (libpng, libjpeg, libtiff,
#: OpenCV's logger, FFmpeg): mistool reports the problem itself as one line.
_NATIVE_NOISE = re.compile(
    rb"^(libpng (error|warning)|Corrupt JPEG data|Premature end of JPEG|Invalid JPEG|"
    rb"JPEG datastream|TIFF(ReadDirectory|FetchNormalTag|ReadRawStrip)|"
    rb"\[ ?(WARN|ERROR|INFO|DEBUG):[^\]]*\] |\[[a-z0-9_]+ @ 0x[0-9a-f]+\] )"
)


#: Seconds the stderr filter waits for more of the codecs' output once the command is done
#: (worker processes and multiprocessing's fork server hold the pipe open after that, so
#: its end of file would only come when they exit).
DRAIN_S = 0.05
#: select() works on pipes (POSIX); elsewhere the filter reads until end of file.
_SELECT = os.name == "posix"
#: Name of the thread that filters stderr (tests).
PUMP_THREAD = "mistool-stderr-filter"


@contextlib.contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Filter the codecs' own stderr lines (:data:`_NATIVE_NOISE`) at the file
    descriptor level, where C libraries write them; every other line passes unchanged
    and in order. A no-op when stderr is not a real file descriptor.

    Python's own ``sys.stderr`` (mistool's lines, the progress bar) keeps writing to the
    real stderr, so that a terminal stays a terminal (``isatty``) and a progress bar's
    carriage returns are not held back until a newline."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield
        return
    read_end, write_end = os.pipe()
    os.dup2(write_end, 2)
    os.close(write_end)
    done = threading.Event()
    pump = threading.Thread(
        target=_pump, args=(read_end, saved, done), name=PUMP_THREAD, daemon=True
    )
    from mistool.forksafe import FORK_SAFE_THREADS

    FORK_SAFE_THREADS.add(pump)  # so mistool serve still forks its tracking process
    pump.start()
    python_stderr, direct = sys.stderr, _direct_stream(saved)
    if direct is not None:
        sys.stderr = direct
    try:
        yield
    finally:
        sys.stderr = python_stderr
        with contextlib.suppress(OSError, ValueError, AttributeError):
            if direct is not None:
                direct.close()
            sys.stderr.flush()
        os.dup2(saved, 2)
        done.set()  # drain what is there, then stop (other processes may hold the pipe)
        pump.join(timeout=5.0)
        os.close(saved)


def _direct_stream(saved: int) -> Any:
    """A text stream on the real stderr (``saved``) in place of ``sys.stderr``, when
    ``sys.stderr`` is the process's file descriptor 2 (not a test's capture object)."""
    try:
        if sys.stderr.fileno() != 2:
            return None
    except (OSError, ValueError, AttributeError):
        return None
    return open(  # noqa: SIM115 - closed by quiet_native_stderr
        os.dup(saved),
        "w",
        encoding=sys.stderr.encoding or "utf-8",
        errors="backslashreplace",
        buffering=1,
    )


def _pump(read_end: int, out: int, done: threading.Event) -> None:
    """Copy the pipe to ``out`` line by line, without the codecs' lines; once ``done``
    is set, stop when the pipe has been quiet for :data:`DRAIN_S`."""
    pending = b""
    try:
        while True:
            ready = select.select([read_end], [], [], DRAIN_S)[0] if _SELECT else [read_end]
            if not ready:
                if done.is_set():
                    break
                continue
            chunk = os.read(read_end, 1 << 16)
            if not chunk:
                break
            *lines, pending = (pending + chunk).split(b"\n")
            for line in lines:
                _pass_line(line + b"\n", out)
        if pending:
            _pass_line(pending, out)
    finally:
        os.close(read_end)


def _pass_line(line: bytes, out: int) -> None:
    if not _NATIVE_NOISE.match(line):
        with contextlib.suppress(OSError):
            os.write(out, line)


@contextlib.contextmanager
def one_line_warnings() -> Iterator[None]:
    """Print :class:`InputWarning` warnings as one ``mistool: warning:`` line each."""
    previous = warnings.showwarning

    def show(message: Any, category: type[Warning], *args: Any, **kwargs: Any) -> None:
        if issubclass(category, InputWarning):
            _print_stderr(f"mistool: warning: {printable(str(message))}")
        else:
            previous(message, category, *args, **kwargs)

    warnings.showwarning = show
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", InputWarning)
            warnings.showwarning = show
            yield
    finally:
        warnings.showwarning = previous


def console_main() -> None:
    """Entry point of the ``mistool`` console script."""
    sys.exit(main())
