"""``mistool export-video``: the replay as a video file for slides (headless)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

DESCRIPTION = """\
Write the replay of a sequence as a video for slides, without a display or a browser:
the 3D view (each instrument's parts as cylinders, drawn from a fixed oblique viewpoint,
with the tips' trails and the endoscope) and the 2D overlay (the mask coloured per
instrument, rotated boxes) side by side, and below them a frame counter (frame, time in
seconds, fps), the legend and the bookmarks as captions (annotations.json of the
sequence, or --annotations). H.264 (libx264, through PyAV's bundled FFmpeg) where
available, else OpenCV's mp4v; at the sequence's fps; written atomically.

The sequence is tracked first unless --poses gives its motion table.

examples:
  mistool export-video masks/ -o replay.mp4
  mistool export-video masks/ -o replay.mp4 --poses motion.csv --max-frames 250
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``export-video`` subcommand."""
    p = subparsers.add_parser(
        "export-video",
        help="the replay as a video (3D view + 2D overlay, captions)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sequence", metavar="SEQUENCE", help="folder of label images or mask video")
    p.add_argument(
        "-o", "--output", metavar="OUT.mp4", default="replay.mp4", help="default replay.mp4"
    )
    p.add_argument("--poses", metavar="POSES.csv", help="use this motion table, do not track")
    p.add_argument("--annotations", metavar="JSON", help="bookmarks file (default: the sequence's)")
    p.add_argument(
        "--codec",
        choices=("auto", "h264", "mp4v"),
        default="auto",
        help="auto: H.264 when available, else mp4v",
    )
    p.add_argument("--max-frames", type=int, metavar="N", help="at most N frames")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, no summary")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``mistool export-video``."""
    from mistool.annotations import default_path, load_annotations
    from mistool.cli._recording import open_recording
    from mistool.errors import InputPathError
    from mistool.export import check_output
    from mistool.sequence import inputs_of, open_sequence
    from mistool.video import export_video

    # before the work: the video never replaces an input
    check_output(args.output, [*inputs_of(args.sequence), args.poses, args.annotations])
    rec = open_recording(args.sequence, poses=args.poses, progress=not args.quiet)
    if rec.sequence is None or rec.config is None:
        raise InputPathError(
            f"{args.sequence}: export-video needs the mask sequence (folder or video); "
            "give a motion table with --poses"
        )
    seq_path, config = rec.sequence, rec.config
    marks = load_annotations(args.annotations or default_path(seq_path))
    seq = open_sequence(seq_path, config)
    first = next(iter(seq), None)
    if first is None:
        raise InputPathError(f"{rec.sequence}: no frames")
    h, w = first[2].shape[:2]
    num = rec.num_frames or seq.num_frames or int(rec.table["frame"].max(initial=0)) + 1
    summary = export_video(
        rec.table,
        lambda: ((i, lab) for i, _, lab in open_sequence(seq_path, config)),
        seq.config,
        Path(args.output),
        image_wh=(w, h),
        num_frames=num,
        bookmarks=marks,
        codec=args.codec,
        max_frames=args.max_frames,
        progress=not args.quiet and sys.stderr.isatty(),
    )
    if not args.quiet:
        print(
            f"mistool export-video: {summary.frames} frames, {summary.size_wh[0]}x"
            f"{summary.size_wh[1]} at {summary.fps:g} fps ({summary.codec}) -> {summary.path}",
            file=sys.stderr,
        )
    return 0
