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


@pytest.fixture(scope="module")
def first_chunk(seq: Path) -> int:
    """Frames in a new run's first chunk: up to the first frame with a part in 3D (a
    metric pose in the raw rows: frame 10 of this sequence), which is stored at once
    rather than at the end of a full chunk."""
    raw = next(api.iter_track(seq, chunk_frames=N))
    posed = np.isfinite(np.asarray(raw["end_x_mm"], dtype=float))
    end = int(np.asarray(raw["frame"])[posed].min()) + 1
    assert end < background.CHUNK_SCHEDULE[0]
    return end


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
    seq: Path, tracked: TrackTable, first_chunk: int, tmp_path: Path
) -> None:
    path, cfg = resolve(seq)
    entry = _entry(seq, tmp_path)
    stop = threading.Event()
    stop.set()  # stop after the first chunk
    first = background.track_into(background.JobSpec(path, cfg, entry), stop)
    assert first.done == first_chunk and not first.complete
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
    first_name = list_frames(path)[first_chunk].name
    assert done.complete and calls[0] == first_name, calls[:3]
    _assert_same(entry.read_final(mmap=False), tracked)  # as if never stopped


class _Killed(BaseException):
    """The tracking process killed (SIGTERM from ``mistool serve``'s Ctrl+C)."""


