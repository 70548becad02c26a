"""Per-frame work in worker processes: identical outputs whatever the number of workers,
the chunked API (iter_track + refine = track), bounded work in flight, one-line errors
from a worker, and no worker process left behind on errors or interrupts."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import re
import signal
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from mistool import parallel
from mistool.api import iter_track, refine, run, track
from mistool.config import Config, InstrumentSpec
from mistool.errors import InputPathError, MaskFormatError
from mistool.model import InstanceObservation, PartObservation, RotatedBox, TrackTable
from mistool.sequence import open_sequence
from mistool.synth import synthesize


def assert_same(a: TrackTable, b: TrackTable) -> None:
    """Every column equal, NaN where NaN (bit for bit on numbers)."""
    assert a.columns == b.columns and a.num_rows == b.num_rows
    for c in a.columns:
        if a[c].dtype == object:
            assert a[c].tolist() == b[c].tolist(), c
        else:
            np.testing.assert_array_equal(a[c], b[c], err_msg=c)


@pytest.fixture(scope="module")
def crossing(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """60 frames, two instruments with merged labels that cross (seed 3: the identity
    step splits their blob in 3 frames), with a camera (metric pose)."""
    out = tmp_path_factory.mktemp("cross") / "seq"
    synthesize(out, frames=60, instruments=2, seed=3)
    return out


def test_the_fixture_takes_the_split_path(crossing: Path) -> None:
    from mistool import tracking

    seq = open_sequence(crossing)
    tracker = tracking.IdentityTracker(seq.config)
    splits = 0
    for i, _, labels in seq:
        found = tracking.observe_frame(labels, seq.config)
        splits += tracker.resolve(i, found)[0] is not found
    assert splits >= 1 and seq.config.camera is not None


def test_workers_1_and_2_give_identical_tables(crossing: Path) -> None:
    one = track(crossing, workers=1)
    two = track(crossing, workers=2)
    assert one.num_rows > 100 and np.isfinite(one["end_x_mm"]).sum() > 50
    assert set(one["instrument"].tolist()) == {"1", "2"}
    assert_same(one, two)


def test_iter_track_chunks_in_frame_order_and_refine_gives_track(crossing: Path) -> None:
    chunks = list(iter_track(crossing, workers=2, chunk_frames=7))
    assert len(chunks) == 9  # 60 frames: 8 x 7 + 4
    for k, chunk in enumerate(chunks):
        frames = chunk["frame"]
        assert frames.size == 0 or (frames.min() >= 7 * k and frames.max() < 7 * (k + 1))
        assert "dx_px" not in chunk.columns  # raw rows: no paper motion yet
    seq = open_sequence(crossing)
    whole = refine(TrackTable.concat(chunks), seq.config)
    assert_same(whole, track(crossing, workers=1))
    online = refine(TrackTable.concat(chunks), seq.config, smoothing="online")
    assert_same(online, track(crossing, workers=1, smoothing="online"))


def test_iter_track_of_nothing_yields_one_empty_table() -> None:
    chunks = list(iter_track([np.zeros((20, 30), np.uint8)] * 3, Config(), workers=1))
    assert len(chunks) == 1 and chunks[0].num_rows == 0 and "cx_px" in chunks[0]


def test_arrays_through_the_pool_equal_in_process(crossing: Path) -> None:
    frames = [labels for _, _, labels in open_sequence(crossing)]
    cfg = open_sequence(crossing).config
    assert_same(track(frames, cfg, workers=2), track(crossing, workers=1))


def _pool_children() -> list[multiprocessing.process.BaseProcess]:
    return list(multiprocessing.active_children())


@pytest.mark.parametrize("in_caller", [False, True])
def test_a_bad_frame_in_a_worker_names_the_frame_and_stops_the_workers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, in_caller: bool
) -> None:
    """The same one-line error whether a worker or the caller (while the workers start)
    decodes the bad frame."""
    img = np.zeros((40, 60), np.uint8)
    img[15:25, 5:40] = 160
    for i in range(40):
        cv2.imwrite(str(tmp_path / f"f{i:03d}.png"), img)
    (tmp_path / "f031.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    monkeypatch.setattr(parallel.LocalPool, "warming", lambda self: in_caller)
    before = set(_pool_children())
    where = re.escape(str(tmp_path.resolve() / "f031.png"))  # the whole path, once
    with pytest.raises(MaskFormatError, match=rf"^{where}: cannot decode as an image \("):
        track(tmp_path, workers=2)
    assert not set(_pool_children()) - before


def test_while_the_workers_start_the_caller_works_on_the_first_frames(crossing: Path) -> None:
    """Batches taken while the pool says it is warming are worked on in the caller, the
    rest in the pool; the table is the same. A real pool stops warming once every
    worker process has answered."""
    from concurrent.futures import Future

    class StartingPool:
        workers = 2
        batch_frames = 4

        def __init__(self) -> None:
            self.asked = 0
            self.batches = 0

        def warming(self) -> bool:
            self.asked += 1
            return self.asked <= 3

        def submit(self, fn, *args):  # type: ignore[no-untyped-def]
            self.batches += fn is parallel.observe_batch
            fut: Future = Future()
            fut.set_result(fn(*args))
            return fut

        def close(self) -> None:
            pass

    pool = StartingPool()
    chunks = list(iter_track(crossing, pool=pool))
    assert pool.batches == 60 // 4 - 3
    cfg = open_sequence(crossing).config
    assert_same(refine(TrackTable.concat(chunks), cfg), track(crossing, workers=1))
    with parallel.LocalPool(2) as real:
        deadline = time.monotonic() + 120
        while real.warming() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not real.warming()
        assert len({real.submit(os.getpid).result() for _ in range(4)} - {os.getpid()}) >= 1


def test_stopping_early_terminates_the_workers(
    crossing: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(parallel.LocalPool, "warming", lambda self: False)  # 2 started
    before = set(_pool_children())
    gen = iter_track(crossing, workers=2, chunk_frames=5)
    next(gen)
    started = set(_pool_children()) - before
    assert len(started) == 2
    gen.close()  # what a consumer's error or Ctrl+C does to the generator
    assert not any(p.is_alive() for p in started)

    def interrupt(_: int) -> None:  # Ctrl+C in the caller while frames are in flight
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run(crossing, workers=2, on_frames=interrupt)
    assert not set(_pool_children()) - before


def test_frames_in_flight_are_bounded_per_worker(tmp_path: Path) -> None:
    """A pool that counts submitted-but-unconsumed batches (in this process)."""
    from concurrent.futures import Future

    class CountingPool:
        workers = 3
        batch_frames = 2

        def __init__(self) -> None:
            self.pending: list[Future] = []
            self.peak = 0

        def submit(self, fn, *args):  # type: ignore[no-untyped-def]
            fut: Future = Future()
            fut.set_result(fn(*args))
            self.pending = [f for f in self.pending if not getattr(f, "taken", False)]
            self.pending.append(fut)
            self.peak = max(self.peak, len(self.pending))
            original = fut.result

            def result(timeout: float | None = None) -> object:
                fut.taken = True  # type: ignore[attr-defined]
                return original(timeout)

            fut.result = result  # type: ignore[method-assign]
            return fut

        def close(self) -> None:
            pass

    img = np.zeros((40, 60), np.uint8)
    img[15:25, 5:40] = 160
    pool = CountingPool()
    chunks = list(iter_track([img] * 50, Config(), pool=pool))
    assert sum(c.num_rows for c in chunks) == 50
    assert pool.peak <= parallel.IN_FLIGHT_PER_WORKER * pool.workers


def test_split_pieces_are_measured_in_the_pool_while_frames_go_on(crossing: Path) -> None:
    """The identity step stays in the caller; the metric pose of the pieces of a split
    blob is a pool task, finished later (frames are identified meanwhile), and the rows
    are the same as when the caller measures them."""
    from concurrent.futures import Future

    class DeferredPool:
        """Runs tasks in this process, the pieces' only when their result is asked."""

        workers = 2
        batch_frames = 1  # one frame per task: its pieces' task is submitted at once

        def __init__(self) -> None:
            self.pieces = 0
            self.later = 0  # piece tasks not done when the caller checked

        def submit(self, fn, *args):  # type: ignore[no-untyped-def]
            fut: Future = Future()
            if fn is not parallel.measure_frames:
                fut.set_result(fn(*args))
                return fut
            self.pieces += 1
            done = False

            def is_done() -> bool:
                self.later += not done
                return done

            def result(timeout: float | None = None) -> object:
                nonlocal done
                if not done:
                    fut.set_result(fn(*args))
                    done = True
                return Future.result(fut, timeout)

            fut.done = is_done  # type: ignore[method-assign]
            fut.result = result  # type: ignore[method-assign]
            return fut

        def close(self) -> None:
            pass

    pool = DeferredPool()
    chunks = list(iter_track(crossing, pool=pool, chunk_frames=7))
    assert pool.pieces >= 1 and pool.later >= 1
    seq = open_sequence(crossing)
    assert_same(refine(TrackTable.concat(chunks), seq.config), track(crossing, workers=1))


