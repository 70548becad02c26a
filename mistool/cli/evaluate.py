"""``mistool eval``: score motion tables against ground truth (e.g. ``mistool synth``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mistool.errors import ConfigError

DESCRIPTION = """\
Score one or more motion tables (CSV, as written by mistool track) against a ground-truth
table (e.g. truth.csv of mistool synth) and print two tables, several predictions side by
side (one line per method under each part):

  Table 1 (the paper's Table 1 layout): per part, coverage (truth rows that have an
    estimate, among rows where the part is visible), extra (predicted rows with no truth
    row), and mean ± sd of the absolute error of the box centre x, y (px) and of the box
    angle θ (degrees, modulo 180).
  Table 2 (the paper's Table 2 layout, per part): coverage of the metric estimate, mean ±
    sd of the absolute error of the distal end x, y, z (mm; shaft: joint J, clasper: tip),
    the median 3D end-point error, and the axis angle error (deg), median and p90.

The truth is the LAST positional file, or the one given with --truth (then every
positional file is a prediction). Rows are matched by (frame, instrument, part). With
merged masks a prediction names instruments its own way, so predicted instruments are
matched one-to-one to truth instruments by the Hungarian algorithm on the mean distance
between their box centres (the mapping is printed). Truth rows whose clean area is below
--min-area px are left out (the tracker ignores such specks by default).

Outputs (written atomically): --json M.json (every number, machine-readable) and
--per-frame F.csv (one row per method x truth row: the errors, empty where no estimate).

examples:
  mistool eval /tmp/p.csv /tmp/s/truth.csv
  mistool eval paper.csv metric.csv /tmp/s/truth.csv --json scores.json
  mistool eval run*.csv --truth /tmp/s/truth.csv --per-frame errors.csv
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``eval`` subcommand."""
    p = subparsers.add_parser(
        "eval",
        help="score motion tables against ground truth",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "files",
        nargs="+",
        metavar="CSV",
        help="PRED.csv [PRED2.csv ...] TRUTH.csv (or only predictions with --truth)",
    )
    p.add_argument("--truth", metavar="TRUTH.csv", help="the ground-truth table")
    p.add_argument(
        "--names",
        nargs="+",
        metavar="NAME",
        help="method names, one per prediction (default: file names)",
    )
    p.add_argument(
        "--min-area",
        type=int,
        default=20,
        metavar="PX",
        help="leave out truth rows with a clean area below PX (default 20)",
    )
    p.add_argument("--json", metavar="M.json", help="also write every score as JSON")
    p.add_argument("--per-frame", metavar="F.csv", help="also write per-row errors as CSV")
    p.set_defaults(func=run)


def _method_names(paths: list[Path]) -> list[str]:
    names = [p.stem for p in paths]
    if len(set(names)) < len(names):
        names = [str(p) for p in paths]
    return names


def run(args: argparse.Namespace) -> int:
    """Run ``mistool eval``."""
    from mistool.columnar import read_any
    from mistool.evaluation import evaluate, format_report
    from mistool.export import atomic_write, check_output, write_table_csv

    files = [Path(f) for f in args.files]
    if args.truth is None:
        if len(files) < 2:
            raise ConfigError(
                "eval: give PRED.csv and TRUTH.csv (the truth last), or --truth TRUTH.csv"
            )
        truth_path, pred_paths = files[-1], files[:-1]
    else:
        truth_path, pred_paths = Path(args.truth), files
    names = args.names or _method_names(pred_paths)
    if len(names) != len(pred_paths):
        raise ConfigError(
            f"eval: --names gives {len(names)} name(s) for {len(pred_paths)} prediction(s)"
        )
    if len(set(names)) != len(names):
        raise ConfigError(f"eval: method names must differ, got {names}")
    if args.min_area < 0:
        raise ConfigError(f"eval: --min-area must be >= 0, got {args.min_area}")
    for out in (args.json, args.per_frame):  # before the work; never over an input
        if out:
            check_output(out, [truth_path, *pred_paths])
    truth = read_any(truth_path)  # CSV, or a columnar .npz / .parquet table
    preds = {n: read_any(p) for n, p in zip(names, pred_paths, strict=True)}
    report = evaluate(preds, truth, min_area_px=args.min_area)
    if args.json:
        with atomic_write(args.json, "w", encoding="utf-8") as f:
            json.dump({"truth": str(truth_path), **report.to_dict()}, f, indent=2)
            f.write("\n")
    if args.per_frame:
        with atomic_write(args.per_frame, "w", newline="", encoding="utf-8") as f:
            write_table_csv(report.per_frame(), f)
    sys.stdout.write(format_report(report))
    return 0
