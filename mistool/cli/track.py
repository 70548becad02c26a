"""``mistool track``: a mask sequence in, the motion table (CSV) out."""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

from mistool.config import PRESETS
from mistool.errors import ConfigError, InputPathError

DESCRIPTION = """\
Track every surgical instrument part through a sequence of segmentation masks and write
the motion table: per frame, instrument and part, the rotated box (the paper's Algorithm 1),
the paper's frame-to-frame 3D motion (Algorithm 2) and, when the camera is known, the
metric 3D pose in millimetres.

A sequence is a folder of label images (PNG first; 8/16-bit grey, palette, grey saved as
RGB, or colour masks) whose names sort naturally into frame order (frame2.png before
frame10.png), or a mask video file (.avi/.mp4). For videos and JPEG frames, single label
values are widened by +-15 to absorb the lossy codec's smearing. Other files in the
folder are ignored.

An optional mistool.toml beside the frames (or beside the video) says what the pixels
mean; without one, EndoVis'15 defaults apply (shaft 160, clasper 70, 25 fps):

  fps = 25.0
  labels = "endovis15"      # or "endovis17" (10/20/30), "ternaus" (85/170/255)
  min_area_px = 20          # specks smaller than this are ignored
  [parts]                   # override the preset: a value, [lo, hi] or "#rrggbb"
  shaft = 160
  clasper = [60, 80]
  [camera]                  # enables metric 3D (end_*_mm, axis_*)
  fx = 580.0
  fy = 580.0
  cx = 359.5
  cy = 287.5
  [[instrument]]            # instruments with their own label values (else merged
  name = "left"             # masks: instruments told apart by connectivity)
  shaft = 160
  clasper = 70

Command-line options override the file.

Output: a CSV, one row per frame x instrument x part seen (an absent part has no row;
an unknown value is an empty cell). Columns: frame, time_s, instrument, part,
cx_px, cy_px, length_px, width_px, angle_deg (rotated box; angle of the long side in
[0, 180) degrees from +x towards +y, y down), area_px, x1_px..y4_px (box corners),
dx_px, dy_px, dz, droll_deg, dpitch_deg, dyaw_deg (paper motion), paper_* (the paper's
per-frame quantities), end_x_mm..axis_z, start_*_mm, qw..qz, quality, trocar_*_mm
(metric pose, camera frame in mm). The default output is ./<sequence name>_motion.csv
in the current folder (its parent when run inside the input folder: mistool never writes
into the input folder unless -o says so); the file is written atomically.

examples:
  mistool track masks/                      # -> ./masks_motion.csv
  mistool track masks/ -o motion.csv --fps 30
  mistool track Dataset1/Segmentation.avi --labels endovis15
  mistool track seq/ -o - --quiet | head    # CSV on stdout
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``track`` subcommand."""
    p = subparsers.add_parser(
        "track",
        help="mask sequence -> motion table (CSV)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "sequence", metavar="SEQUENCE", help="folder of label images, or a mask video file"
    )
    p.add_argument(
        "-o",
        "--output",
        metavar="OUT.csv",
        help="output CSV ('-' for stdout; default ./<name>_motion.csv)",
    )
    p.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="no progress bar and no summary line (errors and warnings only)",
    )
    p.add_argument("--fps", type=float, metavar="F", help="frames per second (time_s)")
    p.add_argument(
        "--labels",
        choices=sorted(PRESETS),
        metavar="PRESET",
        help=f"label preset: {', '.join(PRESETS)} (replaces [parts])",
    )
    p.add_argument(
        "--min-area", type=int, metavar="PX", help="ignore connected specks smaller than PX pixels"
    )
    p.add_argument(
        "--no-metric",
        action="store_true",
        help="skip the metric 3D pose even when [camera] is given",
    )
    p.add_argument(
        "--smoothing",
        choices=("none", "offline", "online"),
        default="offline",
        help="temporal filtering of the metric pose (default: offline)",
    )
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="worker processes for the per-frame work (default: the CPU cores; the output "
        "is the same whatever N)",
    )
    p.set_defaults(func=run_track)


def default_output(source: Path) -> Path:
    """``./<name>_motion.csv`` in the current folder (a video adds its folder's name);
    when the current folder is the input folder, its parent folder instead."""
    src = source.resolve()
    folder = src if src.is_dir() else src.parent
    name = src.name if src.is_dir() else f"{src.parent.name}_{src.stem}"
    out = Path(f"{name or 'sequence'}_motion.csv")
    if Path.cwd().resolve() == folder:  # never write into the input folder unasked
        out = folder.parent / out
    return out


def run_track(args: argparse.Namespace) -> int:
    """Run ``mistool track``; returns the exit code."""
    from mistool import api, sequence
    from mistool.export import write_csv, write_table_csv

    if args.fps is not None and not args.fps > 0:
        raise ConfigError(f"--fps must be > 0, got {args.fps}")
    if args.min_area is not None and args.min_area < 0:
        raise ConfigError(f"--min-area must be >= 0, got {args.min_area}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    path, config = sequence.resolve(args.sequence)
    overrides: dict[str, object] = {"fps": args.fps, "min_area_px": args.min_area}
    if args.labels:
        overrides.update(
            labels=args.labels,
            colour_masks=False,
            parts={p: (v, v) for p, v in PRESETS[args.labels].items()},
        )
    config = config.with_overrides(**overrides)
    out = None if args.output == "-" else Path(args.output or default_output(path))
    if out is not None and not (out.parent if str(out.parent) else Path(".")).is_dir():
        raise InputPathError(f"{out}: output folder {out.parent} does not exist")
    if out is not None and out.is_dir():
        raise InputPathError(f"{out}: is a folder; expected an output file name (-o OUT.csv)")
    show_progress = not args.quiet and sys.stderr.isatty()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", api.MistoolWarning)
        result = api.run(
            path,
            config,
            progress=show_progress,
            workers=args.workers,
            metric=not args.no_metric,
            smoothing=args.smoothing,
        )
    if result.unknown_values:
        print(
            "mistool: warning: "
            + api.unknown_values_message(result.unknown_values, result.config.colour_masks),
            file=sys.stderr,
        )
    if out is None:
        write_table_csv(result.table.full(), sys.stdout)
        sys.stdout.flush()
    else:
        write_csv(result.table, out)
    if not args.quiet:
        n_inst, parts = len(result.instruments), result.parts
        rate = result.num_frames / result.seconds if result.seconds > 0 else float("inf")
        print(
            f"mistool: {result.num_frames} frame(s), {n_inst} instrument(s), "
            f"parts: {', '.join(parts) or 'none'}, {result.table.num_rows} rows, "
            f"{result.seconds:.1f} s ({rate:.0f} frames/s)"
            f"{'' if result.metric else ', no metric 3D'} -> {out or 'stdout'}",
            file=sys.stderr,
        )
    return 0
