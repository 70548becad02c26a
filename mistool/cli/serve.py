"""``mistool serve``: replay a sequence in 3D in the browser."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path
from typing import Any

DESCRIPTION = """\
Replay a recorded procedure in 3D in the browser: every instrument (shaft with its round
end, wrist, two jaws) following the tracked motion, the endoscope as a frustum showing the
current mask, a ground grid, a timeline (slider, play/pause, speed 0.25x-4x, step, loop),
the 2D overlay (mask blended over the procedure's own video when mistool.toml gives
'source', with each part's rotated box), camera presets (Endoscope, Side, Top, Reset),
plots of x/y/z and roll/pitch/yaw with a cursor, and trails of each tip and joint.

The server starts at once and the sequence is tracked in a background process while you
watch: the timeline grows as frames are tracked, the GUI shows the progress (frames, frames/s,
time left), and when every frame is tracked the sequence-level refinement (trocar, smoothing)
replaces the picture in place. Unless --poses gives a motion table (e.g. from 'mistool track').
Tracked tables are cached (~/.cache/mistool/tables, columns as numpy files, keyed by the
frames' names, sizes and times, the config and mistool's version; at most 2 GB, least
recently used entries removed first, MISTOOL_CACHE_MAX_BYTES to change): the next 'mistool
serve' of the unchanged sequence shows it at once, and a run stopped half-way resumes where
it stopped (--no-cache tracks again from the start). Problems with SEQUENCE are reported
before the server starts. The URL printed is the one really in use: when the port is busy
the next free one is taken (with a warning). Ctrl+C stops the server and the tracking at any
moment. Only the viewer's own page may connect (other sites' pages and unknown Host names
get 403; --allow-origin admits more); beyond loopback (--host 0.0.0.0) the URL carries a
per-run token, printed once (docs/hardening.md).

3D modes (switch in the GUI): 'metric' (millimetres, the default when mistool.toml has
[camera]) and 'paper' (the paper's vpython scene in pixel units: cylinder length = box
length, radius = half the box width, the clasper's base attached to the shaft's end).

