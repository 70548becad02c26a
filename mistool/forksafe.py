"""Whether a process may ``fork`` with the threads it has (standard library only: the
command line registers its stderr filter thread here before anything heavy is imported,
:func:`mistool.cli.quiet_native_stderr`)."""

from __future__ import annotations

import threading
import weakref

#: Threads a fork may leave behind: they hold no lock the forked child could need (they
#: only copy bytes between file descriptors, e.g. the command line's stderr filter,
#: :func:`mistool.cli.quiet_native_stderr`, which adds itself here).
FORK_SAFE_THREADS: weakref.WeakSet[threading.Thread] = weakref.WeakSet()


def fork_is_safe() -> bool:
    """Whether this process may fork a child (:mod:`mistool.background`'s tracking
    process): it runs in the main thread, and every other thread is in
    :data:`FORK_SAFE_THREADS`."""
    me = threading.current_thread()
    if me is not threading.main_thread():
        return False
    return all(t is me or t in FORK_SAFE_THREADS for t in threading.enumerate())