def test_a_blob_of_crossing_tools_has_its_pose_measured_after_the_identity_step(
    crossing: Path,
) -> None:
    """A frame with fewer instances than recently seen (the crossing blob) comes back
    from its worker without a pose (deferred): the caller has it measured once the
    identity step has split it or kept it, so the blob's own pose is never measured in
    vain; the rows are those of the in-process run."""
    from concurrent.futures import Future

    class InlinePool:
        workers = 1
        batch_frames = 1  # each frame submitted just after the one before is identified

        def __init__(self) -> None:
            self.deferred = 0
            self.measured = 0  # frames measured by measure_frames tasks

        def submit(self, fn, *args):  # type: ignore[no-untyped-def]
            fut: Future = Future()
            out = fn(*args)
            if fn is parallel.observe_batch:
                self.deferred += sum(r.deferred for r in out)
            else:
                self.measured += len(out)
            fut.set_result(out)
            return fut

        def close(self) -> None:
            pass

    pool = InlinePool()
    chunks = list(iter_track(crossing, pool=pool))
    assert pool.deferred >= 1 and pool.measured >= pool.deferred
    img = np.zeros((40, 60), np.uint8)
    img[15:25, 5:40] = 160
    cfg = open_sequence(crossing).config
    shape = (40, 60)
    never = parallel.observe_labels(img, cfg, True)
    below = parallel.observe_labels(img, cfg, True, defer_below=2)
    assert not never.deferred and len(never.metrics) == len(never.instances) == 1
    assert below.deferred and below.metrics is None and below.shape == shape
    assert not parallel.observe_labels(img, cfg, False, defer_below=2).deferred
    assert_same(refine(TrackTable.concat(chunks), cfg), track(crossing, workers=1))


