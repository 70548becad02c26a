"""Long and live sequences without a browser: the columnar cache (round trip, key,
resume, size policy), background tracking, the growing replay, ``mistool.Viewer``, and the
per-part pose status. The browser tests are in ``test_live_browser.py``."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool import api, background, cache, parallel
from mistool.config import Config
from mistool.model import TrackTable
from mistool.sequence import list_frames, resolve
from mistool.viewer.replay import NO_POSE, NOT_VISIBLE, Replay, build_replay, config_parts

#: Frames of the synthetic sequence.
N = 50


@pytest.fixture(scope="module")
def seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from mistool.synth import synthesize

    out = tmp_path_factory.mktemp("live") / "seq"
    synthesize(out, frames=N, instruments=2, seed=4)
    return out


@pytest.fixture(scope="module")
def tracked(seq: Path) -> TrackTable:
    return api.track(seq)


def _entry(seq: Path, root: Path, **options: object) -> cache.CacheEntry:
    path, cfg = resolve(seq)
    return cache.open_entry(cache.cache_key(path, cfg, list_frames(path), **options), root)


def _assert_same(a: TrackTable, b: TrackTable) -> None:
    assert a.columns == b.columns and a.num_rows == b.num_rows
    for c in a.columns:
        x, y = np.asarray(a[c]), np.asarray(b[c])
        assert x.dtype == y.dtype, c
        if x.dtype.kind == "f":
            np.testing.assert_array_equal(x, y, err_msg=c)
        else:
            assert (x == y).all(), c


def test_cache_round_trip_keeps_every_column(
    seq: Path, tracked: TrackTable, tmp_path: Path
) -> None:
    entry = _entry(seq, tmp_path)
    entry.begin(N, {})
    entry.finish(tracked)
    loaded = entry.read_final()
    _assert_same(loaded, tracked)
    assert isinstance(np.asarray(loaded["cx_px"]).base, np.memmap) or isinstance(
        loaded["cx_px"], np.memmap
    ), "numeric columns are memory-mapped"
    assert entry.progress().complete and not (entry.path / "raw").exists()


def test_cache_key_follows_frames_config_and_options(seq: Path, tmp_path: Path) -> None:
    path, cfg = resolve(seq)
    files = list_frames(path)
    key = cache.cache_key(path, cfg, files, metric=True)
    assert key == cache.cache_key(path, cfg, files, metric=True)
    assert key != cache.cache_key(path, cfg, files, metric=False)
    assert key != cache.cache_key(path, Config(min_area_px=99), files, metric=True)
    assert key != cache.cache_key(path, cfg, files[:-1], metric=True)


def test_a_stopped_run_resumes_where_it_stopped(
    seq: Path, tracked: TrackTable, tmp_path: Path
) -> None:
    path, cfg = resolve(seq)
    entry = _entry(seq, tmp_path)
    stop = threading.Event()
    stop.set()  # stop after the first chunk
    first = background.track_into(background.JobSpec(path, cfg, entry), stop)
    assert first.done == background.CHUNK_SCHEDULE[0] and not first.complete
    calls: list[str] = []
    real = parallel.ordered_results

    def counting(work, pool):  # the frames the resumed run processes
        for name, result in real(work, pool):
            calls.append(name)
            yield name, result

    parallel.ordered_results = counting  # type: ignore[assignment]
    try:
        done = background.track_into(background.JobSpec(path, cfg, entry))
    finally:
        parallel.ordered_results = real  # type: ignore[assignment]
    first_name = list_frames(path)[background.CHUNK_SCHEDULE[0]].name
    assert done.complete and calls[0] == first_name, calls[:3]
    _assert_same(entry.read_final(mmap=False), tracked)  # as if never stopped


def test_bad_frame_mid_sequence_is_recorded_as_one_line(seq: Path, tmp_path: Path) -> None:
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(seq, broken)
    sorted(broken.glob("*.png"))[40].write_bytes(b"not a png")
    path, cfg = resolve(broken)
    entry = _entry(broken, tmp_path / "c")
    with pytest.raises(Exception) as info:
        background.track_into(background.JobSpec(path, cfg, entry))
    progress = entry.progress()
    assert progress.error and "\n" not in progress.error and str(info.value) == progress.error
    assert 0 < progress.done <= 40 and not progress.complete


def test_cache_size_policy_removes_least_recently_used(tmp_path: Path) -> None:
    table = TrackTable(
        {"frame": np.arange(2000), "instrument": ["1"] * 2000, "part": ["shaft"] * 2000}
    )
    table = table.with_columns(cx_px=np.zeros(2000))
    made = []
    for k in range(3):
        e = cache.open_entry(f"k{k}", tmp_path)
        e.begin(2000, {})
        e.finish(table)
        os.utime(e.path / "used", (1000.0 + k, 1000.0 + k))
        made.append(e)
    one = made[0].size_bytes()
    removed = cache.enforce_limit(keep=made[0], limit=2 * one + one // 2)
    assert removed == ["k1"]  # the oldest (k0) is in use
    assert made[0].path.exists() and made[2].path.exists() and not made[1].path.exists()


def test_replay_grown_chunk_by_chunk_equals_the_whole(seq: Path, tracked: TrackTable) -> None:
    _, cfg = resolve(seq)
    whole = build_replay(tracked, cfg, num_frames=N, image_wh=(720, 576))
    grown = Replay(cfg, num_frames=1, image_wh=(720, 576), parts=config_parts(cfg))
    for lo, hi in ((0, 7), (7, 30), (30, N)):  # instruments appear along the way
        grown.write(tracked, lo, hi)
    assert grown.tracked == grown.num_frames == N
    assert set(grown.instruments) == set(whole.instruments)
    order = [grown.instruments.index(n) for n in whole.instruments]
    for mode in whole.modes:
        a, b = whole.modes[mode], grown.modes[mode]
        for name in ("centre", "wxyz", "length", "visible"):
            np.testing.assert_allclose(getattr(b, name)[:N][:, order], getattr(a, name), atol=1e-9)
    assert grown.first_busy_frame() == whole.first_busy_frame()


def test_pose_status_says_why_a_part_has_no_pose(tracked: TrackTable, seq: Path) -> None:
    _, cfg = resolve(seq)
    rows = tracked[tracked["frame"] == int(tracked["frame"].max())]
    rows = TrackTable({c: rows[c] for c in rows.columns if c != "pose_status"})
    end = np.asarray(rows["end_x_mm"], float).copy()
    end[0] = np.nan
    derived = build_replay(rows.with_columns(end_x_mm=end), cfg, image_wh=(720, 576))
    frame = int(rows["frame"][0])
    status = {(i, p): s for i, p, s, _ in derived.frame_status(frame)}
    assert status[(str(rows["instrument"][0]), str(rows["part"][0]))] == NO_POSE
    reasons = np.array(["one silhouette line"] + ["ok"] * (rows.num_rows - 1), dtype=object)
    given = build_replay(rows.with_columns(pose_status=reasons), cfg, image_wh=(720, 576))
    status = {(i, p): (s, q) for i, p, s, q in given.frame_status(frame)}
    assert status[(str(rows["instrument"][0]), str(rows["part"][0]))][0] == "one silhouette line"
    assert all(np.isfinite(q) for s, q in status.values() if s == "ok")
    assert derived.frame_status(0) == [] or all(
        s == NOT_VISIBLE for _, _, s, _ in derived.frame_status(0)
    )


def test_viewer_add_returns_the_trackers_rows(seq: Path) -> None:
    import mistool

    files = list_frames(seq)[:30]
    reference = mistool.Tracker(seq / "mistool.toml")
    with mistool.Viewer(seq / "mistool.toml", port=0) as viewer:
        for f in files:
            labels = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            rows = viewer.add(labels, image=np.dstack([labels] * 3))
            _assert_same(rows, reference.update(labels))
        rv = viewer.replay_viewer
        assert rv.replay.tracked == 30 and rv.timeline.num_frames == 30
        assert rv.timeline.wait_shown(29), "the newest frame is shown (follow)"
        _assert_same(viewer.table(), reference.table())
    with pytest.raises(RuntimeError, match="closed"):
        viewer.add(labels)


def test_serve_tracks_in_the_background_and_resumes_after_ctrl_c(seq: Path, tmp_path: Path) -> None:
    long = tmp_path / "long"
    long.mkdir()
    (long / "mistool.toml").write_bytes((seq / "mistool.toml").read_bytes())
    frames = list_frames(seq)
    for k in range(3000):  # a long procedure from the N frames, forwards and backwards
        src = frames[k % N] if (k // N) % 2 == 0 else frames[N - 1 - k % N]
        os.symlink(src, long / f"{k:05d}.png")
    env = dict(os.environ, XDG_CACHE_HOME=str(tmp_path / "cache"))
    cmd = [
        sys.executable,
        "-c",
        "import sys; from mistool.cli import main; sys.exit(main(sys.argv[1:]))",
    ]
    cmd += ["serve", str(long), "--port", "0"]

    def launch() -> tuple[subprocess.Popen, list[str]]:
        proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        assert proc.stdout is not None
        return proc, [proc.stdout.readline() for _ in range(2)]

    proc, lines = launch()
    try:
        assert "tracking in the background from frame 0" in lines[0], lines
        assert "http://" in lines[1], lines
        entry = cache.entries(tmp_path / "cache" / "mistool" / "tables")
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not (entry and entry[0].progress().done >= 50):
            time.sleep(0.2)
            entry = cache.entries(tmp_path / "cache" / "mistool" / "tables")
        assert entry and entry[0].progress().done >= 50
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped" in err and "Traceback" not in err
    done = entry[0].progress().done
    assert 50 <= done < 3000
    time.sleep(0.5)
    assert entry[0].progress().done == done, "the tracking process kept running"
    proc, lines = launch()  # the next launch resumes where the first stopped
    try:
        assert f"from frame {done}" in lines[0], lines
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0


def test_background_job_with_worker_processes_gives_the_same_table(
    seq: Path, tracked: TrackTable, tmp_path: Path
) -> None:
    """The job's child process is daemonic (it never outlives its parent), yet it starts
    its own pool of worker processes for ``workers > 1``; the table is the same."""
    path, cfg = resolve(seq)
    entry = _entry(seq, tmp_path)
    job = background.TrackingJob(background.JobSpec(path, cfg, entry, workers=2))
    job.start()
    try:
        assert job.wait(timeout=120), "the tracking child did not finish"
    finally:
        job.stop()
    progress = entry.progress()
    assert progress.complete and not progress.error, progress.error
    _assert_same(entry.read_final(mmap=False), tracked)
