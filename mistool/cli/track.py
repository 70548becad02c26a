"""``mistool track``: a mask sequence (or a dataset of them) in, motion tables out."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
import warnings
from pathlib import Path
from typing import Any

from mistool.config import COLOUR_PRESETS, FPS_RANGE, PRESETS, check_number
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

Output formats by the suffix of -o: .csv (the default), .npz (numpy, every value
exact), .parquet (needs pyarrow). The per-frame work runs in --workers processes (default:
the CPU cores), or on a Dask cluster with --dask; the table is the same either way.

A dataset: a folder that holds sequence folders and/or mask videos (and no label images
of its own). Every sequence is tracked into OUT/<name>_motion.csv (--format), the same
table `mistool track SEQ` gives; OUT/summary.csv lists each sequence's frames,
instruments, seconds, status and error. A mistool.toml at the dataset's root gives
defaults that a sequence's own mistool.toml overrides key by key. A broken sequence is
reported (one line) and skipped, the others go on, and the exit code is 1 at the end.
Re-running skips sequences whose output is up to date (resume after a crash or Ctrl+C).

Dask (pip install "mistool[dask]"): --dask tcp://scheduler:8786 sends the per-frame work
of every sequence, in chunks of frames, to the workers of an existing cluster; they read
the mask files by the same paths, so the data must be on a filesystem they share. See
docs/throughput.md.

examples:
  mistool track masks/                      # -> ./masks_motion.csv
  mistool track masks/ -o motion.npz --workers 2
  mistool track dataset/ -o out/            # out/<sequence>_motion.csv + out/summary.csv
  mistool track dataset/ -o out/ --dask tcp://scheduler:8786
  mistool track masks/ -o motion.csv --fps 30
  mistool track Dataset1/Segmentation.avi --labels endovis15
  mistool track seq/ -o - --quiet | head    # CSV on stdout
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``track`` subcommand."""
    p = subparsers.add_parser(
        "track",
        help="mask sequence (or a dataset of them) -> motion table(s)",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "sequence",
        metavar="SEQUENCE",
        help="folder of label images, a mask video file, or a dataset folder of them",
    )
    p.add_argument(
        "-o",
        "--output",
        metavar="OUT",
        help="output table .csv/.npz/.parquet ('-' for CSV on stdout; default "
        "./<name>_motion.csv); for a dataset, the output folder (default ./<name>_motion/)",
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
        "--calibration",
        metavar="FILE",
        help="camera calibration file (OpenCV YAML/XML/JSON or ROS camera_info YAML); "
        "overrides [camera] of mistool.toml",
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
    p.add_argument(
        "--dask",
        metavar="ADDRESS",
        help="run the per-frame work on an existing Dask cluster, e.g. tcp://host:8786 "
        "(inputs on a filesystem the workers share)",
    )
    p.add_argument(
        "--format",
        choices=("csv", "npz", "parquet"),
        default=None,
        help="a dataset's table format (default csv); a single sequence's comes from -o",
    )
    p.set_defaults(func=run_track)


def default_output(source: Path, suffix: str = ".csv") -> Path:
    """``./<name>_motion.csv`` in the current folder (a video adds its folder's name);
    when the current folder is the input folder, its parent folder instead."""
    src = source.resolve()
    folder = src if src.is_dir() else src.parent
    name = src.name if src.is_dir() else f"{src.parent.name}_{src.stem}"
    out = Path(f"{name or 'sequence'}_motion{suffix}")
    if Path.cwd().resolve() == folder:  # never write into the input folder unasked
        out = folder.parent / out
    return out


def _check_options(args: argparse.Namespace) -> None:
    if args.fps is not None:
        check_number("--fps", args.fps, *FPS_RANGE)
    if args.min_area is not None and args.min_area < 0:
        raise ConfigError(f"--min-area must be >= 0, got {args.min_area}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {args.workers}")
    if args.dask is not None and args.workers is not None:
        raise ConfigError("--workers and --dask exclude each other (Dask has its own workers)")


def _overrides(args: argparse.Namespace) -> dict[str, object]:
    overrides: dict[str, object] = {"fps": args.fps, "min_area_px": args.min_area}
    if args.labels:
        overrides.update(
            labels=args.labels,
            colour_masks=args.labels in COLOUR_PRESETS,
            parts={p: (v, v) for p, v in PRESETS[args.labels].items()},
        )
    return overrides


def _pool(args: argparse.Namespace, local: bool) -> Any:
    """The Dask pool for --dask, a local pool when ``local`` and workers > 1, else None."""
    from mistool import parallel

    if args.dask is not None:
        return parallel.DaskPool(args.dask)
    workers = args.workers or parallel.default_workers()
    return parallel.LocalPool(workers) if local and workers > 1 else None


def _start_numba() -> None:
    """numba started without its BLAS check (this process is mistool's own: no kernel
    calls a BLAS; :func:`mistool.numbaload.start_without_blas`)."""
    from mistool.numbaload import start_without_blas

    start_without_blas()


def run_track(args: argparse.Namespace) -> int:
    """Run ``mistool track``; returns the exit code."""
    _check_options(args)
    path = Path(args.sequence).expanduser()
    if _pool_likely(args, path):
        from mistool import forkserver

        forkserver.start()  # loading while the rest of mistool is imported and inputs read
    from mistool import dataset

    if dataset.is_dataset(path):
        return _run_dataset(args, path)
    return _run_sequence(args)


#: ``mistool.api.POOL_MIN_FRAMES`` (not imported here: that import is what the early
#: start overlaps; a test keeps the two equal).
_POOL_MIN_FRAMES = 1000


def _pool_likely(args: argparse.Namespace, path: Path) -> bool:
    """Whether this run will start local worker processes: ``--workers`` above 1, or by
    default with more than one core on a folder of at least ``POOL_MIN_FRAMES`` files
    with an image's extension (a plain count, stopped there; a mask video or a dataset:
    no early start)."""
    from mistool.forkserver import default_workers

    if args.dask is not None:
        return False
    if args.workers is not None:
        return args.workers > 1
    if default_workers() < 2:
        return False
    from mistool.sequence import IMAGE_EXTENSIONS  # (OpenCV: imported by the run anyway)

    count = 0
    try:
        with os.scandir(path) as entries:
            for entry in entries:
                if os.path.splitext(entry.name)[1].lower() in IMAGE_EXTENSIONS:
                    count += 1
                    if count >= _POOL_MIN_FRAMES:
                        return True
    except OSError:  # not a folder, or not readable: the run says what is wrong
        return False
    return False


def _run_sequence(args: argparse.Namespace) -> int:
    from mistool import api, sequence
    from mistool.calibration import with_calibration
    from mistool.columnar import table_format, write_table
    from mistool.export import STDOUT, check_output, stdout_stream, write_stdout, write_table_csv

    path, config = sequence.resolve(args.sequence)
    config = with_calibration(config.with_overrides(**_overrides(args)), args.calibration)
    out = None if args.output == STDOUT else Path(args.output or default_output(path))
    entries = sequence.scan_frames(path) if path.is_dir() else None  # listed once
    frames = [path / e.name for e in entries] if entries is not None else None
    if out is None:
        stdout_stream()  # closed stdout: say so before tracking
    else:
        inputs = sequence.input_files(path, config, frames)
        listed = len(frames) if frames is not None else 0  # (they come first)
        check_output(out, inputs[listed:], existing=entries or ())
        table_format(out)
    show_progress = not args.quiet and sys.stderr.isatty()
    _start_numba()
    pool = _pool(args, local=False)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", api.MistoolWarning)
            result = api.run(
                sequence.open_sequence(path, config, files=frames),
                config,
                progress=show_progress,
                workers=args.workers,
                metric=not args.no_metric,
                smoothing=args.smoothing,
                pool=pool,
            )
    finally:
        if pool is not None:
            pool.close()
    if result.unknown_values:
        print(
            "mistool: warning: "
            + api.unknown_values_message(result.unknown_values, result.config.colour_masks),
            file=sys.stderr,
        )
    if out is None:
        full = result.table.full()
        write_stdout(lambda stream: write_table_csv(full, stream))
    else:
        write_table(result.table, out)
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


def _run_dataset(args: argparse.Namespace, root: Path) -> int:
    from mistool import dataset

    if args.output == "-":
        raise InputPathError(f"{root}: a dataset needs an output folder (-o OUT/), not stdout")
    fmt = "." + (args.format or "csv")
    out = Path(args.output) if args.output else default_output(root, suffix="")
    if out.exists() and not out.is_dir():
        raise InputPathError(f"{out}: is a file; a dataset needs an output folder (-o OUT/)")
    if fmt == ".parquet":
        from mistool.columnar import _pyarrow

        _pyarrow()
    options = dataset.Options(
        metric=not args.no_metric,
        smoothing=args.smoothing,
        overrides={k: v for k, v in _overrides(args).items() if v is not None},
        fmt=fmt,
    )
    entries = dataset.discover(root, exclude=out)
    progress = _DatasetProgress(not args.quiet and sys.stderr.isatty(), len(entries))

    def report(line: str) -> None:
        progress.write(f"mistool: error: {line}" if "\n" not in line else line)

    _start_numba()
    start = time.perf_counter()
    finished = False
    try:
        with _pool(args, local=True) or contextlib.nullcontext() as pool:
            outcomes = dataset.track_dataset(
                root,
                out,
                options,
                pool=pool,
                on_error=report,
                on_sequence=progress.sequence,
                on_frames=progress.frames,
            )
        finished = True
    finally:
        progress.close(finished)
    bad = dataset.failed(outcomes)
    if not args.quiet:
        done = sum(o.status == dataset.STATUS_OK for o in outcomes)
        skipped = sum(o.status == dataset.STATUS_SKIPPED for o in outcomes)
        frames = sum(o.frames for o in outcomes if o.status == dataset.STATUS_OK)
        print(
            f"mistool: {len(outcomes)} sequence(s): {done} tracked ({frames} frames), "
            f"{skipped} up to date, {len(bad)} failed, {time.perf_counter() - start:.1f} s "
            f"-> {out / dataset.SUMMARY_NAME}",
            file=sys.stderr,
        )
    return 1 if bad else 0


class _DatasetProgress:
    """Two tqdm bars on stderr: sequences done, and frames tracked (all sequences)."""

    def __init__(self, enabled: bool, sequences: int) -> None:
        self.enabled = enabled
        self._total = sequences
        self._seq: Any = None
        self._frames: Any = None

    def sequence(self, entry: Any, n_frames: int | None) -> None:
        """A sequence starts (the one before it is done)."""
        if not self.enabled:
            return
        if self._seq is None:
            from tqdm import tqdm

            self._seq = tqdm(
                total=self._total, unit="seq", desc="sequences", position=0, dynamic_ncols=True
            )
            self._frames = tqdm(unit="frame", desc="frames", position=1, dynamic_ncols=True)
        else:
            self._seq.update(1)
        self._seq.set_postfix_str(entry.name, refresh=True)

    def frames(self, n: int) -> None:
        """``n`` more frames tracked."""
        if self._frames is not None:
            self._frames.update(n)

    def write(self, line: str) -> None:
        """A line on stderr that does not break the bars."""
        if self._seq is not None:
            from tqdm import tqdm

            tqdm.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr)

    def close(self, finished: bool) -> None:
        """Remove the bars (``finished``: count the last sequence as done)."""
        if self._seq is not None and finished:
            self._seq.update(1)
        for bar in (self._frames, self._seq):
            if bar is not None:
                bar.close()
