"""Signals held back while compiled code runs (issue 38): a tier-0 helper the kernels' Python callers use.

flakedb's command line turns SIGTERM, SIGHUP and SIGINT into an exception (:class:`flakedb.process.Terminated`)
raised in the main thread, so that every ``finally`` cleans up.  Python runs that handler at the next bytecode
boundary of the main thread, and inside a numba dispatcher (typing the arguments, loading a cached kernel,
boxing the results) that boundary is in the middle of C code that does not expect an exception: 2 of 6
SIGTERMs to a running ``flakedb match`` ended as ``SystemError: CPUDispatcher(_scatter_kernel) returned a result
with an exception set``, 1 of 10 more as a segmentation fault (exit 139).

:func:`deferred` marks such a call: a handler that calls :func:`raise_or_defer` while the main thread is inside
it only records the exception, and it is raised when the outermost :func:`deferred` block ends, in plain Python.
The price: a signal waits for the kernel call in progress to return (one Mie series call or one BSDF
evaluation batch).  Pure Python, no signal or OS import: the kernels' tier may use it.

>>> with deferred():
...     raise_or_defer(RuntimeError("a signal's exception"))
...     print("the kernel call finished")
Traceback (most recent call last):
...
RuntimeError: a signal's exception
"""

from __future__ import annotations

import contextlib
import threading

#: depth of nested :func:`deferred` blocks in the main thread, and the exception held back (if any)
_STATE = {"depth": 0, "pending": None}


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def raise_or_defer(exc: BaseException) -> None:
    """Raise ``exc`` now, or, inside a :func:`deferred` block of the main thread, hold it until the block ends
    (a signal handler's way to raise; handlers run in the main thread)."""
    if _STATE["depth"] > 0 and _in_main_thread():
        if _STATE["pending"] is None:
            _STATE["pending"] = exc
        return
    raise exc


def hold(exc: BaseException) -> None:
    """Keep ``exc`` to be raised when the next outermost :func:`deferred` block of the main thread ends (a signal's
    exception that Python could not raise where it arrived, e.g. inside a finaliser; the first one kept)."""
    if _STATE["pending"] is None:
        _STATE["pending"] = exc


@contextlib.contextmanager
def deferred():
    """A block (a compiled kernel's call) during which :func:`raise_or_defer` holds its exception back; the
    held exception is raised when the outermost block ends.  Other threads: no effect (handlers run in the main
    thread only)."""
    if not _in_main_thread():
        yield
        return
    _STATE["depth"] += 1
    try:
        yield
    finally:
        _STATE["depth"] -= 1
        if _STATE["depth"] == 0 and _STATE["pending"] is not None:
            exc, _STATE["pending"] = _STATE["pending"], None
            raise exc
