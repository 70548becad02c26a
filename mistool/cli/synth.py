"""``mistool synth``: render a synthetic mask sequence with exact 3D ground truth."""

from __future__ import annotations

import argparse
import sys
import time

from mistool.config import COLOUR_PRESETS, PRESETS
from mistool.errors import ConfigError

DESCRIPTION = """\
Render a synthetic sequence of instrument segmentation masks with its exact ground truth,
as a folder every other mistool command opens as it is.

Scene: a pinhole camera (default 720x576, f = 600 px, principal point at the centre) looks
at 1-4 instruments. Each is a long cylindrical shaft (8 mm robotic; --tool laparoscopic:
5 mm, no wrist bending) pivoting about its own trocar point outside the view, a wrist, and
two jaws. Tools enter from out of view, pivot, insert and retract, roll, bend their wrist
and open and close their jaws (grasping) at depths of 50-150 mm; two tools cross.
Masks are ray cast: each pixel is labelled by the first 3D surface its ray hits (exact
projection of the model at pixel centres, nearer surfaces hide farther ones).

Written into OUT (created; it must be absent or empty; --force replaces an earlier
mistool synth output, recognised by its synth.json, never any other folder; written to a
temporary folder and renamed, so a failure leaves nothing behind):
  000000.png ...   8-bit label images (the masks, corrupted if asked)
  mistool.toml     fps, labels preset, [camera], shaft_diameter_mm, clasper_length_mm
                   (and [[instrument]] tables with --distinct-labels)
  truth.csv        the motion table of the truth: boxes of the clean masks (per instrument,
                   its own visible pixels), end_*_mm (shaft: joint J, wrist: jaw pivot W,
                   clasper: tip = middle of the jaw tips) and axis_* exactly from the 3D
                   model; parts are linked segments start_*_mm -> end_*_mm (shaft from the
                   trocar; without a wrist label the clasper runs J -> tip), qw..qz
                   (part frame, z distal), trocar_*_mm, visible_frac (share of the part
                   not hidden by another tool), the paper's motion of the clean
                   boxes, and extras roll_deg, wrist_deg, jaw_yaw_deg, jaw_open_deg,
                   insertion_mm. A row exists where the part has >= 1 clean pixel.
  mask_areas.csv   per truth row (frame, instrument, part): mask_area_px, its pixels left
                   in the written (corrupted) masks
  synth.json       the options and seed
  masks.avi        with --video: the same masks through a lossy codec

Label values: by default all instruments share the preset's values, as in the real
datasets (endovis15: shaft 160, clasper 70 -- the wrist is painted as clasper;
endovis17: shaft 10, wrist 20, clasper 30; ternaus: 85/170/255); instruments are then
told apart by connectivity and are named 1, 2, ... in truth.csv (mistool eval matches
names). --distinct-labels gives instrument i (0-based) the values v - i instead.

Corruptions (all off by default, seeded, they change the masks and never truth.csv):
  --jitter PX        boundaries wobble by up to PX px (smooth random displacement field)
  --bias PX          over-segmentation: every outline moved outward by PX px (inward if
                     negative), sub-pixel exact (e.g. 0.5), rendered at each part's depth
  --holes N          about N specular-highlight holes per frame on the tools (2-7 px)
  --speckle N        about N label specks per frame (1-3 px, random part values)
  --occluders N      N tissue blobs (30-90 px) hovering over the tools' heads, hiding them
  --hide-clasper F   the clasper (and wrist) hidden in a fraction F of the frames, in runs
  --video CODEC      also write masks.avi with a lossy codec (mjpg, xvid, mp4v; values
                     smeared by up to ~20 grey levels at edges with mjpg, ~40 with xvid);
                     the toml then gives value ranges wide enough for the smeared values
The tool leaving the view is a motion, not a mask corruption, so the truth follows it
(no rows while a tool is out of view): --leave-view (each tool retracts out of the view
once and comes back). Other motion options: --no-enter (tools present from the first
frame), --no-cross (tools keep to their side).

examples:
  mistool synth /tmp/s --frames 60 --instruments 2
  mistool synth /tmp/s --preset endovis17 --jitter 2 --occluders 2 --force
  mistool synth /tmp/s && mistool track /tmp/s -o /tmp/p.csv && \\
      mistool eval /tmp/p.csv /tmp/s/truth.csv
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``synth`` subcommand."""
    p = subparsers.add_parser(
        "synth",
        help="render synthetic masks with exact 3D ground truth",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("out", metavar="OUT", help="sequence folder to create")
    p.add_argument(
        "--frames", type=int, default=100, metavar="N", help="number of frames (default 100)"
    )
    p.add_argument(
        "--instruments",
        type=int,
        default=2,
        metavar="K",
        help="number of instruments, 1-4 (default 2)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        metavar="S",
        help="random seed of the motion and corruptions (default 0)",
    )
    p.add_argument(
        "--preset",
        choices=sorted(set(PRESETS) - COLOUR_PRESETS),
        default="endovis15",
        help="label values (default endovis15)",
    )
    p.add_argument(
        "--fps", type=float, default=25.0, metavar="F", help="frames per second (default 25)"
    )
    p.add_argument(
        "--distinct-labels",
        action="store_true",
        help="each instrument its own label values and [[instrument]] table",
    )
    g = p.add_argument_group("scene")
    g.add_argument("--size", default="720x576", metavar="WxH", help="image size (default 720x576)")
    g.add_argument(
        "--focal", type=float, default=600.0, metavar="PX", help="focal length in px (default 600)"
    )
    g.add_argument(
        "--distortion",
        metavar="K1,K2,P1,P2[,K3,...]",
        help="lens distortion in OpenCV's order (4, 5, 8, 12 or 14 values; fisheye: 4), "
        "e.g. -0.22,0.05,0,0,0 for ~16%% barrel at the corners of 720x576 at f = 600; "
        "the masks are rendered through it exactly and mistool.toml gets it",
    )
    g.add_argument(
        "--lens",
        choices=("pinhole", "fisheye"),
        default="pinhole",
        help="lens model of --distortion (default pinhole)",
    )
    g.add_argument(
        "--tool",
        choices=("robotic", "laparoscopic"),
        default="robotic",
        help="robotic: 8 mm shaft, bending wrist (default); laparoscopic: 5 mm",
    )
    g.add_argument(
        "--shaft-diameter",
        type=float,
        metavar="MM",
        help="shaft diameter in mm (scales the tool's head too)",
    )
    g.add_argument(
        "--leave-view",
        action="store_true",
        help="each tool retracts out of the view once and comes back",
    )
    g.add_argument(
        "--no-enter",
        action="store_true",
        help="tools present from the first frame instead of entering",
    )
    g.add_argument("--no-cross", action="store_true", help="tools do not cross")
    c = p.add_argument_group("corruptions (see above)")
    c.add_argument(
        "--jitter", type=float, default=0.0, metavar="PX", help="boundary jitter amplitude"
    )
    c.add_argument(
        "--bias",
        type=float,
        default=0.0,
        metavar="PX",
        help="outlines moved outward (> 0) or inward (< 0) by PX px, sub-pixel (e.g. 0.5)",
    )
    c.add_argument("--holes", type=float, default=0.0, metavar="N", help="specular holes per frame")
    c.add_argument("--speckle", type=float, default=0.0, metavar="N", help="label specks per frame")
    c.add_argument(
        "--occluders", type=int, default=0, metavar="N", help="tissue blobs over the tools"
    )
    c.add_argument(
        "--hide-clasper",
        type=float,
        default=0.0,
        metavar="F",
        help="fraction of frames with the clasper hidden",
    )
    c.add_argument(
        "--fragments", type=float, default=0.0, metavar="N", help="thin cuts across tools per frame"
    )
    c.add_argument(
        "--rough", type=float, default=0.0, metavar="PX", help="network-like boundary noise (px)"
    )
    c.add_argument("--missed", type=float, default=0.0, metavar="N", help="missed blobs per frame")
    c.add_argument(
        "--spurious", type=float, default=0.0, metavar="N", help="spurious blobs per frame"
    )
    c.add_argument(
        "--vignette",
        type=float,
        default=0.0,
        metavar="V",
        help="dark corners: tools lost outside an ellipse (1 + V) x the half image",
    )
    c.add_argument(
        "--real",
        type=float,
        nargs="?",
        const=1.0,
        metavar="SCALE",
        help="real-looking masks: jitter, holes, specks, fragments, network-like noise, "
        "missed and spurious blobs, dark corners at a typical strength (x SCALE, default 1); "
        "other corruption options add to it",
    )
    c.add_argument(
        "--video",
        choices=("mjpg", "xvid", "mp4v"),
        metavar="CODEC",
        help="also write masks.avi (mjpg, xvid, mp4v)",
    )
    p.add_argument("--force", action="store_true", help="replace an earlier synth output in OUT")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress, no summary")
    p.set_defaults(func=run)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--size {text!r}: expected WIDTHxHEIGHT, e.g. 720x576") from None
    return w, h


def _distortion(text: str | None) -> tuple[float, ...]:
    if not text:
        return ()
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(
            f"--distortion {text!r}: expected comma-separated numbers, e.g. -0.22,0.05,0,0,0"
        ) from None


def run(args: argparse.Namespace) -> int:
    """Run ``mistool synth``."""
    from mistool.synth import Corruptions, MotionOptions, SceneOptions, synthesize

    w, h = _size(args.size)
    try:
        base = Corruptions.real(args.real) if args.real is not None else Corruptions()
        corr = Corruptions(
            jitter_px=base.jitter_px + args.jitter,
            bias_px=args.bias,
            holes=base.holes + args.holes,
            speckle=base.speckle + args.speckle,
            occluders=args.occluders,
            hide_clasper=args.hide_clasper,
            fragments=base.fragments + args.fragments,
            rough_px=base.rough_px + args.rough,
            missed=base.missed + args.missed,
            spurious=base.spurious + args.spurious,
            vignette=max(base.vignette, args.vignette),
        )
    except ValueError as exc:
        raise ConfigError(f"corruption option: {exc}") from None
    scene = SceneOptions(
        width=w,
        height=h,
        focal_px=args.focal,
        distortion=_distortion(args.distortion),
        lens_model=args.lens,
        tool=args.tool,
        shaft_diameter_mm=args.shaft_diameter,
        motion=MotionOptions(
            enter=not args.no_enter, leave_view=args.leave_view, cross=not args.no_cross
        ),
    )
    bar = None
    progress = None
    if not args.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=args.frames, unit="frame", desc="synth", file=sys.stderr)

        def progress(done: int, total: int) -> None:
            bar.update(1)

    t0 = time.perf_counter()
    try:
        res = synthesize(
            args.out,
            frames=args.frames,
            instruments=args.instruments,
            seed=args.seed,
            preset=args.preset,
            fps=args.fps,
            corruptions=corr,
            scene=scene,
            distinct_labels=args.distinct_labels,
            video=args.video,
            force=args.force,
            progress=progress,
        )
    finally:
        if bar is not None:
            bar.close()
    dt = time.perf_counter() - t0
    if not args.quiet:
        n_inst = len(set(res.truth["instrument"])) if res.truth.num_rows else 0
        print(
            f"mistool synth: {args.frames} frames, {n_inst} instrument(s) visible, "
            f"{res.truth.num_rows} truth rows -> {res.path} ({args.frames / dt:.0f} "
            "frames/s)",
            file=sys.stderr,
        )
    return 0
