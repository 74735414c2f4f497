"""Independent jobs that several threads may share (docs/rough-interfaces.md, "Whole process").

:class:`SharedJobs` runs a list of independent jobs in the thread that asks for them, in the listed
order, and lets other threads take the ones not yet started: worker threads of its own (``threads``
> 1) and any thread that would otherwise only wait for the result (:meth:`SharedJobs.help`; the
stack solver's main thread, once it has solved the body's first orders, takes parts of the rough top
that the background thread has not reached).  Each job is a pure function of its arguments, so
which thread runs it changes nothing: the results are the serial ones, bit for bit, and in the
listed order.

On the 2-core machine two threads of the rough top beside the main thread's body solve were no
faster than one (measured, whole process at n = 200: the pool's threads contend with the body's for
the cores and the GIL); the main thread's help after its body is where a second core is free.
"""

import threading
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor

#: The solver's thread pools by (name, workers), created on first use under the lock.  Each user has pools of
#: its own name (the slab solves' "flakedb-slab", the rough top's background "flakedb-solve", the helpers of
#: :meth:`SharedJobs.help` "flakedb-jobs"): one may wait for another's jobs, so they never share threads.
_POOLS: dict = {}
_POOLS_LOCK = threading.Lock()


def thread_pool(workers, name) -> ThreadPoolExecutor:
    """The process's pool of ``workers`` threads named ``name`` (one per pair, kept for the process)."""
    key = (str(name), int(workers))
    with _POOLS_LOCK:
        pool = _POOLS.get(key)
        if pool is None:
            pool = _POOLS[key] = ThreadPoolExecutor(key[1], thread_name_prefix=key[0])
    return pool


class SharedJobs:
    """Independent jobs run by whichever threads ask: :meth:`run` in the owner's thread, :meth:`help`
    in any other.  ``threads``: the threads :meth:`run` uses itself (the caller and ``threads`` − 1
    workers); 1 runs every job in the caller unless another thread helps.

    >>> jobs = SharedJobs(threads=2)
    >>> jobs.run([(pow, (2, 10), {}), (sorted, ([3, 1, 2],), {"reverse": True})])
    [1024, [3, 2, 1]]
    >>> jobs.help()  # nothing left to take
    """

    def __init__(self, threads=1):
        self.threads = max(1, int(threads))
        self._lock = threading.Lock()
        self._pending = deque()  # (future, (fn, args, kw)) not yet started, in the listed order

    def run(self, jobs):
        """``[fn(*args, **kw) for fn, args, kw in jobs]``: the caller takes the jobs in order, the workers and
        the threads that help take the ones not yet started; returns when every job is done (the first
        job's exception, if any, is raised)."""
        futures = [Future() for _ in jobs]
        with self._lock:
            self._pending.extend(zip(futures, jobs))
        self._workers(self.threads, len(jobs))
        self.help()
        return [f.result() for f in futures]

    def help(self, threads=1):
        """Run jobs not yet started until none is left, with ``threads`` − 1 workers beside the caller;
        returns at once when there is none (jobs already taken are left to their threads)."""
        self._workers(threads, len(self._pending))
        while True:
            with self._lock:
                if not self._pending:
                    return
                future, (fn, args, kw) = self._pending.popleft()
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn(*args, **kw))
            except BaseException as e:  # the owner sees it too (a KeyboardInterrupt is raised here as well)
                future.set_exception(e)
                if not isinstance(e, Exception):
                    raise

    def _workers(self, threads, n_jobs):
        workers = min(int(threads) - 1, n_jobs - 1)
        if workers > 0:
            pool = thread_pool(workers, "flakedb-jobs")
            for _ in range(workers):
                pool.submit(self.help)
