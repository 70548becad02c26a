"""The worker processes' fork server: its context, and its start ahead of the pool.

mistool's worker processes fork from a ``forkserver`` that has imported the per-frame
code and loaded its compiled kernels once (in a new process: imports ~0.35 s, then numba's
start and the kernels' loading, ~0.57 s before :mod:`mistool.numbaload` and far less with
it: numba's start without its import of scipy.linalg, the kernels without their bitcode).
:func:`start` launches that server without waiting for it, so that a command can have
it loading while it imports and lists its own inputs; the pool made later
(:class:`mistool.parallel.LocalPool`) then forks its workers from it. This module
imports only :mod:`multiprocessing`: calling :func:`start` first thing costs ~5 ms.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable
from multiprocessing import context as mp_context
from multiprocessing import spawn as mp_spawn
from typing import Any

#: What the fork server imports before forking any worker (worker_signals: Ctrl+C
#: ignored from each worker's first instant, see its docstring).
PRELOAD = ["mistool.worker_signals", "mistool.parallel", "mistool.kernels._worker"]


def _without_main(prepare: Callable[[str], dict[str, Any]]) -> Callable[[str], dict[str, Any]]:
    def data(name: str) -> dict[str, Any]:
        d = prepare(name)
        d.pop("init_main_from_path", None)
        d.pop("init_main_from_name", None)
        return d

    return data


_LAUNCH_LOCK = threading.Lock()
try:
    from multiprocessing import popen_forkserver as _mp_popen_forkserver

    _Popen: Any = _mp_popen_forkserver.Popen
    _ForkServerProcess: Any = mp_context.ForkServerProcess
except (ImportError, AttributeError):  # Windows: no fork server (spawn is used)
    _Popen = _ForkServerProcess = None


if _Popen is not None:

    class _NoMainPopen(_Popen):
        """A forkserver process start that leaves the caller's ``__main__`` out (see
        :func:`worker_context`)."""

        def _launch(self, process_obj: Any) -> None:
            with _LAUNCH_LOCK:  # the module attribute is swapped while this process starts
                original = mp_spawn.get_preparation_data
                patched: Any = _without_main(original)
                mp_spawn.get_preparation_data = patched
                try:
                    super()._launch(process_obj)
                finally:
                    mp_spawn.get_preparation_data = original

    class _NoMainProcess(_ForkServerProcess):
        @staticmethod
        def _Popen(process_obj: Any) -> Any:  # noqa: N802 - multiprocessing's name
            return _NoMainPopen(process_obj)


def worker_context() -> Any:
    """A ``forkserver`` multiprocessing context whose processes do not re-run the
    caller's ``__main__``.

    multiprocessing's spawn and forkserver processes import the parent's main script
    again, so a user's script calling ``mistool.track`` at top level (without an
    ``if __name__ == "__main__":`` guard) would run again in every worker. Our workers
    need only :func:`mistool.parallel.observe_batch`, so the main module is left out of
    the data each worker is prepared with. The fork server imports the per-frame code once; each
    worker forks from it (no thread of the caller is forked)."""
    if _Popen is None:  # pragma: no cover - Windows
        return mp_context.SpawnContext()
    ctx: Any = mp_context.ForkServerContext()
    ctx.Process = _NoMainProcess
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


def forget_inherited_fork_server() -> None:
    """Make a process started by ``fork`` start its own fork server for its workers.

    multiprocessing's fork server is per-process state, and a forked child inherits its
    parent's: it would ask the parent's server for its worker processes, which then are
    not its children (waiting for them fails with "No child processes"). Call it first
    thing in a forked child that may start a :class:`~mistool.parallel.LocalPool`
    (:mod:`mistool.background`). The child's copy of the parent server's keep-alive pipe is
    closed: that server is the parent's to stop."""
    try:
        from multiprocessing import forkserver
    except ImportError:  # pragma: no cover - Windows: no fork server
        return
    server: Any = getattr(forkserver, "_forkserver", None)
    if server is None or getattr(server, "_forkserver_pid", None) is None:
        return
    with contextlib.suppress(OSError, TypeError):
        os.close(server._forkserver_alive_fd)
    server._forkserver_address = server._forkserver_alive_fd = server._forkserver_pid = None
    server._lock = threading.Lock()


def default_workers() -> int:
    """The CPU cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def start() -> None:
    """Start the fork server now, with :data:`PRELOAD`, without waiting for its imports
    (its listening socket exists at once: the pool's first worker start waits for it).
    Nothing happens where there is no fork server (Windows) or one is running."""
    if _Popen is None:  # pragma: no cover - Windows
        return
    worker_context()  # (sets the preload list)
    from multiprocessing import forkserver, resource_tracker

    # The server starts with Ctrl+C blocked, as the pool starts its processes
    # (LocalPool._start_workers): a Ctrl+C while it imports would print its traceback.
    # multiprocessing's resource tracker, started with the server when it is not running
    # yet, unblocks SIGINT after its own start: it is started first. A Ctrl+C arriving
    # meanwhile is delivered as the mask is restored.
    resource_tracker.ensure_running()
    blocking = hasattr(signal, "pthread_sigmask")
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT}) if blocking else None
    try:
        forkserver.ensure_running()
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
