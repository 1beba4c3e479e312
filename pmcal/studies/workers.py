"""Worker processes that never delay Ctrl-C: :func:`worker_pool`.

A plain :class:`concurrent.futures.ProcessPoolExecutor` waits for its running tasks on the way out of the
``with`` block, and each worker prints its own ``KeyboardInterrupt`` traceback: Ctrl-C in the demo took
19-29 s and 30-70 lines. Here the workers ignore SIGINT (the parent decides) and, when the block is left
by an exception, the parent kills them at once and cancels what is queued.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
from concurrent.futures import ProcessPoolExecutor
from typing import Iterator


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def worker_pool(max_workers: int) -> Iterator[ProcessPoolExecutor]:
    """A process pool whose workers ignore Ctrl-C and are killed if the block raises (e.g. on Ctrl-C).

    Workers come from a fork server (a fresh interpreter started once), not from forking the caller: a
    caller that has rendered with MuJoCo holds OpenGL (Mesa) threads and their locks, and a forked child
    can deadlock on a lock held by a thread that does not exist in it (seen: the test suite hung in the
    demo after an in-process ``twin render``)."""
    ctx = multiprocessing.get_context("forkserver")
    pool = ProcessPoolExecutor(max_workers=max_workers, initializer=_ignore_sigint, mp_context=ctx)
    try:
        yield pool
    except BaseException:
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            with contextlib.suppress(Exception):
                proc.kill()
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)
