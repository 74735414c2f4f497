"""Local worker processes of a build that end with their parent (issue 13).

:func:`process_pool` is a ``ProcessPoolExecutor`` whose workers exit when the process that started
them dies (killed, crashed): on Linux the kernel sends them SIGKILL (``PR_SET_PDEATHSIG``); everywhere
a watchdog thread checks the parent once a second.  Without this, killing ``flakedb build
--processes`` left its workers computing for nobody.
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time

#: How many times a build restarts its process pool after a worker died before it stops.
MAX_POOL_RESTARTS = 2


def _watch_parent(ppid: int):
    while True:
        time.sleep(1.0)
        if os.getppid() != ppid:
            os._exit(1)


def die_with_parent(ppid: int):
    """Worker initializer: end this process when the process ``ppid`` ends."""
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != ppid:  # the parent died before the initializer ran
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(ppid,), daemon=True, name="flakedb-parent-watch").start()


def process_pool(workers: int | None = None) -> concurrent.futures.ProcessPoolExecutor:
    """A spawn-context process pool whose workers end with this process.

    >>> with process_pool(1) as pool:
    ...     pool.submit(os.getppid).result() == os.getpid()                 # the worker is this process's child
    True
    """
    # concurrent.futures loads its process pool (multiprocessing's queues: 3 ms of every compose) on this first use
    return concurrent.futures.ProcessPoolExecutor(max_workers=workers or os.cpu_count(),
                                                  mp_context=multiprocessing.get_context("spawn"),
                                                  initializer=die_with_parent, initargs=(os.getpid(),))