Every browser shares one timeline and the display options; each has its own camera.
Keyboard: space or K play/pause, J / L one frame back / forward, Home first frame
(also in viser's command palette, Ctrl+K).

examples:
  mistool serve                         # the bundled sample_masks/
  mistool serve masks/ --port 8081
  mistool serve masks/ --poses masks_motion.csv
  mistool serve masks/ --host 0.0.0.0   # reachable from other machines: URL with a token
  mistool serve masks/ --annotations lesson.json   # bookmarks (Bookmarks panel) in lesson.json
  mistool serve expert/ trainee/ --offset 2.5      # two recordings side by side, B 2.5 s later
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``serve`` subcommand."""
    p = subparsers.add_parser(
        "serve",
        help="replay a sequence in 3D in the browser",
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
        "other",
        metavar="SEQUENCE_B",
        nargs="?",
        default=None,
        help="a second recording shown beside the first (own colours and scene region, "
        "one timeline, metrics side by side)",
    )
    p.add_argument(
        "--offset",
        type=float,
        default=0.0,
        metavar="S",
        help="with SEQUENCE_B: B starts S seconds after A on the shared timeline "
        "(negative: before; default 0)",
    )
    p.add_argument(
        "--port", type=int, default=8080, help="first port to try (default 8080; 0 = any free port)"
    )
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="interface to listen on (default 127.0.0.1; 0.0.0.0 for all)",
    )
    p.add_argument(
        "--allow-origin",
        action="append",
        default=[],
        metavar="ORIGIN",
        help="also accept this page origin or host name (e.g. http://mybox.lan:8080, for a "
        "reverse proxy or a deliberate remote name; repeatable). By default only the "
        "viewer's own page may connect: other sites' pages and unknown Host names get 403",
    )
    p.add_argument(
        "--poses",
        metavar="POSES.csv",
        help="show this motion table instead of tracking the sequence",
    )
    p.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        help="accepted for compatibility (tracking progress is shown in the browser)",
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
        help="track again from the start even if this unchanged sequence was tracked "
        "(or partly tracked) before (tables are cached in ~/.cache/mistool/tables)",
    )
    p.add_argument(
        "--annotations",
        metavar="JSON",
        help="bookmarks file of the Bookmarks panel (default: annotations.json in the "
        "sequence's folder; the bundled sample keeps bookmarks in memory)",
    )
    p.add_argument(
        "--environment-map",
        action="store_true",
        help="light the scene with viser's HDR environment map (off by "
        "default: about 1 s slower to first render without a GPU, "
        "scripts/bench_viewer.py)",
    )
    p.set_defaults(func=run)


def _open(args: argparse.Namespace) -> tuple[Any, Any]:
    """The sequence to show (and, with SEQUENCE_B, what the metrics panel needs)."""
    from mistool.viewer import load_sequence

    if args.other is not None:
        return _load_two(args)
    background = args.poses is None
    return (
        load_sequence(
            args.sequence,
            poses=args.poses,
            background=background,
            fresh=args.no_cache,
            calibration=args.calibration,
        ),
        None,
    )


def _metrics_panel(viewer: Any, compare: Any, offset_s: float) -> None:
    from mistool.viewer.compare import add_metrics_panel

    panel, shift, names = compare
    add_metrics_panel(viewer.server, panel, names=names, offset_s=offset_s, shift_mm=shift)


def _load_two(args: argparse.Namespace) -> tuple[Any, Any]:
    """Both recordings tracked (or read from the cache), B merged into A's replay
    (:mod:`mistool.viewer.compare`); returns the sequence to show and what the metrics
    panel needs."""
    import math

    from mistool.errors import ConfigError
    from mistool.viewer import load_sequence
    from mistool.viewer.compare import PREFIXES, combine_tables

    if args.sequence is None:
        raise ConfigError("serve: give SEQUENCE and SEQUENCE_B to compare two recordings")
    if not math.isfinite(args.offset):
        raise ConfigError(f"--offset {args.offset}: must be a number of seconds")
    a = load_sequence(
        args.sequence, poses=args.poses, cache=not args.no_cache, calibration=args.calibration
    )
    b = load_sequence(args.other, cache=not args.no_cache)  # its own mistool.toml camera
    if a.table is None or b.table is None:  # pragma: no cover - complete loads keep it
        raise ConfigError("serve: both recordings must be tracked completely to compare")
    fa, fb = a.replay.fps, b.replay.fps
    n = a.replay.num_frames
    table, shift = combine_tables(
        a.table, b.table, fps_a=fa, fps_b=fb, offset_s=args.offset, num_frames=n
    )
    both = load_sequence(args.sequence, table=table, calibration=args.calibration)
    panel = [
        (PREFIXES[0], a.table, fa, n),
        (PREFIXES[1], b.table, fb, b.replay.num_frames),
    ]
    return both, (panel, shift, (a.name, b.name))


def _annotations_path(args: argparse.Namespace) -> Path | None:
    """The bookmarks file: --annotations, else the sequence's own (none for the sample,
    which ships inside mistool)."""
    from mistool.annotations import default_path

    if args.annotations:
        return Path(args.annotations)
    return default_path(args.sequence) if args.sequence is not None else None


def _say_start(sequence: Any) -> None:
    """The first line: what is shown (the length of a sequence tracked in the background
    comes later, from :func:`_say_stored`)."""
    replay = sequence.replay
    if sequence.feed is not None:
        what = "tracking in the background (progress in the browser)"
    else:
        what = f"{replay.num_frames} frames, {len(replay.instruments)} instrument(s)"
    print(f"mistool serve: {sequence.name}: {what}, {replay.default_mode} mode", flush=True)


def _say_stored(sequence: Any) -> bool:
    """Print, once the tracking job has found its cache entry, how long the sequence is
    and what was stored; returns whether it was printed (or nothing will be)."""
    feed = sequence.feed
    if feed is None or feed.finished and feed.stored is None:
        return True
    stored = feed.stored
    if stored is None:
        return False
    if stored.complete:
        state = "tracked (cached)"
    elif stored.done:
        state = f"resuming from frame {stored.done} (cached before)"
    else:
        state = "tracking from frame 0"
    total = f"{stored.total:,} frames" if stored.total is not None else "frames"
    print(f"mistool serve: {sequence.name}: {total}, {state}", flush=True)
    return True


def run(
    args: argparse.Namespace,
    *,
    ready: threading.Event | None = None,
    stop: threading.Event | None = None,
) -> int:
    """Serve until Ctrl+C (or until ``stop`` is set, for in-process tests)."""
    from mistool.errors import ConfigError
    from mistool.viewer import ReplayViewer  # viser only for this command
    from mistool.viewer.guard import AccessPolicy

    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: must be in 0..65535")
    sequence, compare = _open(args)
    if sequence.feed is not None:  # tracking starts while the server starts
        sequence.feed.start()
    try:
        access = AccessPolicy.for_host(args.host, args.allow_origin)
        viewer = ReplayViewer(
            sequence,
            host=args.host,
            port=args.port,
            environment_map=args.environment_map,
            access=access,
            annotations=_annotations_path(args),
        )
        if compare is not None:
            _metrics_panel(viewer, compare, args.offset)
    except BaseException:
        if sequence.feed is not None:
            sequence.feed.stop()
        raise
    waiter = stop or threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        # SIGTERM (e.g. from a service manager) stops as cleanly as Ctrl+C.
        previous = signal.signal(signal.SIGTERM, lambda *_: waiter.set())
    try:  # from here on, Ctrl+C (even during the prints) stops cleanly
        _say_start(sequence)
        _say_odd(args, viewer.port, access)
        print(f"open {viewer.url}   (Ctrl+C to stop)", flush=True)
        if ready is not None:
            ready.set()
        said = False
        while not waiter.wait(0.2):
            if not said:
                said = _say_stored(sequence)
        print("mistool serve: stopped", file=sys.stderr)
    except KeyboardInterrupt:
        print("mistool serve: stopped", file=sys.stderr)
    finally:
        viewer.close()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    feed = sequence.feed
    if feed is not None and feed.status().error:
        print(f"mistool serve: tracking stopped: {feed.status().error}", file=sys.stderr)
    if viewer.feed_errors:  # a bug, not bad input
        last_exc = viewer.feed_errors[-1]
        print(
            f"mistool serve: tracking failed: {type(last_exc).__name__}: {last_exc}",
            file=sys.stderr,
        )
        return 1
    errors = viewer.timeline.draw_errors
    if errors:  # a bug, not bad input: say so, with the last error
        last = errors[-1]
        print(
            f"mistool serve: {viewer.timeline.draw_error_count} frame(s) failed to draw; "
            f"last: {type(last).__name__}: {last}",
            file=sys.stderr,
        )
        return 1
    return 0


def _say_odd(args: argparse.Namespace, port: int, access: Any) -> None:
    """Warn on stderr about a busy port and a server reachable beyond this machine."""
    if args.port not in (0, port):
        print(
            f"mistool: warning: port {args.port} is busy; serving on port {port} instead",
            file=sys.stderr,
            flush=True,
        )
    if access.token is not None:
        print(
            f"mistool: warning: --host {args.host} serves beyond this machine (other "
            "machines on the network can connect); only someone with the token in the URL "
            "below can see the replay",
            file=sys.stderr,
            flush=True,
        )