def test_a_run_killed_just_after_storing_a_chunk_resumes_after_it(
    seq: Path, first_chunk: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Killed right after the chunk that completes the frames digest was stored (the
    moment a Ctrl+C lands when it follows the progress, as the serve test's does): the
    digest was stored after that chunk, so it was lost and the next run started again
    from frame 0 (the serve test failed so on a loaded machine)."""
    path, cfg = resolve(seq)
    entry = _entry(seq, tmp_path)
    real = cache.CacheEntry.add_chunk

    def killed_after(self, start, stop, table, state=None):  # noqa: ANN001, ANN202
        real(self, start, stop, table, state)
        raise _Killed

    monkeypatch.setattr(cache.CacheEntry, "add_chunk", killed_after)
    with pytest.raises(_Killed):
        background.track_into(background.JobSpec(path, cfg, entry))
    monkeypatch.undo()
    assert entry.progress().done == first_chunk
    opened: list[cache.Progress] = []
    stop = threading.Event()
    stop.set()
    background.track_into(background.JobSpec(path, cfg, entry), stop, lambda e, p: opened.append(p))
    assert opened[0].done == first_chunk, "the stored chunk was not resumed from"


def test_a_run_killed_while_storing_a_chunk_resumes_after_the_one_before(
    seq: Path, first_chunk: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Killed between storing the tracker's state after a chunk and listing that chunk:
    the state after the chunk before was overwritten, so the next run started again
    from frame 0; it resumes after the chunk before."""
    path, cfg = resolve(seq)
    entry = _entry(seq, tmp_path)
    stop = threading.Event()
    stop.set()
    background.track_into(background.JobSpec(path, cfg, entry), stop)
    assert entry.progress().done == first_chunk
    real = cache.CacheEntry._write_meta

    def killed_listing_the_second(self, meta):  # noqa: ANN001, ANN202
        if len(meta.get("chunks", [])) == 2:
            raise _Killed
        real(self, meta)

    monkeypatch.setattr(cache.CacheEntry, "_write_meta", killed_listing_the_second)
    with pytest.raises(_Killed):
        background.track_into(background.JobSpec(path, cfg, entry))
    monkeypatch.undo()
    assert entry.progress().done == first_chunk
    opened: list[cache.Progress] = []
    background.track_into(background.JobSpec(path, cfg, entry), stop, lambda e, p: opened.append(p))
    assert opened[0].done == first_chunk, "the stored chunk was not resumed from"
    assert len(list(entry.path.glob("state-*.pkl"))) == 1  # the older state removed


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


def _stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/<pid>/stat`` after the command name (None: no such process)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _processes_under(pid: int) -> list[tuple[int, str]]:
    """Every living descendant of ``pid``: (pid, start time), the start time telling a
    process from a later one given the same pid."""
    found: list[tuple[int, str]] = []
    parents = {pid}
    while True:
        new = []
        for d in Path("/proc").glob("[0-9]*"):
            fields = _stat(int(d.name))
            if fields and int(fields[1]) in parents and fields[0] != "Z":
                if int(d.name) not in {p for p, _ in found}:
                    new.append((int(d.name), fields[19]))
        if not new:
            return found
        found += new
        parents = {p for p, _ in new}


def _alive(process: tuple[int, str]) -> bool:
    fields = _stat(process[0])
    return fields is not None and fields[0] != "Z" and fields[19] == process[1]


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
        # What was stored is said once the job has found the cache entry (after the URL).
        return proc, [proc.stdout.readline() for _ in range(3)]

    proc, lines = launch()
    try:
        assert "tracking in the background" in lines[0], lines
        assert "http://" in lines[1], lines
        assert "3,000 frames, tracking from frame 0" in lines[2], lines
        tracking = _processes_under(proc.pid)  # the tracking process (forked) and its own
        assert tracking, "no tracking process"
        # Deadlines are generous: the tracking process runs at a lower priority once its
        # first picture is stored, and on a loaded machine it gets little.
        entry = cache.entries(tmp_path / "cache" / "mistool" / "tables")
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not (entry and entry[0].progress().done >= 50):
            time.sleep(0.2)
            entry = cache.entries(tmp_path / "cache" / "mistool" / "tables")
        assert entry and entry[0].progress().done >= 50
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped" in err and "Traceback" not in err
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and any(_alive(p) for p in tracking):
        time.sleep(0.1)
    assert not any(_alive(p) for p in tracking), "the tracking process kept running"
    done = entry[0].progress().done  # no process is left to change it
    assert 50 <= done < 3000
    proc, lines = launch()  # the next launch resumes where the first stopped
    try:
        assert f"resuming from frame {done}" in lines[2], lines
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0


def _assert_two_worker_job_tracks(seq: Path, tracked: TrackTable, tmp_path: Path) -> None:
    """A background job with 2 worker processes finishes and stores ``tracked``."""
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


def test_background_job_with_worker_processes_gives_the_same_table(
    seq: Path, tracked: TrackTable, tmp_path: Path
) -> None:
    """The job's child process is daemonic (it never outlives its parent), yet it starts
    its own pool of worker processes for ``workers > 1``; the table is the same."""
    _assert_two_worker_job_tracks(seq, tracked, tmp_path)


def test_a_job_forked_from_a_process_that_had_workers_starts_its_own(
    seq: Path, tracked: TrackTable, tmp_path: Path
) -> None:
    """multiprocessing's fork server is per-process state: a tracking child forked from a
    process that had already started worker processes (a script that tracked before it
    served) asked its parent's fork server for its workers, and then could not wait for
    them ("No child processes"); it starts its own."""
    from mistool import parallel

    with parallel.LocalPool(1) as pool:  # this process's fork server is running
        assert pool.submit(abs, -2).result(timeout=60) == 2
    _assert_two_worker_job_tracks(seq, tracked, tmp_path)


def test_the_command_lines_stderr_filter_does_not_stop_the_tracking_process_forking(
    seq: Path, tmp_path: Path
) -> None:
    """Every command runs with a thread filtering the codecs' stderr lines; it holds no
    lock, so ``mistool serve`` still forks its tracking process (a new interpreter cost
    about half a second before the first frame); any other thread means spawn. In a new
    interpreter: pytest's own process has threads of its own."""
    script = f"""
import threading, time
from mistool import background
from mistool.cli import quiet_native_stderr
from mistool.sequence import resolve

path, cfg = resolve({str(seq)!r})
spec = background.JobSpec(path, cfg, None, root=__import__("pathlib").Path({str(tmp_path)!r}))
with quiet_native_stderr():
    threads = threading.active_count()
    job = background.TrackingJob(spec)
    job.start()
    forked = job.method
    while job.opened() is None:
        time.sleep(0.01)
    job.stop()
    other = threading.Thread(target=time.sleep, args=(0.5,))
    other.start()
    print(threads, forked, background.fork_is_safe())
"""
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["2", "fork", "False"]


def test_the_tracking_process_yields_to_the_viewer_after_its_first_picture(
    seq: Path, first_chunk: int, tmp_path: Path
) -> None:
    """Once the first chunk with a drawn frame is stored, the tracking process lowers its
    priority (background.CHILD_NICE): on 2 cores, chromium loading the page with software
    WebGL and the server go first (first picture 2.78 -> 2.67 s, medians of 5)."""
    path, cfg = resolve(seq)
    job = background.TrackingJob(background.JobSpec(path, cfg, None, root=tmp_path))
    base = os.getpriority(os.PRIO_PROCESS, 0)
    job.start()
    try:
        pid = job._process.pid  # type: ignore[union-attr]
        end = time.monotonic() + 60
        niceness = base
        while time.monotonic() < end and job.running:
            niceness = os.getpriority(os.PRIO_PROCESS, pid)
            if niceness != base:
                break
            time.sleep(0.002)
        said = job.opened()
        assert said is not None and said[0] is not None
        assert niceness == min(19, base + background.CHILD_NICE)
        assert said[0].progress().done >= first_chunk  # not before its first picture
    finally:
        job.stop()


# -- mistool serve starts without listing the frames ---------------------------------------
def _grow(feed, replay: Replay, timeout: float = 120.0) -> list[tuple[int, int]]:
    """Poll ``feed`` into ``replay`` until it is finished; the patches' frame ranges."""
    ranges = []
    end = time.monotonic() + timeout
    feed.start()
    try:
        while not feed.finished and time.monotonic() < end:
            for patch in feed.poll(replay):
                replay.apply(patch)
                ranges.append((patch.lo, patch.hi))
            time.sleep(0.05)
    finally:
        feed.stop()
    assert feed.finished, feed.status()
    return ranges


def test_background_load_lists_nothing_and_the_job_finds_the_entry(
    seq: Path,
    tracked: TrackTable,
    first_chunk: int,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Opening a sequence for ``mistool serve`` neither lists its frames nor keys the
    cache in this process (the work that grows with the length): the tracking process
    does both, tells which entry it uses, and the frame names reach the overlay's store
    before the first frame is shown."""
    from mistool import sequence as sequence_module
    from mistool.viewer import app
    from mistool.viewer.app import load_sequence

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    calls: list[str] = []
    real_list, real_key = sequence_module.list_frames, cache.cache_key

    def listing(folder: Path) -> list[Path]:
        calls.append(f"list {os.getpid()}")
        return real_list(folder)

    def keying(*args: object, **kwargs: object) -> str:
        calls.append(f"key {os.getpid()}")
        return real_key(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(sequence_module, "list_frames", listing)
    monkeypatch.setattr("mistool.viewer.overlay.list_frames", listing)
    monkeypatch.setattr(cache, "cache_key", keying)
    loaded = load_sequence(seq, background=True)
    feed = loaded.feed
    assert feed is not None and feed.entry is None and feed.status().phase == "opening"
    assert not loaded.frames.listed and loaded.frames.labels(0) is None
    assert loaded.replay.tracked == 0
    ranges = _grow(feed, loaded.replay)
    here = [c for c in calls if c.endswith(f" {os.getpid()}")]
    assert here == [], "the server's process listed the frames or keyed the cache"
    assert feed.status().phase == "done" and feed.total == N
    assert ranges[0] == (0, first_chunk), ranges  # grew chunk by chunk
    # The length learnt from the job sizes the replay (not doubled past it: 64 frames).
    assert loaded.replay.expected_frames == N == loaded.replay.capacity
    assert loaded.frames.listed and loaded.frames.mask_files == list_frames(seq)
    np.testing.assert_array_equal(
        loaded.frames.labels(3), cv2.imread(str(list_frames(seq)[3]), cv2.IMREAD_UNCHANGED)
    )
    # The job's entry is the one the foreground path (and the key's inputs) name.
    path, cfg = resolve(seq)
    assert feed.entry is not None and feed.entry.key == app._entry_for(path, cfg).key
    _assert_same(feed.entry.read_final(mmap=False), tracked)
    assert feed.stored is not None and feed.stored.done == 0


def test_the_job_keys_the_cache_honestly_and_resumes(
    seq: Path, first_chunk: int, tmp_path: Path
) -> None:
    """With ``entry=None`` the job finds the entry from the frame names: a stopped run is
    resumed by the next job; a touched frame (its size or time: the entry's frames digest)
    or a run stopped before its digest was stored is tracked again from the start."""
    import shutil

    copy = tmp_path / "seq"
    shutil.copytree(seq, copy)
    path, cfg = resolve(copy)
    root = tmp_path / "cache"
    spec = background.JobSpec(path, cfg, None, root=root)
    opened: list[tuple[cache.CacheEntry, cache.Progress]] = []

    def on_open(entry: cache.CacheEntry, progress: cache.Progress) -> None:
        opened.append((entry, progress))

    stop = threading.Event()
    stop.set()  # stop after the first chunk
    first = background.track_into(spec, stop, on_open)
    assert first.done == first_chunk and not first.complete
    done = background.track_into(spec, None, on_open)  # found again: resumed
    assert done.complete
    assert opened[1][0].key == opened[0][0].key
    assert opened[0][1].done == 0 and opened[1][1].done == first_chunk
    assert opened[1][0].frame_names() == [f.name for f in list_frames(copy)]
    assert opened[1][0].frames_digest() == cache.frames_digest(list_frames(copy))
    frame = list_frames(copy)[40]  # a frame of the stored table
    st = frame.stat()
    os.utime(frame, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))  # touched
    background.track_into(spec, stop, on_open)  # the same names: the same entry, emptied
    assert opened[2][0].key == opened[0][0].key and opened[2][1].done == 0
    assert not opened[2][1].complete
    opened[2][0].set_frames_digest("a run stopped before its digest was stored")
    background.track_into(spec, stop, on_open)
    assert opened[3][1].done == 0, "rows of unknown files were reused"
    fresh = background.track_into(replace_fresh(spec), stop, on_open)
    assert opened[4][0].key == opened[2][0].key and opened[4][1].done == 0, "fresh: emptied"
    assert fresh.done == first_chunk


def replace_fresh(spec: background.JobSpec) -> background.JobSpec:
    import dataclasses

    return dataclasses.replace(spec, fresh=True)


def test_feed_reports_a_job_that_fails_before_its_first_frames(seq: Path, tmp_path: Path) -> None:
    """A frame the server's start does not look at (a dangling symlink) stops the job
    before it tracks anything: the feed says so in one line, and shows nothing."""
    from mistool.viewer.feed import CacheFeed

    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "mistool.toml").write_bytes((seq / "mistool.toml").read_bytes())
    for f in list_frames(seq)[:5]:
        os.symlink(f, bad / f.name)
    os.symlink(tmp_path / "gone.png", bad / "000999.png")
    path, cfg = resolve(bad)
    feed = CacheFeed(None, background.JobSpec(path, cfg, None, root=tmp_path / "c"), None)
    replay = Replay(cfg, num_frames=1, image_wh=(720, 576), parts=config_parts(cfg))
    assert _grow(feed, replay) == [] and replay.tracked == 0
    status = feed.status()
    assert status.phase == "failed" and status.done == 0
    assert status.error is not None and "dangling symlink" in status.error
    assert "\n" not in status.error and "dangling symlink" in status.text()


def test_overlay_of_a_frame_not_listed_yet_is_not_kept(seq: Path) -> None:
    """Before a deferred listing arrives, an overlay has no mask: it is drawn but not
    cached, so the same frame is drawn again, with its mask, once the names are known."""
    from mistool.viewer.overlay import FrameStore, OverlayCache, OverlayRenderer

    path, cfg = resolve(seq)
    table = api.track(seq)
    replay = build_replay(table, cfg, num_frames=N, image_wh=(720, 576))
    frames = FrameStore(path, cfg, defer_listing=True)
    assert frames.probe_file is not None and frames.probe_file.parent == path
    assert frames.mask_shape() == (576, 720) and frames.num_mask_frames == 0
    overlays = OverlayCache(OverlayRenderer(replay, frames))
    try:
        busy = int(replay.first_busy_frame() or 0)
        before = overlays.get(busy, 1.0, False)[0]
        assert overlays.peek(busy, 1.0, False) is None, "a render without masks was kept"
        frames.set_mask_names([f.name for f in list_frames(seq)])
        after = overlays.get(busy, 1.0, False)[0]
        assert overlays.peek(busy, 1.0, False) is not None
        assert (after != before).any(axis=2).sum() > 100, "the mask is not drawn"
    finally:
        overlays.close()
        frames.close()


def test_a_deferred_source_folder_is_listed_after_the_server_is_up(
    seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ``source`` folder of a procedure's length (90,000 images: 0.15-0.3 s to list) is
    not listed before the server starts: the viewer lists it in a thread once the first
    frames are drawn; until then no source frame is read and overlays are not kept, then
    they have it."""
    from mistool.viewer import overlay as overlay_module
    from mistool.viewer.app import ReplayViewer, load_sequence

    here = tmp_path / "seq"  # the sequence, with a source folder
    here.mkdir()
    for f in list_frames(seq):
        os.symlink(f, here / f.name)
    toml = (seq / "mistool.toml").read_text()
    (here / "mistool.toml").write_text('source = "src"\n' + toml)
    src = here / "src"
    src.mkdir()
    for k in range(N):
        cv2.imwrite(str(src / f"{k}.jpg"), np.full((576, 720, 3), 40 + 3 * k, np.uint8))
    path, cfg = resolve(here)
    assert cfg.source == src
    frames = overlay_module.FrameStore(path, cfg, defer_listing=True)
    frames.set_mask_names([f.name for f in list_frames(seq)])
    assert frames.has_source and not frames.listed and frames.source(5) is None
    frames.list_source()
    assert frames.listed and frames.source(5) is not None
    assert int(frames.source(12)[0, 0, 0]) == pytest.approx(40 + 3 * 12, abs=2)  # "12" > "5"
    frames.close()

    listed_by: list[str] = []
    real = overlay_module.source_frame_names

    def listing(folder: Path) -> list[str]:
        listed_by.append(threading.current_thread().name)
        return real(folder)

    real_fit = ReplayViewer._fit

    def fit(self: ReplayViewer, busy: int) -> None:
        listed_by.append("fitted")
        real_fit(self, busy)

    def counting(folder: Path) -> list[str]:  # the source's check, counting its frames
        listed_by.append(f"counted {threading.current_thread().name}")
        return real(folder)

    monkeypatch.setattr(overlay_module, "source_frame_names", listing)
    monkeypatch.setattr(ReplayViewer, "_fit", fit)
    monkeypatch.setattr("mistool.sequence.source_frame_names", counting)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    loaded = load_sequence(here, background=True)
    assert listed_by == [] and not loaded.frames.listed
    viewer = ReplayViewer(loaded, port=0)
    try:
        end = time.monotonic() + 60
        while not loaded.frames.listed and time.monotonic() < end:
            time.sleep(0.01)
        # After the first picture: not competing with the browser loading the page.
        assert loaded.frames.listed and listed_by == ["fitted", "mistool-list-source"]
        assert loaded.frames.source(0) is not None
    finally:
        viewer.close()


def test_a_viewer_closed_while_its_feed_starts_the_job_leaves_no_process(
    seq: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Closing the viewer at once (a script, a test, Ctrl+C in the first second) while its
    feed thread is still starting the tracking job: the job started after the feed was
    told to stop kept running, and at exit multiprocessing's handler printed a traceback
    ("process object is closed"). The feed thread is now joined before the job stops."""
    import multiprocessing

    from mistool.viewer.app import ReplayViewer, load_sequence
    from mistool.viewer.feed import CacheFeed

    real_start = CacheFeed.start

    def slow_start(self: CacheFeed) -> None:
        time.sleep(0.3)  # the feed thread is late: close() comes first
        real_start(self)

    monkeypatch.setattr(CacheFeed, "start", slow_start)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    loaded = load_sequence(seq, background=True, fresh=True)
    viewer = ReplayViewer(loaded, port=0)
    viewer.close()
    feed = loaded.feed
    assert feed is not None and feed.job is not None  # it did start
    assert not feed.job.running and viewer.feed_errors == []
    assert [p for p in multiprocessing.active_children() if p.name == "mistool-track"] == []


def test_a_growing_replay_allocates_little_first_and_the_length_once(seq: Path) -> None:
    """The first frames of a long procedure are stored without allocating its whole
    length; storage then doubles, and takes the whole length in one step once that is at
    most 4x the storage (never doubled past it)."""
    _, cfg = resolve(seq)
    table = api.track(seq)
    replay = Replay(cfg, num_frames=1, image_wh=(720, 576), parts=config_parts(cfg))
    replay.expected_frames = 90_000
    capacities = []
    for lo in range(0, 40_000, 25):  # 25-frame patches (most empty: past the table)
        replay.apply(replay.compute(table, lo, lo + 25))
        if not capacities or capacities[-1] != replay.capacity:
            capacities.append(replay.capacity)
    # 64 .. 16,384 doubling; the next doubling (32,768) is within 4x of the length: 90,000.
    assert capacities == [64 * 2**k for k in range(9)] + [90_000]


class _StopAfter:
    """A stop event set after ``n`` chunks (``track_into`` asks once per chunk)."""

    def __init__(self, n: int) -> None:
        self.asked, self.n = 0, n

    def is_set(self) -> bool:
        self.asked += 1
        return self.asked >= self.n


def test_the_frames_digest_is_spread_over_the_first_chunks(
    seq: Path, first_chunk: int, tmp_path: Path
) -> None:
    """A new run stats its files as it goes (STATS_PER_FRAME per frame tracked, each file
    before it is read), not all before its first chunk: stopped before every file is in
    the digest, nothing is reused; once it is stored, the run resumes."""
    long = tmp_path / "long"
    long.mkdir()
    (long / "mistool.toml").write_bytes((seq / "mistool.toml").read_bytes())
    frames = list_frames(seq)
    n = 3 * background.STATS_PER_FRAME * background.CHUNK_SCHEDULE[0]  # > the first chunk's
    for k in range(n):
        os.symlink(
            frames[k % N] if (k // N) % 2 == 0 else frames[N - 1 - k % N], long / f"{k:05d}.png"
        )
    path, cfg = resolve(long)
    spec = background.JobSpec(path, cfg, None, root=tmp_path / "cache")
    opened: list[tuple[cache.CacheEntry, cache.Progress]] = []

    def on_open(entry: cache.CacheEntry, progress: cache.Progress) -> None:
        opened.append((entry, progress))

    background.track_into(spec, _StopAfter(1), on_open)
    entry = opened[0][0]
    assert entry.progress().done == first_chunk
    assert entry.frames_digest() is None, "every frame was stat'ed before the first chunk"
    background.track_into(spec, _StopAfter(2), on_open)
    assert opened[1][1].done == 0, "a run without its digest was resumed"
    assert entry.frames_digest() == cache.frames_digest(list_frames(long))
    background.track_into(spec, _StopAfter(1), on_open)
    # The first chunk ended at the first instrument; the second is the schedule's second.
    assert opened[2][1].done == first_chunk + background.CHUNK_SCHEDULE[1], "not resumed"