def test_the_workers_compute_the_identity_steps_border_runs(crossing: Path) -> None:
    """Each instance's shaft border runs come with the frame's result (computed in the
    worker, not in the sequential caller); the identity step given them returns what it
    returns computing them itself, frame after frame."""
    from mistool import tracking
    from mistool.tracking.split import border_runs

    seq = open_sequence(crossing)
    cfg = seq.config
    given, itself = tracking.IdentityTracker(cfg), tracking.IdentityTracker(cfg)
    entering = 0
    for i, _, labels in seq:
        result = parallel.observe_labels(labels, cfg, False)
        assert (result.runs is None) == (not result.instances)  # (no instance: none)
        for inst, runs in zip(result.instances, result.runs or [], strict=True):
            want = border_runs(inst)
            assert len(runs) == len(want)
            for (ends, n), (ends2, n2) in zip(runs, want, strict=True):
                assert n == n2 and np.array_equal(ends, ends2)
            entering += len(runs)
        a, names_a = given.resolve(i, result.instances, result.runs)
        b, names_b = itself.resolve(i, result.instances)
        assert names_a == names_b and len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            assert x.parts.keys() == y.parts.keys() and x.bbox_xywh == y.bbox_xywh
    assert entering >= 1  # the fixture's tools enter the view
    labelled = Config(instruments=(InstrumentSpec("a", {"shaft": (10, 10)}),))
    img = np.zeros((40, 60), np.uint8)
    img[15:25, 5:40] = 10
    assert parallel.observe_labels(img, labelled, False).runs is None


def test_a_script_without_a_main_guard_is_not_run_again_by_the_workers(
    crossing: Path, tmp_path: Path
) -> None:
    import subprocess
    import sys

    script = tmp_path / "user_script.py"
    script.write_text(
        "import mistool\n"
        f"table = mistool.track({str(crossing)!r}, workers=2)\n"
        "print('rows', table.num_rows)\n"
    )
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.count("rows") == 1 and done.stderr == ""


_KILLED_PARENT = """
import os, sys, time
from mistool import parallel
pool = parallel.LocalPool(2)
futures = [pool.submit(os.getpid) for _ in range(8)]
print(" ".join(str(p) for p in sorted({f.result() for f in futures})), flush=True)
time.sleep(60)
"""


