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
(:func:`flakedb.rt.adding.stack.solve_stack`); this makes the rest of the process do the same.
:func:`available_threads`: how many threads flakedb's own pools use (the CPUs the process may run on, capped by
``FLAKEDB_THREADS`` or ``OMP_NUM_THREADS``).
"""

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import threading

from flakedb.interrupts import hold, raise_or_defer

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


#: The environment variables that choose a BLAS library's thread count.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")
#: Those that name the BLAS itself: a user who sets any of them is obeyed.  ``OMP_NUM_THREADS`` alone caps
#: flakedb's own threads (:func:`available_threads`), and the BLAS still gets one thread per call: its threads and
#: flakedb's would multiply (OpenBLAS reads ``OMP_NUM_THREADS`` when its own variable is unset).
BLAS_OWN_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def blas_one_thread(environ=None, modules=None) -> bool:
    """Set ``OPENBLAS_NUM_THREADS=1`` and ``MKL_NUM_THREADS=1`` for this process and its children (module
    docstring); True when set.  Left alone (False) when the user set any of :data:`BLAS_OWN_VARIABLES`, or
    when numpy is already imported (its BLAS read the variables as it loaded, so setting them now would only
    reach child processes, inconsistently).  ``environ``, ``modules``: ``os.environ`` and ``sys.modules``.

    >>> blas_one_thread({"OPENBLAS_NUM_THREADS": "2"}, {})  # the user's choice stands
    False
    >>> env = {"OMP_NUM_THREADS": "2"}                        # flakedb's cap (available_threads), not the BLAS's
    >>> blas_one_thread(env, {}), env["OPENBLAS_NUM_THREADS"]
    (True, '1')
    >>> blas_one_thread({}, {"numpy": object()})            # too late for this process
    False
    """
    environ = os.environ if environ is None else environ
    modules = sys.modules if modules is None else modules
    if "numpy" in modules or any(environ.get(v, "").strip() for v in BLAS_OWN_VARIABLES):
        return False
    environ["OPENBLAS_NUM_THREADS"] = "1"
    environ["MKL_NUM_THREADS"] = "1"
    return True


#: Environment variables that cap the threads flakedb runs itself (its solver's and writers' pools); the first set
#: to a positive integer wins: flakedb's own, then OpenMP's (the usual "threads this job may use" of a CI runner or
#: a batch system).
#: ``OPENBLAS_NUM_THREADS`` / ``MKL_NUM_THREADS`` are not among them: they size the BLAS's own pool, which the
#: solver holds at one thread per call (``flakedb.rt.adding.stack.solve_stack``), so flakedb's threads times
#: the BLAS's stay within the cap; the command line sets them to 1 itself (:func:`blas_one_thread`).
THREAD_CAP_VARIABLES = ("FLAKEDB_THREADS", "OMP_NUM_THREADS")


def available_threads(environ=None, cpus=None) -> int:
    """The threads flakedb's own pools may use: the CPUs this process may run on (``os.sched_getaffinity``, a
    ``taskset`` or a container's cpuset; ``os.cpu_count()`` where the platform has no affinity), capped by the
    first of :data:`THREAD_CAP_VARIABLES` that is set to a positive integer (other values are ignored).  Every
    pool of the solve, the writers and compose asks this one function.  ``environ``, ``cpus``: ``os.environ`` and
    the CPU count, for tests.

    >>> available_threads({}, cpus=2), available_threads({"OMP_NUM_THREADS": "1"}, cpus=2)
    (2, 1)
    >>> available_threads({"FLAKEDB_THREADS": "8", "OMP_NUM_THREADS": "1"}, cpus=2)   # flakedb's first; never above the CPUs
    2
    >>> available_threads({"OMP_NUM_THREADS": "0"}, cpus=2), available_threads({"OMP_NUM_THREADS": "x"}, cpus=4)
    (2, 4)
    """
    environ = os.environ if environ is None else environ
    if cpus is None:
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    cap = next((c for c in (_positive_count(environ.get(v)) for v in THREAD_CAP_VARIABLES) if c), None)
    return max(1, min(int(cpus), cap) if cap else int(cpus))


def _positive_count(raw):
    """``raw`` (an environment value) as a positive whole number, else None."""
    value = str(raw if raw is not None else "").strip()
    return int(value) if value.isdigit() and int(value) > 0 else None


def _libc():
    """The C library: glibc's soname first (``ctypes.util.find_library`` runs ``ldconfig -p`` in a subprocess,
    3 ms of every command), then whatever find_library names."""
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")


class Terminated(KeyboardInterrupt):
    """SIGTERM, SIGHUP or SIGINT arrived (issues 25, 38): raised in the main thread like Ctrl-C's
    KeyboardInterrupt (a subclass of it), so every ``finally`` / ``except BaseException`` that cleans up
    (temporary files and directories, half-built outputs) runs for all three, and the command line ends
    with exit status 128 + ``signum`` (:func:`signal_exit_status`), which a script tells from exit status 1
    ("target not reached") and 2 (bad input)."""

    def __init__(self, signum):
        super().__init__(f"terminated by {signal.Signals(signum).name}")
        self.signum = signum


#: The signal numbers received by :func:`_raise_terminated` in this process (first first).
_RECEIVED = []


def _raise_terminated(signum, frame):
    # one clean-up at a time: a second signal during the clean-up is ignored (SIGKILL still works, and the
    # next run removes what a SIGKILL left: flakedb.outputs.sweep_stale)
    for s in TERMINATING_SIGNALS:
        with contextlib.suppress(ValueError, OSError):
            signal.signal(s, signal.SIG_IGN)
    _RECEIVED.append(signum)
    raise_or_defer(Terminated(signum))   # held back while the main thread is inside a compiled kernel


#: The signals that end a run with clean-up (those that exist on this platform).
TERMINATING_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP", "SIGINT") if hasattr(signal, n))


def _terminated_where_it_cannot_be_raised(unraisable, previous=sys.unraisablehook):
    """``sys.unraisablehook``: a :class:`Terminated` that arrived inside a finaliser or a weakref callback (Python
    prints "Exception ignored in ..." with a traceback and goes on) is held for the next kernel call's end
    (:func:`flakedb.interrupts.hold`) instead, so the run still stops, and nothing is printed; the command's exit
    status is 128 + the signal either way (:func:`received_signal`).  Anything else: Python's own report."""
    if isinstance(unraisable.exc_value, Terminated):
        hold(unraisable.exc_value)
        return
    previous(unraisable)


