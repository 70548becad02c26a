"""``mistool export-html``: a standalone, offline HTML replay of a sequence."""

from __future__ import annotations

import argparse
import sys

DESCRIPTION = """\
Write one HTML file that replays a sequence in 3D without a server or network: the
instruments' cylinders, their trails and the endoscope frustum showing the mask and boxes,
frame by frame, with viser's own play/pause and time slider, and around it a title, a
frame counter with units (frame, seconds, fps), the legend (one colour per instrument)
and plots of each tip's speed and depth with a cursor at the current time and the
bookmarks marked (annotations.json of the sequence, or --annotations). It opens paused
at the first frame (--autoplay: playing). Share it by e-mail or open it from a USB stick
in a lecture room. (The GUI panel of 'mistool serve' -- mode switch, 2D overlay panel,
bookmark editing -- is not part of the file.)

The sequence is tracked first unless --poses gives its motion table (tracked tables are
cached as for 'mistool serve'). The file is written
atomically. Size grows with frames x image size: about 10-20 kB per frame with images;
use --stride, --max-frames or --no-images for long sequences.

examples:
  mistool export-html masks/ -o replay.html
  mistool export-html masks/ -o replay.html --poses masks_motion.csv --stride 2
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export-html`` subcommand."""
    p = subparsers.add_parser(
        "export-html",
        help="standalone offline HTML replay",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "sequence",
        metavar="SEQUENCE",
        nargs="?",
        default=None,
        help="folder of label images or mask video (default: bundled sample)",
    )
    p.add_argument(
        "-o",
        "--output",
        metavar="OUT.html",
        default="replay.html",
        help="HTML file to write (default ./replay.html)",
    )
    p.add_argument(
        "--poses",
        metavar="POSES.csv",
        help="use this motion table instead of tracking the sequence",
    )
    p.add_argument(
        "--mode",
        choices=("metric", "paper"),
        help="3D mode (default: metric when the camera is known)",
    )
    p.add_argument("--stride", type=int, default=1, metavar="K", help="every K-th frame")
    p.add_argument("--max-frames", type=int, metavar="N", help="at most N frames")
    p.add_argument(
        "--no-images", action="store_true", help="no mask images on the frustum (much smaller file)"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, no summary")
    p.add_argument("--title", help="the page's title (default: mistool replay: <name>)")
    p.add_argument("--autoplay", action="store_true", help="start playing when opened")
    p.add_argument(
        "--annotations",
        metavar="JSON",
        help="bookmarks to mark on the plots (default: the sequence's annotations.json)",
    )
    p.add_argument(
        "--calibration",
        metavar="FILE",
        help="camera calibration file (OpenCV YAML/XML/JSON or ROS camera_info YAML); "
        "overrides [camera] of mistool.toml",
    )
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="track again even if this unchanged sequence was tracked before",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Export the replay."""
    from mistool.annotations import default_path, load_annotations
    from mistool.export import check_output
    from mistool.resources import sample_masks_dir
    from mistool.sequence import input_files, resolve
    from mistool.viewer import export_html, load_sequence  # viser only for this command

    path, config = resolve(args.sequence if args.sequence is not None else sample_masks_dir())
    check_output(args.output, [*input_files(path, config), args.poses])  # before the work
    progress = not args.quiet and sys.stderr.isatty()
    sequence = load_sequence(
        args.sequence,
        poses=args.poses,
        progress=progress,
        cache=not args.no_cache,
        calibration=args.calibration,
    )
    marks = load_annotations(args.annotations or default_path(path))
    summary = export_html(
        sequence,
        args.output,
        mode=args.mode,
        stride=args.stride,
        max_frames=args.max_frames,
        images=not args.no_images,
        title=args.title,
        autoplay=args.autoplay,
        bookmarks=marks,
    )
    if not args.quiet:
        print(
            f"mistool export-html: {summary.frames} frames ({summary.mode} mode) -> "
            f"{summary.path} ({summary.bytes / 1e6:.1f} MB)"
        )
    return 0
