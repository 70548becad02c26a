#!/usr/bin/env python
"""Long procedures and live use: ``mistool serve`` on 2,000 / 20,000 / 90,000 frames, the
columnar cache, and ``mistool.Viewer.add``, in headless Debian chromium.

Measures (several runs, median):

1. **time to first picture**: from starting ``mistool serve DIR`` (a new process, empty
   cache) to the first screenshot of the 3D view showing an instrument's colour, while the
   sequence is tracked in the background; also the time until the URL is printed, and,
   without server or browser, the tracking process's time to name its cache entry
   (listing the frames and keying the cache) and to store its first chunk. The
   sequences are a 200-frame synthetic procedure (2 instruments, camera) played forwards
   and backwards to the length asked (frames symlinked), each with a ``source`` folder of
   as many endoscope frames (JPEGs, symlinked). Ratio: each length against the
   shortest, measured in the same run, the lengths taking turns (the goal: no growth).
2. **server memory**: peak resident memory (VmHWM) of the ``mistool serve`` process for a
   procedure tracked to the end (the cache entry is filled beforehand with the tracked
   table tiled to the length, so that the server loads it as a finished run would leave it),
   with one browser connected, scrubbing and playing at 4x.
3. **cache load**: reading a finished 90,000-frame table from the cache (memory-mapped
   columns, then every column read once) against reading the same table from CSV (the
   former cache), in this process.
4. **``Viewer.add`` throughput**: frames per second of ``viewer.add(labels)`` over the
   synthetic frames (2 instruments, metric pose) with one browser watching, against
   ``mistool.Tracker.update`` alone on the same frames (same run). 25 fps is the goal.

Usage::

    scripts/bench_live.py [--runs 3] [--lengths 2000 20000 90000] [--add-frames 400]

Needs /usr/bin/chromium and playwright. Other processes on the machine slow it: the load
average at the start and the end is printed.
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
#: Frames of the synthetic procedure the long ones are made of.
BASE_FRAMES = 200


def _base(tmp: Path) -> Path:
    from mistool.synth import synthesize

    out = tmp / "base"
    synthesize(out, frames=BASE_FRAMES, instruments=2, seed=7)
    return out


def _source_index(k: int, n: int) -> int:
    """Frame of the base sequence shown at frame ``k`` (forwards, then backwards)."""
    return k % n if (k // n) % 2 == 0 else n - 1 - k % n


def _endoscope_frames(base: Path) -> list[Path]:
    """JPEG frames standing in for the endoscope video under the base's masks (tissue-like
    background, the instruments grey), made once beside the base sequence."""
    from mistool.sequence import list_frames

    folder = base.parent / "endoscope"
    files = list_frames(base)
    if not folder.is_dir():
        folder.mkdir()
        rng = np.random.default_rng(0)
        tissue = cv2.GaussianBlur(rng.integers(90, 200, (576, 720, 3), dtype=np.uint8), (0, 0), 9)
        tissue[..., 2] = np.clip(tissue[..., 2].astype(int) + 50, 0, 255)  # reddish (BGR)
        for k, f in enumerate(files):
            img = tissue.copy()
            labels = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            img[labels > 0] = (150, 150, 150)
            cv2.imwrite(str(folder / f"{k:06d}.jpg"), img)
    return sorted(folder.glob("*.jpg"))


def _long(base: Path, frames: int, out: Path) -> Path:
    """The base sequence played forwards and backwards to ``frames`` frames (symlinks),
    with a ``source`` folder of as many endoscope frames, as a recorded procedure has."""
    from mistool.sequence import list_frames

    out.mkdir(parents=True)
    toml = (base / "mistool.toml").read_text()
    (out / "mistool.toml").write_text('source = "endoscope"\n' + toml)
    files = list_frames(base)
    video = _endoscope_frames(base)
    (out / "endoscope").mkdir()
    for k in range(frames):
        i = _source_index(k, len(files))
        os.symlink(files[i], out / f"{k:06d}.png")
        os.symlink(video[i], out / "endoscope" / f"{k:06d}.jpg")
    return out


def _serve(seq: Path, env: dict[str, str]) -> tuple[subprocess.Popen, str, float]:
    cmd = [sys.executable, "-c", "import sys; from mistool.cli import main; sys.exit(main())"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [*cmd, "serve", str(seq), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    for line in proc.stdout:
        m = re.search(r"(http://\S+)", line)
        if m:
            return proc, m.group(1), t0
    raise RuntimeError(f"mistool serve failed: {proc.stderr.read() if proc.stderr else ''}")


def _instrument_pixels(img_bgr: np.ndarray) -> int:
    """Pixels with the hue of instrument 1's or 2's shaft colour (saturated)."""
    from mistool.viewer.replay import PALETTE

    hsv = cv2.cvtColor(img_bgr, cv2.COLOR_BGR2HSV).astype(int)
    best = 0
    for rgb in PALETTE[:2]:
        target = int(cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0, 0])
        dh = np.abs(hsv[..., 0] - target)
        dh = np.minimum(dh, 180 - dh)
        best = max(best, int(((dh <= 8) & (hsv[..., 1] > 90) & (hsv[..., 2] > 40)).sum()))
    return best


def _shot(page) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(page.screenshot(clip=CLIP), np.uint8), cv2.IMREAD_COLOR)


def _stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


def first_picture(browser, seq: Path, cache_home: Path) -> tuple[float, float]:
    """(seconds to the URL, seconds to the first instrument on screen), empty cache."""
    env = dict(os.environ, XDG_CACHE_HOME=str(cache_home))
    proc, url, t0 = _serve(seq, env)
    t_url = time.perf_counter() - t0
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(url)
        while True:
            if (
                page.locator("canvas[data-engine]").count()
                and _instrument_pixels(_shot(page)) > 300
            ):
                return t_url, time.perf_counter() - t0
            if time.perf_counter() - t0 > 120:
                raise RuntimeError("no instrument on screen within 120 s")
            time.sleep(0.02)
    finally:
        page.close()
        _stop(proc)


def job_start(seq: Path, cache_home: Path) -> tuple[float, float]:
    """The tracking process alone (no server, no browser), empty cache: seconds from its
    start to naming its cache entry (it has listed the frames and keyed the cache) and to
    storing its first chunk, in this process (forked, as ``mistool serve`` does)."""
    from mistool.background import JobSpec, TrackingJob
    from mistool.sequence import resolve

    path, cfg = resolve(seq)
    job = TrackingJob(JobSpec(path, cfg, None, root=cache_home))
    t0 = time.perf_counter()
    job.start()
    try:
        said = None
        while said is None:
            said = job.opened()
            time.sleep(0.002)
        t_open = time.perf_counter() - t0
        entry = said[0]
        if entry is None:
            raise RuntimeError(f"tracking failed: {said[1]}")
        while not entry.progress().chunks:
            time.sleep(0.002)
        return t_open, time.perf_counter() - t0
    finally:
        job.stop()


def _tiled_table(base_table, frames: int, base_frames: int, fps: float):
    """The base sequence's tracked table laid out as the long sequence's frames."""
    fr = np.asarray(base_table["frame"])
    rows = [np.flatnonzero(fr == f) for f in range(base_frames)]
    src = [_source_index(k, base_frames) for k in range(frames)]
    idx = np.concatenate([rows[s] for s in src])
    counts = np.array([len(rows[s]) for s in src])
    new_frame = np.repeat(np.arange(frames), counts)
    return base_table[idx].with_columns(frame=new_frame, time_s=new_frame / fps)


def server_memory(browser, seq: Path, table, cache_home: Path) -> dict[str, float]:
    """Peak RSS (MB) of ``mistool serve`` showing a finished ``table``, and seconds from
    launch to the whole timeline being available."""
    from mistool.cache import frames_digest
    from mistool.sequence import list_frames, resolve
    from mistool.viewer.app import _entry_for

    os.environ["XDG_CACHE_HOME"] = str(cache_home)
    path, cfg = resolve(seq)
    entry = _entry_for(path, cfg)
    entry.begin(None, {})
    entry.finish(table)
    entry.set_frames_digest(frames_digest(list_frames(path)))  # as a finished run leaves it
    env = dict(os.environ)
    proc, url, t0 = _serve(seq, env)
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(url)
        page.wait_for_selector("canvas[data-engine]", timeout=60000)
        page.get_by_text("Tracked", exact=False).first.wait_for(timeout=120000)
        t_all = time.perf_counter() - t0
        thumb = page.get_by_role("slider").first
        thumb.focus()
        for _ in range(20):
            page.keyboard.press("PageUp")
            time.sleep(0.1)
        page.mouse.click(400, 600)
        page.keyboard.press(" ")  # play
        time.sleep(4.0)
        page.keyboard.press(" ")
        status = Path(f"/proc/{proc.pid}/status").read_text()
        hwm = int(re.search(r"VmHWM:\s+(\d+)", status).group(1)) / 1024.0  # type: ignore[union-attr]
        rss = int(re.search(r"VmRSS:\s+(\d+)", status).group(1)) / 1024.0  # type: ignore[union-attr]
        return {"peak_rss_mb": hwm, "rss_mb": rss, "seconds_to_whole_timeline": t_all}
    finally:
        page.close()
        _stop(proc)


def cache_load(table, tmp: Path, runs: int) -> dict[str, float]:
    from mistool import cache
    from mistool.export import read_csv, write_csv

    entry = cache.open_entry("bench", tmp / "cache_load")
    entry.begin(None, {})
    entry.finish(table)
    mapped, full = [], []
    for _ in range(runs):
        t = time.perf_counter()
        loaded = entry.read_final()
        mapped.append(time.perf_counter() - t)
        t = time.perf_counter()
        loaded = entry.read_final()
        for c in loaded.columns:
            np.asarray(loaded[c]).sum() if np.asarray(loaded[c]).dtype.kind == "f" else None
        full.append(time.perf_counter() - t)
    csv = tmp / "table.csv"
    write_csv(table, csv)
    t = time.perf_counter()
    read_csv(csv)
    t_csv = time.perf_counter() - t
    return {
        "rows": float(table.num_rows),
        "load_mmap_s": statistics.median(mapped),
        "load_and_read_all_s": statistics.median(full),
        "csv_read_s": t_csv,
        "ratio_csv_to_columnar": t_csv / statistics.median(full),
    }


def add_throughput(browser, base: Path, frames: int) -> dict[str, float]:
    import mistool
    from mistool.sequence import list_frames

    files = list_frames(base)
    labels = [
        cv2.imread(str(files[_source_index(k, len(files))]), cv2.IMREAD_UNCHANGED)
        for k in range(frames)
    ]
    tracker = mistool.Tracker(base / "mistool.toml")
    t = time.perf_counter()
    for lab in labels:
        tracker.update(lab)
    t_tracker = time.perf_counter() - t
    viewer = mistool.Viewer(base / "mistool.toml", port=0)
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(viewer.url)
        page.wait_for_selector("canvas[data-engine]", timeout=30000)
        t = time.perf_counter()
        for lab in labels:
            viewer.add(lab)
        t_add = time.perf_counter() - t
    finally:
        page.close()
        viewer.close()
    return {
        "frames": float(frames),
        "add_fps": frames / t_add,
        "tracker_update_fps": frames / t_tracker,
        "ratio_add_to_update_time": t_add / t_tracker,
    }


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--lengths", type=int, nargs="+", default=[2000, 20000, 90000])
    ap.add_argument("--memory-lengths", type=int, nargs="*", default=[20000, 90000])
    ap.add_argument("--add-frames", type=int, default=400)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    from mistool import api

    print(f"load average at start: {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as d, sync_playwright() as p:
        tmp = Path(d)
        base = _base(tmp)
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            firsts: dict[int, float] = {}
            seqs = {n: _long(base, n, tmp / f"long{n}") for n in args.lengths}
            runs: dict[int, list[tuple[float, float]]] = {n: [] for n in args.lengths}
            for r in range(args.runs):  # lengths interleaved: the machine's load drifts
                for n in args.lengths:
                    runs[n].append(first_picture(browser, seqs[n], tmp / f"c{n}_{r}"))
            for n in args.lengths:
                got = runs[n]
                firsts[n] = statistics.median(g[1] for g in got)
                url = statistics.median(g[0] for g in got)
                print(
                    f"first picture, {n:,} frames: {firsts[n]:.2f} s (URL printed after "
                    f"{url:.2f} s); runs: {', '.join(f'{g[1]:.2f}' for g in got)}"
                )
            shortest = min(firsts)
            for n in args.lengths:
                print(f"  ratio {n:,} / {shortest:,} frames: {firsts[n] / firsts[shortest]:.2f}")
            for n in args.lengths:
                jobs = [job_start(tmp / f"long{n}", tmp / f"j{n}_{r}") for r in range(args.runs)]
                named, stored = (statistics.median(j[k] for j in jobs) for k in (0, 1))
                print(
                    f"tracking process alone, {n:,} frames: cache entry named after "
                    f"{named:.2f} s (frames listed, cache keyed), first chunk stored after "
                    f"{stored:.2f} s"
                )
            base_table = api.track(base)
            fps = 25.0
            for n in args.memory_lengths:
                seq = tmp / f"long{n}"
                if not seq.exists():
                    _long(base, n, seq)
                table = _tiled_table(base_table, n, BASE_FRAMES, fps)
                mem = server_memory(browser, seq, table, tmp / f"m{n}")
                print(
                    f"server memory, {n:,} frames tracked ({table.num_rows:,} rows): peak RSS "
                    f"{mem['peak_rss_mb']:.0f} MB (now {mem['rss_mb']:.0f} MB); whole timeline "
                    f"shown {mem['seconds_to_whole_timeline']:.1f} s after launch"
                )
            table = _tiled_table(base_table, 90000, BASE_FRAMES, fps)
            load = cache_load(table, tmp, args.runs)
            print(
                f"cache load, 90,000 frames ({load['rows']:,.0f} rows): "
                f"{1e3 * load['load_mmap_s']:.0f} ms memory-mapped, "
                f"{1e3 * load['load_and_read_all_s']:.0f} ms with every column read; "
                f"CSV (the former cache): {load['csv_read_s']:.1f} s "
                f"({load['ratio_csv_to_columnar']:.0f}x slower)"
            )
            add = add_throughput(browser, base, args.add_frames)
            print(
                f"Viewer.add, {args.add_frames} frames, 2 instruments, metric pose, one browser: "
                f"{add['add_fps']:.0f} frames/s (Tracker.update alone: "
                f"{add['tracker_update_fps']:.0f} frames/s; add/update time "
                f"{add['ratio_add_to_update_time']:.2f})"
            )
        finally:
            browser.close()
    print(f"load average at end: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