def install_signal_handlers() -> bool:
    """Make SIGTERM, SIGHUP and SIGINT raise :class:`Terminated` in the main thread (True when installed;
    False off the main thread, where Python cannot install handlers).  A signal the parent set to be ignored
    (``nohup`` ignores SIGHUP; a background job of a non-interactive shell, SIGINT) stays ignored.  A
    :class:`Terminated` raised where Python cannot raise it (a finaliser) is held, not printed
    (:func:`_terminated_where_it_cannot_be_raised`)."""
    if threading.current_thread() is not threading.main_thread():
        return False
    if sys.unraisablehook is not _terminated_where_it_cannot_be_raised:
        sys.unraisablehook = _terminated_where_it_cannot_be_raised
    for s in TERMINATING_SIGNALS:
        if signal.getsignal(s) is signal.SIG_IGN:
            continue
        signal.signal(s, _raise_terminated)
    return True


def signal_exit_status(exc) -> int | None:
    """128 + the signal number when ``exc`` is, or was caused by, a signal's :class:`Terminated` (130 for a
    plain KeyboardInterrupt), else None.

    A signal that arrives while a numba dispatcher runs a compiled kernel (the Mie series) raises
    :class:`Terminated` inside the dispatcher's C code, which then returns with the exception set: Python
    reports ``SystemError: CPUDispatcher(...) returned a result with an exception set`` with the
    Terminated as its cause (2 of 6 SIGTERMs to a running ``match`` ended as "internal error" that way).
    The chain is followed, so that run ends as the signal's, not as an internal error:

    >>> try:
    ...     try:
    ...         raise Terminated(15)
    ...     except Terminated as t:
    ...         raise SystemError("CPUDispatcher(_scatter_kernel) returned a result with an exception set") from t
    ... except SystemError as e:
    ...     signal_exit_status(e)
    143
    >>> signal_exit_status(ValueError("x")) is None
    True
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, Terminated):
            return 128 + int(exc.signum)
        if isinstance(exc, KeyboardInterrupt):
            return 128 + int(getattr(signal, "SIGINT", 2))
        exc = exc.__cause__ or exc.__context__
    return None


def signals_received() -> int:
    """How many terminating signals the handler has received in this process (a command compares the count
    before and after its work to tell whether a signal ended it)."""
    return len(_RECEIVED)


def received_signal_since(count: int) -> int | None:
    """The first signal received after the first ``count`` (:func:`signals_received`), or None."""
    return _RECEIVED[count] if len(_RECEIVED) > count else None


def received_signal() -> int | None:
    """The first signal :func:`install_signal_handlers`' handler received in this process, or None."""
    return _RECEIVED[0] if _RECEIVED else None


