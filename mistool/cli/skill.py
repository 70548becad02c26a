"""``mistool skill``: surgical skill metrics of one or more recordings (CSV out)."""

from __future__ import annotations

import argparse
import sys

from mistool.errors import ConfigError

DESCRIPTION = """\
Compute motion-based surgical skill metrics, one row per recording x instrument (x time
window), from each instrument's tip (the clasper's metric end; the shaft joint when the
clasper has no 3D estimate) in millimetres, camera frame:

  duration_s           length of the recording (or window)
  visible_s            time with a 3D estimate of the point
  out_of_view_s        time the instrument has no mask pixel at all
  path_length_mm       distance travelled by the point
  depth_perception_mm  distance travelled along the shaft axis (PerkTutor)
  mean_speed_mm_s      path length / time of the continuous runs
  ldlj                 log dimensionless jerk of the speed profile (Balasubramanian et
                       al. 2015), duration-weighted over runs >= 1 s; higher = smoother
  idle_fraction        share of 1-s intervals (track resampled to 1 Hz) moving <= 5 mm/s
  working_volume_cm3   axis-aligned bounding box of the positions (2.5%-97.5% per axis)
  economy_of_volume    cube root of the volume / path length
  movements            runs faster than 50 mm/s lasting >= 0.2 s
  bimanual_dexterity   Pearson r of the two instruments' speeds (two instruments only)

A SOURCE is a motion table (.csv, as written by mistool track; time_s gives the frame
rate) or a mask sequence (folder or mask video; tracked first, with metric pose). The
metrics see the table's own smoothing (mistool track: offline Kalman) plus a Gaussian
low-pass of --smoothing-s along time; gaps <= 0.5 s are bridged. Definitions, sources
and accuracy against ground truth: docs/teaching.md.

examples:
  mistool skill motion.csv -o skill.csv
  mistool skill novice/ expert/ -o skill.csv --window 60s
  mistool skill masks/ -o skill.csv --phases      # per phase bookmark (mistool bookmark)
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``skill`` subcommand."""
    p = subparsers.add_parser(
        "skill",
        help="surgical skill metrics (path length, LDLJ, idle time, volume, ...)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sources", nargs="+", metavar="SOURCE", help="motion table CSV or sequence")
    p.add_argument(
        "-o", "--output", metavar="OUT.csv", help="CSV to write (default: CSV on stdout)"
    )
    p.add_argument("--window", metavar="DURATION", help="also split into windows, e.g. 60s or 2min")
    p.add_argument(
        "--phases",
        action="store_true",
        help="also split at the 'phase' bookmarks (annotations.json of each sequence)",
    )
    p.add_argument(
        "--annotations",
        nargs="+",
        metavar="JSON",
        help="with --phases: bookmark files, one per SOURCE (default: each sequence's)",
    )
    p.add_argument("--fps", type=float, metavar="F", help="frame rate (default: from the data)")
    p.add_argument(
        "--smoothing-s",
        type=float,
        default=None,
        metavar="S",
        help="Gaussian low-pass sigma in seconds (default 0.1; 0 = none)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, no summary")
    p.set_defaults(func=run)


def write_skill_csv(result: dict, out: object) -> None:
    """Write a :func:`mistool.skill.skill` result as CSV to an open text stream."""
    import csv

    from mistool.export import format_value

    writer = csv.writer(out, lineterminator="\n")  # type: ignore[arg-type]
    names = list(result)
    writer.writerow(names)
    n = len(result[names[0]]) if names else 0
    for i in range(n):
        writer.writerow([format_value(result[c][i]) for c in names])


def _phases(args: argparse.Namespace, k: int, rec: object) -> list[tuple[int, str]]:
    """The (start frame, name) of the phase bookmarks of the ``k``-th SOURCE."""
    from mistool.annotations import default_path, load_annotations

    sequence = getattr(rec, "sequence", None)
    if args.annotations:
        path = args.annotations[k]
    elif sequence is not None:
        path = default_path(sequence)
    else:
        raise ConfigError(
            f"--phases: {args.sources[k]} is a table; give its bookmarks with --annotations"
        )
    return [(b.frame, b.text) for b in load_annotations(path) if b.kind == "phase"]


def run(args: argparse.Namespace) -> int:
    """Run ``mistool skill``."""
    import mistool.skill as sk  # the module (mistool.skill is also callable)
    from mistool.cli._recording import open_recording, unique_names
    from mistool.config import FPS_RANGE, check_number
    from mistool.export import atomic_write, check_output, stdout_stream, write_stdout
    from mistool.sequence import inputs_of

    if args.fps is not None:
        check_number("--fps", args.fps, *FPS_RANGE)
    if args.output not in (None, "-"):  # before the work; never over an input
        check_output(args.output, [p for s in args.sources for p in inputs_of(s)])
    else:
        stdout_stream()
    smoothing = sk.SMOOTHING_S if args.smoothing_s is None else args.smoothing_s
    if not smoothing >= 0:
        raise ConfigError(f"--smoothing-s must be >= 0, got {args.smoothing_s}")
    window = sk.parse_window(args.window)
    if args.phases and window is not None:
        raise ConfigError("give --window or --phases, not both")
    if args.annotations and len(args.annotations) != len(args.sources):
        raise ConfigError(
            f"--annotations gives {len(args.annotations)} file(s) for "
            f"{len(args.sources)} SOURCE(s); give one per SOURCE"
        )
    recordings = [open_recording(s, progress=not args.quiet) for s in args.sources]
    unique_names(recordings)
    results = []
    for k, r in enumerate(recordings):
        sk.check_table(r.table, r.name)
        phases = _phases(args, k, r) if args.phases else None
        results.append(
            sk.skill(
                r.table,
                recording=r.name,
                num_frames=r.num_frames,
                fps=args.fps or r.fps,
                window_s=window,
                phases=phases,
                smoothing_s=smoothing,
            )
        )
    result = sk.concat(results)
    if args.output in (None, "-"):
        write_stdout(lambda stream: write_skill_csv(result, stream))
    else:
        with atomic_write(args.output, "w", newline="", encoding="utf-8") as f:
            write_skill_csv(result, f)
        if not args.quiet:
            print(
                f"mistool skill: {len(result['instrument'])} row(s) from "
                f"{len(recordings)} recording(s) -> {args.output}",
                file=sys.stderr,
            )
    return 0
