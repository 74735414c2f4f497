"""Process-wide settings for flakedb's command line and for batch scripts: an edge module, called by
``flakedb.cli.main`` and by scripts that want the same behaviour, never by the numerics.

:func:`tune_allocator` keeps freed memory in the process for reuse.  glibc's malloc hands every block
above its mmap threshold (128 KiB at start, raised only as blocks are freed) to the kernel and takes
fresh pages for the next one; each fresh page is a page fault, and on the 2-core VM these cost
0.4–3 ms per MB (measured: an 85 MB array filled in 0.04–0.24 s the first time, 0.02 s the second).
A solve makes many short-lived arrays of 0.1–30 MB (the rough interface's temporaries, the order
blocks), so with the threshold at 32 MiB and trimming at 1 GiB the rough coat α 0.1 interface at
n = 200 took 0.28–0.31 s instead of 0.39–0.42 s in a fresh process (the same call a second time:
0.24–0.27 s either way; docs/rough-interfaces.md, "Whole process").  The cost: memory freed after a
peak stays mapped to the process until it exits (it is reused by later arrays).

:func:`request_fast_exit` / :func:`fast_exit`: a command whose outputs are all written and closed (compose)
may end the process without the interpreter's teardown, which freed every object one by one and took
45–50 ms of a 0.7 s whole-process compose (measured: external wall − the end of the work, 0.07 s with the
teardown, 0.027 s with ``os._exit`` after flushing; atexit handlers themselves took < 1 ms).

:func:`blas_one_thread`: flakedb's parallelism is its own (thread pools over orders and channels, worker
processes in a build); the BLAS library's threads only compete with it.  OpenBLAS at 2 threads leaves its
worker spinning for ~50 ms after every threaded call (measured: 48–52 ms of process CPU during a 50 ms
sleep after one 300 × 300 product), and on 2 cores that worker takes a core from the solve or the texture
thread: the 3-species store compose used 0.76 s of CPU against 0.65 s with one BLAS thread (wall 0.57 s
against 0.54 s).  The solver already runs its batched matrices on one BLAS thread
(:func:`flakedb.rt.stack.solve_stack`); this makes the rest of the process do the same.
"""

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import threading

#: glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap and are reused (glibc's largest allowed value, 32 MiB).
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
#: The heap is given back to the kernel only above this much free memory at its top.
TRIM_THRESHOLD_BYTES = 1024 * 1024 * 1024


def tune_allocator():
    """Set glibc's mmap and trim thresholds (module docstring); True when applied.  A no-op (False)
    without glibc's ``mallopt`` (macOS, musl) or with ``FLAKEDB_MALLOC_TUNING=0`` in the environment.

    The opt-out is honoured (without touching the allocator):

    >>> from unittest import mock
    >>> with mock.patch.dict(os.environ, {"FLAKEDB_MALLOC_TUNING": "0"}):
    ...     tune_allocator()
    False
    """
    if os.environ.get("FLAKEDB_MALLOC_TUNING", "1").strip() == "0":
        return False
    try:
        libc = _libc()
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))


#: The environment variables that choose a BLAS library's thread count; a user who sets any of them is obeyed.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def blas_one_thread(environ=None, modules=None) -> bool:
    """Set ``OPENBLAS_NUM_THREADS=1`` and ``MKL_NUM_THREADS=1`` for this process and its children (module
    docstring); True when set.  Left alone (False) when the user set any of :data:`BLAS_THREAD_VARIABLES`, or
    when numpy is already imported (its BLAS read the variables as it loaded, so setting them now would only
    reach child processes, inconsistently).  ``environ``, ``modules``: ``os.environ`` and ``sys.modules``.

    >>> blas_one_thread({"OMP_NUM_THREADS": "2"}, {})       # the user's choice stands
    False
    >>> env = {}
    >>> blas_one_thread(env, {}), env["OPENBLAS_NUM_THREADS"]
    (True, '1')
    >>> blas_one_thread({}, {"numpy": object()})            # too late for this process
    False
    """
    environ = os.environ if environ is None else environ
    modules = sys.modules if modules is None else modules
    if "numpy" in modules or any(environ.get(v, "").strip() for v in BLAS_THREAD_VARIABLES):
        return False
    environ["OPENBLAS_NUM_THREADS"] = "1"
    environ["MKL_NUM_THREADS"] = "1"
    return True


def _libc():
    """The C library: glibc's soname first (``ctypes.util.find_library`` runs ``ldconfig -p`` in a subprocess,
    3 ms of every command), then whatever find_library names."""
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived (issue 25): raised in the main thread like Ctrl-C's KeyboardInterrupt,
    so every ``finally`` / ``except BaseException`` that cleans up after SIGINT (temporary files and
    directories, half-built outputs) does the same for them.  ``signum`` is the signal's number."""

    def __init__(self, signum):
        super().__init__(f"terminated by {signal.Signals(signum).name}")
        self.signum = signum


def _raise_terminated(signum, frame):
    # one clean-up at a time: a second SIGTERM/SIGHUP during the clean-up is ignored (SIGKILL still works,
    # and the next run removes what a SIGKILL left: flakedb.outputs.sweep_stale)
    for s in TERMINATING_SIGNALS:
        with contextlib.suppress(ValueError, OSError):
            signal.signal(s, signal.SIG_IGN)
    raise Terminated(signum)


#: The signals that end a run the way SIGINT does (those that exist on this platform).
TERMINATING_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


def install_signal_handlers() -> bool:
    """Make SIGTERM and SIGHUP raise :class:`Terminated` in the main thread (True when installed; False
    off the main thread, where Python cannot install handlers).  A signal the parent set to be ignored
    (``nohup`` ignores SIGHUP) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        return False
    for s in TERMINATING_SIGNALS:
        if signal.getsignal(s) is signal.SIG_IGN:
            continue
        signal.signal(s, _raise_terminated)
    return True


#: Set by :func:`request_fast_exit`.
_FAST_EXIT = []


def request_fast_exit():
    """Say that the running command's work is done and every file it wrote is closed (called by ``flakedb
    compose`` at its end): :func:`fast_exit` may then end the process without the interpreter's teardown."""
    _FAST_EXIT.append(True)


def fast_exit(code) -> None:
    """End the process now with status 0 if :func:`request_fast_exit` was called and ``code`` is success (0
    or None), after flushing stdout and stderr and running the ``atexit`` handlers (``os._exit``: no freeing
    of every object, no module teardown; module docstring); otherwise return (the caller exits normally)."""
    if not _FAST_EXIT or code not in (0, None):
        return
    import atexit  # lazy: only the fast exit needs it

    run = getattr(atexit, "_run_exitfuncs", None)  # CPython's own hook (what a normal exit calls)
    if run is not None:
        run()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(0)
