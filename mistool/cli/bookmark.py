"""``mistool bookmark``: list, add or remove bookmarks of a sequence (annotations.json)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mistool.errors import ConfigError, InputPathError

DESCRIPTION = """\
List, add or remove the bookmarks of a recording: short texts at key moments (a phase, an
event, a comment) kept in annotations.json inside the sequence folder (beside a mask
video: <stem>.annotations.json), or in the .json file given with --annotations. The file
is written atomically; the masks are never touched. 'mistool report' and 'mistool
export-video' show the bookmarks. Schema: docs/teaching.md.

examples:
  mistool bookmark masks/                                  # list
  mistool bookmark masks/ --add 120 "needle grasped" --kind event
  mistool bookmark masks/ --add 30s "suturing" --kind phase   # at 30 s (mistool.toml fps)
  mistool bookmark masks/ --remove 0
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``bookmark`` subcommand."""
    p = subparsers.add_parser(
        "bookmark",
        help="list, add or remove bookmarks (annotations.json)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sequence", metavar="SEQUENCE", help="sequence folder or mask video")
    p.add_argument("--annotations", metavar="JSON", help="the bookmarks file to use")
    p.add_argument(
        "--add",
        nargs=2,
        metavar=("AT", "TEXT"),
        help="add a bookmark at AT: a frame index, or a time such as 12.5s",
    )
    p.add_argument(
        "--kind", choices=("phase", "event", "comment"), default="comment", help="for --add"
    )
    p.add_argument("--remove", type=int, metavar="N", help="remove the N-th bookmark (0-based)")
    p.set_defaults(func=run)


def _frame(at: str, fps: float) -> int:
    text = at.strip().lower()
    try:
        if text.endswith("s"):
            return int(round(float(text[:-1]) * fps))
        return int(text)
    except ValueError:
        raise ConfigError(
            f"--add {at!r}: expected a frame index (e.g. 120) or a time (e.g. 4.8s)"
        ) from None


def run(args: argparse.Namespace) -> int:
    """Run ``mistool bookmark``."""
    import mistool.annotations as an
    from mistool.sequence import resolve

    path, config = resolve(args.sequence)
    if not path.exists():
        raise InputPathError(f"{path}: no such sequence")
    target = Path(args.annotations) if args.annotations else an.default_path(path)
    if args.add and args.remove is not None:
        raise ConfigError("give --add or --remove, not both")
    if args.add:
        marks = an.add_bookmark(target, _frame(args.add[0], config.fps), args.add[1], args.kind)
    elif args.remove is not None:
        marks = an.remove_bookmark(target, args.remove)
    else:
        marks = an.load_annotations(target)
    for k, b in enumerate(marks):
        print(f"{k:3d}  frame {b.frame:6d}  {b.time_s(config.fps):8.2f} s  {b.kind:7s}  {b.text}")
    if not marks:
        print(f"no bookmarks ({target})")
    return 0
