"""Ctrl+C ignored from the very start of every worker process (import side effect).

Imported only by the fork server of mistool's worker processes
(:func:`mistool.parallel.worker_context` preloads it); never import it elsewhere: it makes
the importing process ignore SIGINT.

multiprocessing's fork server gives each child the signal handlers the server had before
it started serving. A worker ignores SIGINT in its initializer
(``mistool.parallel._init_worker``), but only once that runs: a Ctrl+C in the first
milliseconds of a worker's life raised ``KeyboardInterrupt`` there and printed its
traceback under the caller's one-line message. With this module preloaded the server
(and so every worker) ignores SIGINT from the start; the caller still gets the Ctrl+C and
stops the workers.
"""

from __future__ import annotations

import signal

signal.signal(signal.SIGINT, signal.SIG_IGN)