def test_workers_exit_when_their_parent_is_killed(tmp_path: Path) -> None:
    """SIGKILL leaves the parent no chance to stop its workers: they notice and exit."""
    import signal
    import subprocess
    import sys
    import time

    child = subprocess.Popen(
        [sys.executable, "-c", _KILLED_PARENT], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout is not None
        pids = [int(p) for p in child.stdout.readline().split()]
        assert pids and child.pid not in pids
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()

    def alive(pid: int) -> bool:
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().split(")")[-1].split()[0] != "Z"
        except FileNotFoundError:
            return False

    deadline = time.monotonic() + 30
    while any(alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(alive(p) for p in pids), [p for p in pids if alive(p)]


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def test_ctrl_c_on_the_command_line_stops_every_worker(crossing: Path, tmp_path: Path) -> None:
    """SIGINT to the whole process group, as a terminal's Ctrl+C: one line, exit 130, no
    output file, and no process of the run left."""
    import os
    import shutil
    import signal
    import subprocess
    import sys
    import time

    # A long sequence (the 60 frames linked 50 times over), so that the run cannot finish
    # before the SIGINT lands (the 60 frames alone take ~1.5 s: a race).
    long_seq = tmp_path / "long"
    long_seq.mkdir()
    shutil.copy(crossing / "mistool.toml", long_seq / "mistool.toml")
    frames = sorted(crossing.glob("*.png"))
    for k in range(50 * len(frames)):
        (long_seq / f"{k:06d}.png").symlink_to(frames[k % len(frames)])
    out = tmp_path / "o.csv"
    code = (
        "import sys; from mistool.cli import main; "
        f"sys.exit(main(['track', {str(long_seq)!r}, '-o', {str(out)!r}, '--workers', '2']))"
    )
    child = subprocess.Popen(
        [sys.executable, "-c", code], stderr=subprocess.PIPE, text=True, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 120
        workers: list[int] = []
        while len(workers) < 2 and time.monotonic() < deadline and child.poll() is None:
            workers = [w for s in _children(child.pid) for w in _children(s)]
            time.sleep(0.02)
        assert len(workers) == 2, "the workers never started"
        os.killpg(child.pid, signal.SIGINT)
        _, err = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == 130 and err == "mistool: interrupted\n", err
    assert not out.exists()
    deadline = time.monotonic() + 30
    while any(Path(f"/proc/{w}").exists() for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [w for w in workers if Path(f"/proc/{w}").exists()]


@pytest.fixture(scope="module")
def crossing_video(crossing: Path) -> Path:
    """The crossing fixture's 60 frames as a grey MJPG mask video, with its config."""
    out = crossing.parent / "video"
    out.mkdir()
    (out / "mistool.toml").write_bytes((crossing / "mistool.toml").read_bytes())
    frames = [labels for _, _, labels in open_sequence(crossing)]
    h, w = frames[0].shape
    writer = cv2.VideoWriter(
        str(out / "masks.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25, (w, h), False
    )
    for f in frames:
        writer.write(f)
    writer.release()
    return out / "masks.avi"


def _tracked_with_warnings(source: Path, workers: int) -> tuple[TrackTable, list[str]]:
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        table = track(source, workers=workers)
    return table, [str(w.message) for w in caught]


def test_a_mask_video_is_decoded_by_the_workers_not_the_caller(
    crossing_video: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With a local pool the workers decode the video's frames themselves (each reads it
    in order, skipping the other workers' frames): the caller never decodes a frame,
    and the table is the one the caller's own decoding gives."""
    from mistool import sequence

    one, _ = _tracked_with_warnings(crossing_video, 1)
    decoded: list[str] = []
    real = sequence.MaskSequence.frames

    def frames(self: sequence.MaskSequence):  # type: ignore[no-untyped-def]
        decoded.append(self.name)
        return real(self)

    monkeypatch.setattr(sequence.MaskSequence, "frames", frames)
    two, _ = _tracked_with_warnings(crossing_video, 2)
    assert decoded == [] and one.num_rows > 100
    assert_same(one, two)


def test_a_truncated_or_corrupt_video_warns_the_same_with_workers(
    crossing: Path, tmp_path: Path
) -> None:
    """The end of a video decoded by the workers (a file cut short) and its frames that
    look like garbage give the caller's warnings, and the same table."""
    frames = [labels for _, _, labels in open_sequence(crossing)]
    h, w = frames[0].shape
    (tmp_path / "mistool.toml").write_bytes((crossing / "mistool.toml").read_bytes())
    path = tmp_path / "masks.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (w, h), False)
    noise = np.random.default_rng(0).integers(0, 256, (h, w), dtype=np.uint8)
    for i, f in enumerate(frames):
        writer.write(noise if i in (5, 17) else f)
    writer.release()
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.7)])
    one, said_one = _tracked_with_warnings(path, 1)
    two, said_two = _tracked_with_warnings(path, 2)
    assert any("look corrupt (#5, #17" in m for m in said_one), said_one
    assert any("the video ended after" in m for m in said_one), said_one
    assert said_two == said_one
    assert 10 < one["frame"].max() < 59
    assert_same(one, two)


def test_a_dataset_of_mask_videos_through_one_pool_equals_each_alone(
    crossing: Path, tmp_path: Path
) -> None:
    """One pool serves every sequence of a dataset: its workers switch from one video to
    the next (and to a folder in between) and each table is the video's tracked alone."""
    import shutil

    from mistool.cli import main

    root = tmp_path / "data"
    root.mkdir()
    (root / "mistool.toml").write_bytes((crossing / "mistool.toml").read_bytes())
    frames = [labels for _, _, labels in open_sequence(crossing)]
    h, w = frames[0].shape
    for name, order in (("a", frames[:45]), ("c", frames[::-1][:37])):
        writer = cv2.VideoWriter(
            str(root / f"{name}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25, (w, h), False
        )
        for f in order:
            writer.write(f)
        writer.release()
    shutil.copytree(crossing, root / "b")
    out = tmp_path / "out"
    assert main(["track", str(root), "-o", str(out), "-q", "--workers", "2"]) == 0
    for name in ("a", "c"):
        alone = tmp_path / f"{name}.csv"
        argv = ["track", str(root / f"{name}.avi"), "-o", str(alone), "-q", "--workers", "1"]
        assert main(argv) == 0
        assert alone.read_bytes() == (out / f"{name}_motion.csv").read_bytes(), name


def test_terminating_the_pool_unblocks_a_half_received_result() -> None:
    """A worker terminated while writing its result leaves half a message in the result
    pipe: the executor's manager thread waits for the rest, and the interpreter joins it
    at exit (a Ctrl+C'd ``mistool track --workers 2`` hung after "interrupted").
    Terminating the pool must let that thread finish."""
    import struct

    pool = parallel.LocalPool(1)
    ex = pool._executor
    assert ex is not None
    assert pool.submit(abs, -3).result(timeout=60) == 3  # the manager thread is running
    manager = ex._executor_manager_thread
    writer = ex._result_queue._writer
    assert manager is not None and manager.is_alive()
    # What a worker killed mid-write leaves: a header announcing 100 bytes, then 10.
    os.write(writer.fileno(), struct.pack("!i", 100) + b"x" * 10)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and "recv" not in _stack_of(manager):
        time.sleep(0.01)
    assert "recv" in _stack_of(manager), "the manager thread is not reading the result"
    pool.close(terminate=True)
    manager.join(timeout=30)
    try:
        assert not manager.is_alive(), "the manager thread still waits for the result"
    finally:
        if manager.is_alive():  # unblock it, or this test run would hang at exit
            writer.close()


def _stack_of(thread: threading.Thread) -> str:
    import sys
    import traceback

    frame = sys._current_frames().get(thread.ident or -1)
    return "".join(traceback.format_stack(frame)) if frame is not None else ""


def test_the_fork_server_and_workers_start_with_ctrl_c_blocked() -> None:
    """A terminal's Ctrl+C goes to the whole process group: one landing while the fork
    server was still importing (before it ignores SIGINT) printed its KeyboardInterrupt
    traceback under 'mistool: interrupted' (2 of 20 runs of scripts/stress_ctrl_c.py).
    The pool's processes are started from a thread that blocks SIGINT, so they start
    with it blocked; the caller's main thread still gets it."""
    import re

    def blocked(pid: int) -> bool:
        status = Path(f"/proc/{pid}/status").read_text()
        mask = int(re.search(r"SigBlk:\s*(\w+)", status).group(1), 16)  # type: ignore[union-attr]
        return bool(mask & (1 << (signal.SIGINT - 1)))

    with parallel.LocalPool(2) as pool:
        pids = {pool.submit(os.getpid).result(timeout=60) for _ in range(8)}
        parents = {int(Path(f"/proc/{p}/stat").read_text().split()[3]) for p in pids}
        assert pids and all(blocked(p) for p in pids | parents)
    assert not blocked(os.getpid())


def test_the_pools_cancelled_future_race_is_not_printed(monkeypatch: pytest.MonkeyPatch) -> None:
    """A Ctrl+C'd run: the pool's manager thread, finding the terminated workers, marked
    every pending future failed, and one the consumer had just cancelled raised
    InvalidStateError; its traceback was printed under "mistool: interrupted" (a fresh-
    clone CI run of test_ctrl_c_on_the_command_line_stops_every_worker). Once a pool is
    terminated that error is dropped, and only that one."""
    from concurrent.futures import Future, InvalidStateError

    class _ExecutorManagerThread:  # the name of Python's manager thread class
        pass

    def raised(exc_type: type[BaseException], fn: Callable[[], object]) -> object:
        try:
            fn()
        except exc_type as exc:
            return threading.ExceptHookArgs(
                [exc_type, exc, exc.__traceback__, _ExecutorManagerThread()]
            )
        raise AssertionError("did not raise")

    cancelled: Future[int] = Future()
    cancelled.cancel()
    race = raised(InvalidStateError, lambda: cancelled.set_exception(RuntimeError("broken")))
    other = raised(ValueError, lambda: int("x"))
    seen: list[type] = []
    monkeypatch.setattr(threading, "excepthook", lambda args: seen.append(args.exc_type))
    monkeypatch.setattr(parallel, "_previous_excepthook", None)
    threading.excepthook(race)
    assert seen == [InvalidStateError]  # printed before a pool is terminated
    with parallel.LocalPool(1) as pool:
        pool.submit(abs, -1).result(timeout=60)
        pool.close(terminate=True)
    threading.excepthook(race)
    threading.excepthook(other)
    assert seen == [InvalidStateError, ValueError]


def _frame_key(r: parallel.FrameResult) -> tuple:
    """Everything in a frame's result, numbers as bits (``pickle`` of the packed form)."""
    import pickle

    packed = parallel.pack_frames([r])
    return (
        pickle.dumps(packed[:9]),  # (the metric pose as bits)
        None if r.metrics is None else (r.metrics.shape, r.metrics.tobytes()),
        r.unknown.tolist(),
        r.shape,
        r.deferred,
        repr(r.runs),
    )


def test_an_8_bit_grey_png_is_read_straight_to_runs_with_the_same_results(
    crossing: Path, tmp_path: Path
) -> None:
    """A worker decodes an 8-bit grey PNG straight to its runs (``_load``: no image):
    the frame's results are those of the decoded image, bit for bit (instances, boxes,
    masks, metric pose, unknown values, border runs). Other files (16-bit, palette, a
    file the fast decoder leaves to OpenCV, colour labels) are read as images, as
    before; a broken file is the same one-line error."""
    from mistool.sequence import read_label_image
    from mistool.tracking.instances import LabelRuns

    cfg = open_sequence(crossing).config
    frames = sorted(crossing.glob("*.png"))[::7]
    for path in frames:
        runs = parallel._load(path, cfg)
        assert isinstance(runs, LabelRuns)
        image = read_label_image(path, max_pixels=cfg.max_pixels)
        for metric in (False, True):
            assert _frame_key(parallel.observe_labels(runs, cfg, metric)) == _frame_key(
                parallel.observe_labels(image, cfg, metric)
            )
    img = read_label_image(frames[3])
    img[0, :3] = 7  # a value the config does not know
    folder = tmp_path / "odd"
    folder.mkdir()
    cv2.imwrite(str(folder / "sixteen.png"), img.astype(np.uint16))
    blob = cv2.imencode(".png", img)[1].tobytes()
    gama = b"gAMA\x00\x00\xb1\x8f"  # an ancillary chunk the fast decoder leaves to OpenCV
    chunk = len(gama[4:]).to_bytes(4, "big") + gama + zlib.crc32(gama).to_bytes(4, "big")
    (folder / "gama.png").write_bytes(blob[:33] + chunk + blob[33:])
    want = parallel.observe_labels(img, cfg, True)
    for name in ("gama", "sixteen"):
        got = parallel._load(folder / f"{name}.png", cfg)
        assert isinstance(got, np.ndarray)
        result = parallel.observe_labels(got, cfg, True)
        assert result.unknown.tolist() == [7]
        assert _frame_key(result)[:4] == _frame_key(want)[:4]
    grey = tmp_path / "grey"
    grey.mkdir()
    (grey / "a.png").write_bytes(blob)
    assert isinstance(parallel._load(grey / "a.png", cfg), LabelRuns)
    colour = dataclasses.replace(cfg, colour_masks=True)  # packed colours: an image
    assert parallel._load(grey / "a.png", colour).dtype == np.uint32  # type: ignore[union-attr]
    (grey / "cut.png").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(MaskFormatError, match=r"cut\.png: cannot decode"):
        parallel._load(grey / "cut.png", cfg)


def test_a_frame_file_is_read_whole_and_its_read_errors_are_unchanged(
    crossing: Path, tmp_path: Path
) -> None:
    """A worker reads a frame's file with ``os.read`` (``parallel._read``, no file
    objects): a file longer than one read (a PNG with a large text chunk, which the fast
    decoder takes) is read whole and decoded to the same runs; a folder named like a
    frame and a missing file give ``read_label_image``'s one-line error."""
    from mistool.sequence import read_label_image
    from mistool.tracking.instances import LabelRuns, scan_labels

    cfg = open_sequence(crossing).config
    path = sorted(crossing.glob("*.png"))[5]
    blob = path.read_bytes()
    text = b"tEXt" + b"Comment\x00" + bytes(range(32, 127)) * 1000  # ~95 KB
    chunk = (len(text) - 4).to_bytes(4, "big") + text + zlib.crc32(text).to_bytes(4, "big")
    big = tmp_path / "big"
    big.mkdir()
    (big / "a.png").write_bytes(blob[:33] + chunk + blob[33:])
    assert (big / "a.png").stat().st_size > 4 * parallel._READ_PIECE
    assert parallel._read(str(big / "a.png")) == (big / "a.png").read_bytes()
    got = parallel._load(big / "a.png", cfg)
    want = scan_labels(read_label_image(path))
    assert isinstance(got, LabelRuns) and got.bounds == want.bounds and got.n == want.n
    for name in ("ry", "rx0", "rx1", "rv"):
        assert getattr(got, name)[: got.n].tolist() == getattr(want, name)[: want.n].tolist()
    (big / "b.png").mkdir()
    with pytest.raises(InputPathError, match=r"b\.png: cannot read: Is a directory"):
        parallel._load(big / "b.png", cfg)
    with pytest.raises(InputPathError, match=r"c\.png: cannot read: No such file"):
        parallel._load(big / "c.png", cfg)


@pytest.mark.parametrize("seed", range(6))
def test_unknown_values_of_8_bit_frames_are_the_trackings(seed: int) -> None:
    """The values a frame has that the config does not know, from its runs or its
    8-bit histogram through a per-config table of the 256 values: those
    ``tracking.unknown_values`` gives (mask videos: values covering at least
    ``min_area_px`` pixels, none up to ``VIDEO_TOLERANCE``), whatever the config."""
    from mistool import tracking
    from mistool.sequence import VIDEO_TOLERANCE
    from mistool.tracking.instances import scan_labels

    rng = np.random.default_rng(seed)
    configs = [
        Config(),
        Config(labels="endovis17", min_area_px=3),
        Config(instruments=(InstrumentSpec("a", {"shaft": (10, 12), "clasper": (200, 255)}),)),
    ]
    for cfg in configs:
        for _ in range(4):
            img = np.zeros((30, 50), np.uint8)
            for v in rng.integers(0, 256, int(rng.integers(0, 8))):
                y, x = rng.integers(0, 30), rng.integers(0, 50)
                img[y : y + int(rng.integers(1, 4)), x : x + int(rng.integers(1, 6))] = v
            for lossy in (False, True):
                hist = np.bincount(img.ravel(), minlength=256)
                present = np.flatnonzero(hist >= (max(cfg.min_area_px, 1) if lossy else 1))
                if lossy:
                    present = present[present > VIDEO_TOLERANCE]
                want = tracking.unknown_values(present.astype(np.uint8)[None, :], cfg)
                for got in (
                    parallel.unknown_values(img, cfg, lossy),
                    parallel.unknown_values(img, cfg, lossy, runs=scan_labels(img)),
                    parallel.unknown_values(None, cfg, lossy, runs=scan_labels(img)),
                ):
                    assert got.dtype == np.int64 and got.tolist() == want.tolist()


def test_a_batch_defers_a_frame_with_fewer_instances_than_an_earlier_frame_of_it(
    crossing: Path,
) -> None:
    """Within a batch that defers (``defer_below`` > 0: the caller's hint, one batch old,
    64 frames or more behind), a worker defers the pose of a frame with fewer instances
    than an earlier frame of the same batch; the frames of as many instances keep
    theirs, and a batch that never defers (0: the viewer's tracking) defers nothing."""
    cfg = open_sequence(crossing).config
    two = np.zeros((40, 60), np.uint8)
    two[3:9, 2:45] = 160
    two[30:36, 2:45] = 160
    one = np.zeros((40, 60), np.uint8)
    one[15:25, 5:40] = 160
    frames = [two, one, two]
    assert [len(parallel.observe_labels(f, cfg, True).instances) for f in frames] == [2, 1, 2]
    batch = parallel.Batch(("a", "b", "c"), tuple(frames), cfg, True, False, defer_below=1)
    got = parallel.observe_batch(batch)
    assert [r.deferred for r in got] == [False, True, False]
    assert len(got[0].metrics) == 2 and got[1].metrics is None and len(got[2].metrics) == 2
    first = parallel.Batch(("b",), (one,), cfg, True, False, defer_below=1)
    assert not parallel.observe_batch(first)[0].deferred  # nothing earlier in its batch
    never = parallel.Batch(("a", "b"), (two, one), cfg, True, False)  # (defer_below 0)
    assert [r.deferred for r in parallel.observe_batch(never)] == [False, False]


@pytest.mark.parametrize(
    "changes",
    [
        {},
        {"metrics": None},
        {"instances": [], "metrics": np.zeros((0, 3, 28)), "deferred": False},
        {"corrupt": True, "runs": [[]], "shape": (3, 4)},
    ],
)
def test_a_frame_result_replaced_is_dataclasses_replace(changes) -> None:
    """FrameResult.replaced (the caller's copy of a split or deferred frame's result)
    gives what dataclasses.replace gives: every field, the changed ones new, a new
    object; an unknown field is an error naming it."""
    r = parallel.FrameResult([], None, np.zeros(2, np.int64), (5, 6), deferred=True)
    got, want = r.replaced(**changes), dataclasses.replace(r, **changes)
    assert got is not r and type(got) is parallel.FrameResult
    assert [f.name for f in dataclasses.fields(got)] == [f.name for f in dataclasses.fields(want)]
    for f in dataclasses.fields(want):
        assert getattr(got, f.name) is getattr(want, f.name), f.name
    assert r.deferred and r.metrics is None and r.shape == (5, 6)  # the original unchanged
    with pytest.raises(TypeError, match="'metric'"):
        r.replaced(metric=None)


def test_a_mask_the_identity_step_seldom_reads_is_unpacked_at_its_first_use() -> None:
    """The caller unpacks the mask bits of a shaft, and of a head in a frame not deferred
    with one instrument, only when the mask is read (the identity step seldom reads them:
    a blob's shaft runs come from its bits), the others at once (a deferred frame's
    heads, a head beside another instrument: one ``unpackbits`` for the batch): read in
    any order, each mask equals the one the worker had (bool, C-contiguous, its shape);
    a part pickled or replaced unread is a plain PartObservation of the same values."""
    import pickle

    rng = np.random.default_rng(5)
    sent = []
    for n, deferred in ((2, False), (0, False), (3, True), (1, False), (2, False)):
        parts = {}
        for name in ("clasper", "shaft", "wrist")[: 1 + n % 3]:
            h, w = (int(v) for v in rng.integers(1, 13, 2))
            box = RotatedBox(5.0, 6.0, 9.0, 2.0, 30.0)
            mask = rng.random((h, w)) < 0.5
            parts[name] = PartObservation(name, box, box.corners(), 7, mask, (3, 4))
        inst = InstanceObservation(None, parts, (1.0, 2.0), 7, (3, 4, 5, 6), (40, 50))
        empty = np.zeros(0, np.int64)
        sent.append(parallel.FrameResult([inst] * n, None, empty, (40, 50), deferred=deferred))
    got = parallel.unpack_frames(parallel.pack_frames(sent))
    pairs = [
        (p, q, s.deferred, len(s.instances))
        for g, s in zip(got, sent, strict=True)
        for gi, si in zip(g.instances, s.instances, strict=True)
        for p, q in zip(gi.parts.values(), si.parts.values(), strict=True)
    ]
    lazy = [p.part == "shaft" or (not deferred and n < 2) for p, _, deferred, n in pairs]
    assert any(lazy) and not all(lazy)
    assert any(k and p.part != "shaft" for k, (p, *_) in zip(lazy, pairs, strict=True))
    assert [("mask" not in p.__dict__) for p, *_ in pairs] == lazy  # not unpacked yet
    pairs = [(p, q, deferred) for p, q, deferred, _ in pairs]
    shafts = [(p, q) for (p, q, _), k in zip(pairs, lazy, strict=True) if k]
    plain = pickle.loads(pickle.dumps(shafts[0][0]))
    assert type(plain) is PartObservation and np.array_equal(plain.mask, shafts[0][1].mask)
    moved = dataclasses.replace(shafts[1][0], offset=(0, 0))
    assert np.array_equal(moved.mask, shafts[1][1].mask) and moved.offset == (0, 0)
    for p, q, _ in reversed(pairs):
        assert p.mask.dtype == np.bool_ and p.mask.flags.c_contiguous
        assert p.mask.shape == q.mask.shape and np.array_equal(p.mask, q.mask)
        assert (p.part, p.box, p.area_px, p.offset) == (q.part, q.box, q.area_px, q.offset)
        assert p.mask is p.mask  # unpacked once


def test_a_fitted_parts_mask_is_sent_as_the_bits_the_kernel_set(crossing: Path) -> None:
    """A worker sends a fitted part's mask as the bits ``fit_parts`` set from its runs
    (the part's ``_bits``: no ``packbits`` of the mask again), each part's from a byte
    boundary; a part whose mask is not the one those bits were set for (replaced) is
    packed from its mask. Either way the caller unpacks the worker's masks."""
    seq = open_sequence(crossing)
    sent = []
    for _, _, labels in seq:
        r = parallel.observe_labels(labels, seq.config, False)
        if r.instances:  # (frames with instruments in view)
            sent.append(r)
        if len(sent) == 8:
            break
    parts = [p for r in sent for i in r.instances for p in i.parts.values()]
    assert len(parts) >= 8
    for p in parts:
        mask, bits = p.__dict__["_bits"]
        assert mask is p.mask and np.array_equal(bits, np.packbits(p.mask.reshape(-1)))
    # the bits sent are those arrays: marked ones come out of the batch's buffer
    marked = parts[0]
    mask, bits = marked.__dict__["_bits"]
    mark = np.full_like(bits, 0xA5)
    marked.__dict__["_bits"] = (mask, mark)
    buffer = parallel.pack_frames(sent)[6]
    size = [-(-p.mask.size // 8) for p in parts]
    assert buffer.dtype == np.uint8 and len(buffer) == sum(size)
    assert np.array_equal(buffer[: size[0]], mark)
    # a replaced mask: packed from it (the stale bits are not sent)
    other = parts[1]
    flipped = ~other.mask
    other.__dict__["mask"] = flipped
    marked.__dict__["_bits"] = (mask, bits)
    got = parallel.unpack_frames(parallel.pack_frames(sent))
    back = [p for r in got for i in r.instances for p in i.parts.values()]
    assert np.array_equal(back[1].mask, flipped)
    for p, q in zip(back, parts, strict=True):
        assert np.array_equal(p.mask, q.mask) and p.mask.shape == q.mask.shape


def test_unpacked_parts_carry_their_rows_cells_and_checked_values() -> None:
    """Each part a batch unpacks to carries its row's box cells (``_row``: the batch's
    cells, made at once, and its row there, what ``mistool.rows`` writes) equal to those
    read from its fields, and its box and part are the model's types with the values sent."""
    from mistool.rows import BOX_COLUMNS, _row_cells

    rng = np.random.default_rng(7)
    sent = []
    for n, deferred in ((2, False), (3, True), (1, False)):
        insts = []
        for _ in range(n):
            parts = {}
            for name in ("shaft", "wrist", "clasper"):
                h, w = (int(v) for v in rng.integers(1, 9, 2))
                length, width = sorted(rng.uniform(1.0, 50.0, 2), reverse=True)
                box = RotatedBox(*rng.uniform(0, 500, 2), length, width, rng.uniform(0, 180))
                corners = box.corners() + rng.normal(size=(4, 2))
                area = int(rng.integers(1, 10**6))
                parts[name] = PartObservation(
                    name, box, corners, area, rng.random((h, w)) < 0.5, (1, 2)
                )
            insts.append(InstanceObservation(None, parts, (1.0, 2.0), 7, (3, 4, 5, 6), (40, 50)))
        empty = np.zeros(0, np.int64)
        sent.append(parallel.FrameResult(insts, None, empty, (40, 50), deferred=deferred))
    got = parallel.unpack_frames(parallel.pack_frames(sent))
    for g, s in zip(got, sent, strict=True):
        for gi, si in zip(g.instances, s.instances, strict=True):
            for p, q in zip(gi.parts.values(), si.parts.values(), strict=True):
                assert isinstance(p, PartObservation) and type(p.box) is RotatedBox
                assert (p.part, p.box, p.area_px, p.offset) == (q.part, q.box, q.area_px, q.offset)
                assert np.array_equal(p.corners, q.corners) and np.array_equal(p.mask, q.mask)
                cells, row = p._row  # type: ignore[attr-defined]
                assert cells.dtype == np.float64 and cells.shape[1] == len(BOX_COLUMNS)
                assert cells[row].tolist() == _row_cells(q) == _row_cells(p)


@pytest.mark.parametrize("seed", range(12))
def test_a_batchs_masks_unpack_to_the_workers_whatever_their_sizes_and_frames(seed) -> None:
    """Random batches (frames of 0-3 instruments, deferred or not, parts of 1-200 bits,
    so masks start at every bit of a byte, and several share one): every unpacked part's
    mask, read in a random order, is the worker's (values, shape, bool, C-contiguous),
    whether it was unpacked with the batch's or at its first use."""
    rng = np.random.default_rng(seed)
    sent = []
    for _ in range(int(rng.integers(1, 9))):
        insts = []
        for _ in range(int(rng.integers(0, 4))):
            names = [p for p in ("shaft", "wrist", "clasper") if rng.random() < 0.6] or ["shaft"]
            parts = {}
            for name in names:
                h, w = (int(v) for v in rng.integers(1, 15, 2))
                box = RotatedBox(5.0, 6.0, 9.0, 2.0, 30.0)
                mask = rng.random((h, w)) < 0.5
                parts[name] = PartObservation(name, box, box.corners(), 7, mask, (3, 4))
            insts.append(InstanceObservation(None, parts, (1.0, 2.0), 7, (3, 4, 5, 6), (40, 50)))
        empty = np.zeros(0, np.int64)
        sent.append(
            parallel.FrameResult(insts, None, empty, (40, 50), deferred=bool(rng.random() < 0.3))
        )
    got = parallel.unpack_frames(parallel.pack_frames(sent))
    pairs = [
        (p, q)
        for g, s in zip(got, sent, strict=True)
        for gi, si in zip(g.instances, s.instances, strict=True)
        for p, q in zip(gi.parts.values(), si.parts.values(), strict=True)
    ]
    for k in rng.permutation(len(pairs)):
        p, q = pairs[k]
        assert p.mask.dtype == np.bool_ and p.mask.flags.c_contiguous
        assert p.mask.shape == q.mask.shape and np.array_equal(p.mask, q.mask)
