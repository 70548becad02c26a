#!/usr/bin/env python
"""Speed and memory of the replay viewer (``mistool serve``), in headless Debian chromium.

Measures, each over several runs (median reported):

1. **launch to first render**: from starting ``mistool serve`` (a new process) to the first
   screenshot of the 3D view that is not blank, in headless chromium with software WebGL,
   with viser's HDR environment map off (mistool's default) and on (``--environment-map``);
   the process's own time to print its URL is reported too. Once with tracking
   (``--no-cache``), then with the tracked table cached (what every later launch does).
2. **per-frame server update**: ``ReplayViewer`` drawing every frame in random order
   (scrubbing) with one browser connected: the update itself (cylinders, trails, plot
   cursor; wall and thread CPU time) and the time until the frame's overlay (mask decoded,
   drawn, JPEG-encoded by the overlay worker) is sent too; baseline in the same run:
   decoding the same frame's mask PNG with ``cv2.imread``. During playback the overlays of
   the next frames are prepared ahead, so the update sends them with the scene; the update
   time during playback is reported too.
3. **playback**: frames drawn per second while playing at 1x (the sequence's fps, 25) and
   at 4x, with one browser connected.
4. **memory**: peak resident memory (VmHWM) of a ``mistool serve`` process showing a
   10,000-frame sequence (the frames hard-linked from the input, its table tiled) while
   playing at 4x and scrubbing, with one browser connected.

Usage::

    scripts/bench_viewer.py [DIR] [--poses POSES.csv] [--runs 3]
    scripts/bench_viewer.py --screenshot web_assets/screenshot.png   # README image

DIR defaults to the bundled sample_masks/ (or a 250-frame synthetic sequence when the
sample is not there). Needs /usr/bin/chromium and playwright.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

CHROMIUM = "/usr/bin/chromium"
ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
]
CLIP = {"x": 0, "y": 160, "width": 860, "height": 640}


def _sequence(args: argparse.Namespace, tmp: Path) -> tuple[Path, Path | None]:
    if args.dir is not None:
        return Path(args.dir), Path(args.poses) if args.poses else None
    from mistool.resources import sample_masks_dir

    try:
        sample = sample_masks_dir()
        if any(sample.glob("*.png")):
            return sample, Path(args.poses) if args.poses else None
    except Exception:
        pass
    from mistool.synth import synthesize

    out = tmp / "synth"
    synthesize(out, frames=250, instruments=2, seed=7)
    return out, Path(args.poses) if args.poses else out / "truth.csv"


def _serve(seq: Path, poses: Path | None, extra: list[str]) -> tuple[subprocess.Popen, str]:
    cmd = [
        sys.executable,
        "-c",
        "import sys; from mistool.cli import main; sys.exit(main(sys.argv[1:]))",
        "serve",
        str(seq),
        "--port",
        "0",
        "-q",
    ]
    if poses is not None:
        cmd += ["--poses", str(poses)]
    proc = subprocess.Popen(cmd + extra, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        m = re.search(r"(http://\S+)", line)
        if m:
            return proc, m.group(1)
    raise RuntimeError(f"mistool serve failed: {proc.stderr.read() if proc.stderr else ''}")


def _blank(img: np.ndarray) -> bool:
    return float(img.std()) < 8.0


def _shot(page) -> np.ndarray:
    png = page.screenshot(clip=CLIP)
    return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)


def bench_launch(
    browser, seq: Path, poses: Path | None, env_map: bool, cache: bool = True
) -> tuple[float, float, float]:
    """Seconds from process start to the URL and to the first non-blank 3D view, and
    from opening the page to that render."""
    extra = (["--environment-map"] if env_map else []) + ([] if cache else ["--no-cache"])
    t0 = time.perf_counter()
    proc, url = _serve(seq, poses, extra)
    t_url = time.perf_counter() - t0
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        t_page = time.perf_counter()
        page.goto(url)
        while True:
            if page.locator("canvas[data-engine]").count() and not _blank(_shot(page)):
                break
            if time.perf_counter() - t0 > 60:
                raise RuntimeError("no render within 60 s")
            time.sleep(0.02)
        t1 = time.perf_counter()
        return t_url, t1 - t0, t1 - t_page
    finally:
        page.close()
        proc.terminate()
        proc.wait(10)


def _viewer(seq: Path, poses: Path | None):
    from mistool.viewer import ReplayViewer, load_sequence

    return ReplayViewer(load_sequence(seq, poses=poses), port=0)


def bench_updates(browser, seq: Path, poses: Path | None, passes: int) -> dict[str, float]:
    from mistool.sequence import list_frames

    viewer = _viewer(seq, poses)
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(viewer.url)
        page.wait_for_selector("canvas[data-engine]", timeout=30000)
        time.sleep(1.0)
        viewer.timeline.set_playing(False)
        n = viewer.replay.num_frames
        files = list_frames(seq) if seq.is_dir() else []
        upd: list[float] = []
        cpu: list[float] = []
        full: list[float] = []
        dec: list[float] = []
        order = np.random.default_rng(0).permutation(n)  # scrubbing: no prefetch helps
        for _ in range(passes):
            for k in order:
                c0 = time.thread_time()
                t0 = time.perf_counter()
                upd.append(viewer.draw_now(int(k)))
                cpu.append(time.thread_time() - c0)
                assert viewer.wait_overlay(int(k), 10.0)
                full.append(time.perf_counter() - t0)
                if k < len(files):
                    t = time.perf_counter()
                    cv2.imread(str(files[k]), cv2.IMREAD_UNCHANGED)
                    dec.append(time.perf_counter() - t)
        out = {
            "update_median_ms": 1e3 * statistics.median(upd),
            "update_p90_ms": 1e3 * float(np.percentile(upd, 90)),
            "update_cpu_median_ms": 1e3 * statistics.median(cpu),
            "overlay_median_ms": 1e3 * statistics.median(full),
            "overlay_p90_ms": 1e3 * float(np.percentile(full, 90)),
            "frames": float(n),
        }
        if dec:
            out["decode_median_ms"] = 1e3 * statistics.median(dec)
            out["ratio_update_to_decode"] = statistics.median(upd) / statistics.median(dec)
            out["ratio_overlay_to_decode"] = statistics.median(full) / statistics.median(dec)
        for speed in ("1x", "4x"):
            viewer.timeline.speed.value = speed
            viewer.timeline.seek(0)
            viewer.timeline.wait_shown(0)
            viewer.update_seconds.clear()
            drawn0, t0 = viewer.timeline.frames_drawn, time.perf_counter()
            viewer.timeline.set_playing(True)
            time.sleep(4.0)
            viewer.timeline.set_playing(False)
            fps = (viewer.timeline.frames_drawn - drawn0) / (time.perf_counter() - t0)
            out[f"playback_{speed}_fps"] = fps
            out[f"playback_{speed}_update_median_ms"] = 1e3 * statistics.median(
                list(viewer.update_seconds)
            )
        out["target_fps"] = viewer.replay.fps
        assert not viewer.timeline.draw_errors, viewer.timeline.draw_errors
        return out
    finally:
        page.close()
        viewer.close()


def _big_sequence(seq: Path, poses: Path | None, tmp: Path, frames: int) -> tuple[Path, Path]:
    """A ``frames``-long copy of the sequence: hard links to its frames, tiled table."""
    from mistool.export import read_csv, write_csv
    from mistool.model import TrackTable
    from mistool.sequence import list_frames

    files = list_frames(seq)
    big = tmp / "big"
    big.mkdir()
    if (seq / "mistool.toml").exists():  # without 'source': its video is not tiled along
        lines = (seq / "mistool.toml").read_text().splitlines(keepends=True)
        kept = [line for line in lines if not line.lstrip().startswith("source")]
        (big / "mistool.toml").write_text("".join(kept))
    for k in range(frames):
        os.link(files[k % len(files)], big / f"{k:06d}{files[0].suffix}")
    if poses is None:
        from mistool import api

        table = api.track(seq)
    else:
        table = read_csv(poses)
    n = len(files)
    tiles = []
    for start in range(0, frames, n):
        t = table[np.asarray(table["frame"]) < frames - start]
        tiles.append(t.with_columns(frame=np.asarray(t["frame"]) + start))
    out = tmp / "big_motion.csv"
    write_csv(TrackTable.concat(tiles), out)
    return big, out


def bench_memory(
    browser, seq: Path, poses: Path | None, tmp: Path, frames: int = 10_000
) -> dict[str, float]:
    big, big_poses = _big_sequence(seq, poses, tmp, frames)
    proc, url = _serve(big, big_poses, [])
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(url)
        page.wait_for_selector("canvas[data-engine]", timeout=30000)
        time.sleep(1.0)
        page.keyboard.press("Escape")
        page.mouse.click(400, 600)
        page.keyboard.press(" ")  # play (1x) for a while
        time.sleep(5.0)
        page.keyboard.press(" ")
        slider = page.get_by_role("slider").first
        slider.focus()
        for key in ("End", "Home", "PageUp", "PageUp", "PageDown") * 4:  # scrub
            page.keyboard.press(key)
            time.sleep(0.05)
        time.sleep(1.0)
        status = Path(f"/proc/{proc.pid}/status").read_text()
        kb = {
            k: int(v.split()[0])
            for k, v in (line.split(":", 1) for line in status.splitlines())
            if k in ("VmRSS", "VmHWM")
        }
        return {
            "frames": float(frames),
            "rss_mb": kb["VmRSS"] / 1024,
            "peak_rss_mb": kb["VmHWM"] / 1024,
        }
    finally:
        page.close()
        proc.terminate()
        proc.wait(10)


def screenshot(browser, seq: Path, poses: Path | None, path: Path) -> None:
    """The README's screenshots: the overview camera at the frame showing most parts, and
    the Endoscope view of it (``<name>_endoscope.png``)."""
    viewer = _viewer(seq, poses)
    page = browser.new_page(viewport={"width": 1280, "height": 760})
    try:
        g = viewer.replay.modes[viewer.replay.default_mode]
        visible = g.visible.reshape(viewer.replay.num_frames, -1).sum(axis=1)
        frame = int(
            np.flatnonzero(visible == visible.max())[
                len(np.flatnonzero(visible == visible.max())) // 2
            ]
        )
        page.goto(viewer.url)
        page.wait_for_selector("canvas[data-engine]", timeout=30000)
        page.get_by_role("slider").first.wait_for(timeout=30000)
        close = page.locator(".mantine-Notification-root button")
        if close.count():
            close.first.click()
        viewer.timeline.seek(frame)
        viewer.timeline.wait_shown(frame)
        viewer.wait_overlay(frame)
        time.sleep(2.0)
        page.screenshot(path=str(path))
        print(f"screenshot of frame {frame} -> {path}")
        endo = path.with_name(f"{path.stem}_endoscope{path.suffix}")
        # Without the rotated boxes: a box bounds the whole perspective-tapered shaft, so
        # near the joint it is much wider than the shaft and reads as a misalignment.
        viewer.boxes.value = False
        page.get_by_role("button", name="Endoscope").click()
        time.sleep(2.5)
        page.screenshot(path=str(endo))
        print(f"looking through the endoscope -> {endo}")
    finally:
        page.close()
        viewer.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dir", nargs="?", help="sequence folder (default: sample_masks/)")
    parser.add_argument("--poses", help="motion table CSV instead of tracking")
    parser.add_argument("--runs", type=int, default=3, help="runs of the launch benchmark")
    parser.add_argument("--skip-memory", action="store_true")
    parser.add_argument("--skip-launch", action="store_true")
    parser.add_argument(
        "--screenshot", metavar="PNG", help="only save the README's screenshot of the replay to PNG"
    )
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as d, sync_playwright() as p:
        tmp = Path(d)
        seq, poses = _sequence(args, tmp)
        print(f"sequence: {seq} (poses: {poses or 'tracked'})")
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        if args.screenshot:
            screenshot(browser, seq, poses, Path(args.screenshot))
            browser.close()
            return 0
        if not args.skip_launch:
            if poses is None:  # cold: tracking included (the table is cached afterwards)
                cold = bench_launch(browser, seq, poses, False, cache=False)
                print(
                    f"launch, tracking the sequence (--no-cache): URL after {cold[0]:.2f} s, "
                    f"first non-blank render after {cold[1]:.2f} s"
                )
                bench_launch(browser, seq, poses, False)  # fills the cache
            for env_map in (False, True):
                runs = [bench_launch(browser, seq, poses, env_map) for _ in range(args.runs)]
                med = [statistics.median(r[j] for r in runs) for j in range(3)]
                print(
                    f"launch, {'poses given' if poses else 'cached table'}, environment map "
                    f"{'on ' if env_map else 'off'}: URL after {med[0]:.2f} s, first "
                    f"non-blank render after {med[1]:.2f} s (page open to render "
                    f"{med[2]:.2f} s; median of {args.runs}: "
                    f"{', '.join(f'{r[1]:.2f}' for r in runs)})"
                )
        res = bench_updates(browser, seq, poses, passes=2)
        print(
            f"per-frame update, scrubbing ({res['frames']:.0f} frames x 2, random order): "
            f"median {res['update_median_ms']:.2f} ms wall "
            f"({res['update_cpu_median_ms']:.2f} ms CPU), p90 {res['update_p90_ms']:.2f} ms; "
            f"until its overlay is sent too: median {res['overlay_median_ms']:.2f} ms, "
            f"p90 {res['overlay_p90_ms']:.2f} ms"
            + (
                f"; cv2.imread of the mask: median {res['decode_median_ms']:.2f} ms, "
                f"ratios to it {res['ratio_update_to_decode']:.2f} (update) and "
                f"{res['ratio_overlay_to_decode']:.2f} (with overlay)"
                if "decode_median_ms" in res
                else ""
            )
        )
        print(
            f"playback: {res['playback_1x_fps']:.1f} frames/s at 1x (target "
            f"{res['target_fps']:.0f}; update median "
            f"{res['playback_1x_update_median_ms']:.2f} ms with prefetch), "
            f"{res['playback_4x_fps']:.1f} frames/s at 4x (target {4 * res['target_fps']:.0f}; "
            f"update median {res['playback_4x_update_median_ms']:.2f} ms)"
        )
        if not args.skip_memory:
            mem = bench_memory(browser, seq, poses, tmp)
            print(
                f"memory, {mem['frames']:.0f}-frame sequence: peak RSS "
                f"{mem['peak_rss_mb']:.0f} MB (now {mem['rss_mb']:.0f} MB)"
            )
        browser.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