def exit_after_signal(code) -> None:
    """End the process now with ``code`` after a signal's clean-up has run (the command's ``finally`` blocks:
    outputs and temporaries are gone): stdout and stderr flushed, then ``os._exit``.  The interpreter's
    teardown is skipped on purpose: the solver's pool threads may still be inside a compiled kernel, and
    finalising the interpreter under them crashed (1 of 6 SIGTERMs to a running ``match``: segmentation
    fault, exit 139)."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(int(code))


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


# --- environment variables ---------------------------------------------------------------------------

class EnvironmentSettingError(ValueError):
    """An environment variable flakedb reads has a value it cannot use; the message names the variable, the
    value (cut), what is allowed and an example."""


#: Byte units of :func:`parse_bytes`: SI prefixes with B are powers of 1000, IEC (KiB...) and a bare letter
#: (K, M, G, T, as ``docker --memory`` and Java's ``-Xmx``) powers of 1024.
_BYTE_UNITS = {"": 1, "b": 1, "kb": 1e3, "mb": 1e6, "gb": 1e9, "tb": 1e12,
               "kib": 2.0**10, "mib": 2.0**20, "gib": 2.0**30, "tib": 2.0**40,
               "k": 2.0**10, "m": 2.0**20, "g": 2.0**30, "t": 2.0**40}
#: The smallest memory budget accepted [bytes]: one channel of a small solve needs a few MiB.
MIN_MEMORY_BUDGET_BYTES = 16 * 2**20


def _shown(value) -> str:
    v = str(value)
    return repr(v) if len(v) <= 40 else repr(v[:37]) + f"... ({len(v):,} characters)"


def parse_bytes(text, variable) -> float:
    """Bytes from ``12GB`` (10^9), ``12 GiB`` / ``12G`` (2^30), ``512MB``, ``1e9`` (units case-insensitive);
    :class:`EnvironmentSettingError` naming ``variable`` for anything else, for a value that is not finite or
    not > 0.

    >>> parse_bytes("12GB", "FLAKEDB_MEMORY_BUDGET"), parse_bytes("1.5 GiB", "X"), parse_bytes("4e9", "X")
    (12000000000.0, 1610612736.0, 4000000000.0)
    >>> parse_bytes("lots", "FLAKEDB_MEMORY_BUDGET")
    Traceback (most recent call last):
    ...
    flakedb.process.EnvironmentSettingError: FLAKEDB_MEMORY_BUDGET='lots': not a size; write bytes with an optional unit (B, kB, MB, GB, TB powers of 1000; KiB, MiB, GiB, TiB or K, M, G, T powers of 1024), e.g. FLAKEDB_MEMORY_BUDGET=12GB
    """
    s = str(text).strip()
    i = len(s)
    while i and s[i - 1].isalpha():
        i -= 1
    num, unit = s[:i].strip(), s[i:].lower()
    try:
        value = float(num) * _BYTE_UNITS[unit]
    except (ValueError, KeyError):
        raise EnvironmentSettingError(
            f"{variable}={_shown(text)}: not a size; write bytes with an optional unit (B, kB, MB, GB, TB powers "
            f"of 1000; KiB, MiB, GiB, TiB or K, M, G, T powers of 1024), e.g. {variable}=12GB") from None
    if not (value > 0 and value < float("inf")):
        raise EnvironmentSettingError(f"{variable}={_shown(text)}: a size must be a finite number of bytes > 0, "
                                      f"e.g. {variable}=12GB")
    return value


def memory_budget_bytes(environ=None) -> float | None:
    """The solver's memory budget from ``$FLAKEDB_MEMORY_BUDGET`` (:func:`parse_bytes`; at least
    :data:`MIN_MEMORY_BUDGET_BYTES`), or None when it is unset or empty (the solver's default)."""
    environ = os.environ if environ is None else environ
    raw = environ.get("FLAKEDB_MEMORY_BUDGET", "")
    if not raw.strip():
        return None
    value = parse_bytes(raw, "FLAKEDB_MEMORY_BUDGET")
    if value < MIN_MEMORY_BUDGET_BYTES:
        raise EnvironmentSettingError(f"FLAKEDB_MEMORY_BUDGET={_shown(raw)}: {value:,.0f} bytes is below the smallest "
                                      f"budget, 16 MiB (one channel of a small solve); e.g. FLAKEDB_MEMORY_BUDGET=4GiB")
    return value


#: The switches flakedb reads, and their allowed values.
_SWITCHES = ("FLAKEDB_H5_PROBE", "FLAKEDB_MALLOC_TUNING")
#: The variables that name a path (an empty value means the default; a value with a NUL byte cannot be a path).
_PATH_VARIABLES = ("FLAKEDB_CATALOG", "FLAKEDB_MATERIALS_DIR", "FLAKEDB_STORE")


def environment_problems(environ=None) -> list[str]:
    """Every flakedb environment variable whose value cannot be used, one message each (the variable named):
    checked by the command line before any work (issue 38: ``FLAKEDB_MEMORY_BUDGET=12GB`` failed only inside
    the solve, as "internal error", without naming the variable).

    >>> environment_problems({"FLAKEDB_MEMORY_BUDGET": "12GB", "FLAKEDB_H5_PROBE": "0"})
    []
    >>> environment_problems({"FLAKEDB_H5_PROBE": "no"})
    ["FLAKEDB_H5_PROBE='no': use 0 (off) or 1 (on)"]
    >>> environment_problems({"FLAKEDB_THREADS": "0"})[0].split(":")[0], environment_problems({"FLAKEDB_THREADS": "2"})
    ("FLAKEDB_THREADS='0'", [])
    >>> environment_problems({"FLAKEDB_CATALOG": "/nonexistent/particles.yaml"})[0].split(":")[0]
    "FLAKEDB_CATALOG='/nonexistent/particles.yaml'"
    """
    environ = os.environ if environ is None else environ
    out = []
    try:
        memory_budget_bytes(environ)
    except EnvironmentSettingError as exc:
        out.append(str(exc))
    for v in _SWITCHES:
        raw = environ.get(v)
        if raw is not None and raw.strip() not in ("", "0", "1"):
            out.append(f"{v}={_shown(raw)}: use 0 (off) or 1 (on)")
    raw = environ.get("FLAKEDB_THREADS")
    if raw is not None and raw.strip() and _positive_count(raw) is None:
        out.append(f"FLAKEDB_THREADS={_shown(raw)}: use a positive whole number of threads (e.g. FLAKEDB_THREADS=1), "
                   f"or unset it for every CPU this process may use")
    for v in _PATH_VARIABLES:
        raw = environ.get(v)
        if raw is not None and "\0" in raw:
            out.append(f"{v}={_shown(raw)}: a path cannot hold a NUL byte")
    cat = environ.get("FLAKEDB_CATALOG", "")
    if cat.strip() and "\0" not in cat and not os.path.exists(cat):
        out.append(f"FLAKEDB_CATALOG={_shown(cat)}: no such file (it names the particle catalogue YAML; unset it "
                   f"for the package's catalog/particles.yaml)")
    mat = environ.get("FLAKEDB_MATERIALS_DIR", "")
    if mat.strip() and "\0" not in mat and not os.path.lexists(os.path.join(mat, "materials.yaml")):
        out.append(f"FLAKEDB_MATERIALS_DIR={_shown(mat)}: not a folder holding materials.yaml (the optical-constant "
                   f"index); unset it for the package's catalog/materials")
    return out


# --- warnings ----------------------------------------------------------------------------------------

def format_warning(message, category, filename=None, lineno=None, line=None) -> str:
    """One line for a library's warning (numpy's RuntimeWarning "divide by zero encountered in log", say):
    ``flakedb: warning (RuntimeWarning): ...``, without the file and source line Python prints by default, the
    message cut to 300 characters.

    >>> format_warning(RuntimeWarning("invalid value encountered in divide"), RuntimeWarning, "/x/numpy/_methods.py", 12)
    'flakedb: warning (RuntimeWarning): invalid value encountered in divide\\n'
    """
    text = " ".join(str(message).split())
    text = text if len(text) <= 300 else text[:297] + "..."
    return f"flakedb: warning ({getattr(category, '__name__', 'Warning')}): {text}\n"


def install_warning_format() -> None:
    """Print every warning as :func:`format_warning`'s one line, each distinct line once per process, for the
    command line (issue 38: numpy's RuntimeWarnings came with their source lines, once per call site)."""
    import warnings  # lazy: only the command line changes how warnings look

    shown = set()

    def show(message, category, filename, lineno, file=None, line=None):
        text = format_warning(message, category)
        if text in shown:
            return
        shown.add(text)
        stream = file if file is not None else sys.stderr
        with contextlib.suppress(Exception):
            stream.write(text)

    warnings.showwarning = show
