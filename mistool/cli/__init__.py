"""The ``mistool`` command line: a thin layer over the Python API.

Each subcommand lives in its own module of this package with ``register(subparsers)``
adding its parser and setting ``func`` to a function ``(args) -> int``. ``main(argv)``
returns the exit code, so tests run the CLI in-process.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from mistool import __version__
from mistool.errors import MistoolError

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
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except MistoolError as exc:
        print(f"mistool: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("mistool: interrupted", file=sys.stderr)
        return 130


def console_main() -> None:
    """Entry point of the ``mistool`` console script."""
    sys.exit(main())
