"""``mistool report``: a self-contained offline HTML report for a teacher."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mistool.errors import ConfigError

DESCRIPTION = """\
Write one HTML file, self-contained and offline (inline styles and SVG plots, no script,
no network), that opens in any browser without a server: per recording, the skill
metrics of each instrument (see 'mistool skill --help'), its bookmarks, the tip's speed
and depth over time with the bookmarks marked, and the tip path in three projections.
With two recordings, a comparison comes first: per metric, which recording is better
(the direction -- lower or higher is better -- is stated per metric) and by how much.

A SOURCE is a motion table (.csv) or a mask sequence (folder or mask video; tracked
first). Bookmarks are read from each sequence's annotations.json (see docs/teaching.md),
or from --annotations files, one per SOURCE in order.

examples:
  mistool report masks/ -o report.html
  mistool report novice.csv expert.csv -o compare.html --annotations a.json b.json
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``report`` subcommand."""
    p = subparsers.add_parser(
        "report",
        help="self-contained offline HTML report (metrics, plots, comparison)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("sources", nargs="+", metavar="SOURCE", help="motion table CSV or sequence")
    p.add_argument(
        "-o", "--output", metavar="OUT.html", default="report.html", help="default report.html"
    )
    p.add_argument("--title", default="mistool report", help="the report's title")
    p.add_argument(
        "--annotations",
        nargs="+",
        metavar="JSON",
        help="bookmark files, one per SOURCE (default: each sequence's annotations.json)",
    )
    p.add_argument(
        "--smoothing-s",
        type=float,
        default=None,
        metavar="S",
        help="Gaussian low-pass sigma in seconds (default 0.1; 0 = none)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar, no summary")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``mistool report``."""
    from mistool.annotations import default_path, load_annotations
    from mistool.cli._recording import open_recording, unique_names
    from mistool.export import check_output
    from mistool.report import ReportRecording, write_report
    from mistool.sequence import inputs_of
    from mistool.skill import SMOOTHING_S, check_table

    if args.annotations and len(args.annotations) != len(args.sources):
        raise ConfigError(
            f"--annotations gives {len(args.annotations)} file(s) for "
            f"{len(args.sources)} SOURCE(s); give one per SOURCE"
        )
    smoothing = SMOOTHING_S if args.smoothing_s is None else args.smoothing_s
    if not smoothing >= 0:
        raise ConfigError(f"--smoothing-s must be >= 0, got {args.smoothing_s}")
    out = Path(args.output)
    sources = [p for s in args.sources for p in inputs_of(s)]
    check_output(out, [*sources, *(args.annotations or [])])  # before the work
    recordings = [open_recording(s, progress=not args.quiet) for s in args.sources]
    unique_names(recordings)
    inputs = []
    for k, r in enumerate(recordings):
        check_table(r.table, r.name)
        if args.annotations:
            marks = load_annotations(args.annotations[k])
        else:
            marks = load_annotations(default_path(r.sequence)) if r.sequence else []
        inputs.append(ReportRecording(r.name, r.table, r.num_frames, r.fps, marks))
    write_report(out, inputs, title=args.title, smoothing_s=smoothing)
    if not args.quiet:
        print(
            f"mistool report: {len(inputs)} recording(s) -> {out} "
            f"({out.stat().st_size / 1e3:.0f} kB)",
            file=sys.stderr,
        )
    return 0
