"""What a series of solves of one recipe family (a fit: match, calibrate) may reuse between its evaluations
(issue 39 item 1, docs/fit-speed.md).

A fit changes a few recipe fields per evaluation; most often only loadings (volume fraction, optical depth),
which enter a medium linearly: σ_t and σ_s scale with them, and so does its kernel.  Everything computed
*per unit loading* is then the same in every evaluation: each species' optics (thin-film R(c), T(c) of a
flake, the Mie cross-sections and phase function of a pigment) and each medium's basis kernels projected on
the cosine series (:mod:`flakedb.rt.scattering.projection`; the loading sits in the combination matrix M).

A :class:`ReuseCache` holds such results keyed by *everything they depend on* (the species entry, the
binder index, the wavelengths, the node cosines, the orientation α, …: :func:`array_key` hashes arrays by
their bytes), never by the loading.  A change of a non-loading field (α, a film thickness, a size) is a
different key, computed afresh.  A value served from the cache is the very array that was computed, so a
cached fit gives the uncached fit's numbers (tests/rt/test_reuse.py, tests/match/test_fit_reuse.py).

The cache is active only inside :func:`reusing` (the fit's scope: match and calibrate open one per fit) and
holds at most ``budget_bytes`` (least recently used entries are dropped first), so it never grows without
bound; outside any scope nothing is kept and every function computes as before.
"""

from __future__ import annotations

import functools
import hashlib
import threading
from collections import OrderedDict
from contextlib import contextmanager

import numpy as np

#: Bytes a fit's cache may hold (arrays' nbytes).  The largest entries are a projection's basis coefficients,
#: B × h × 2h × (n_φ + 1) float64 (in memory, below the projection's budget) or a chunked round's envelope and
#: resident orders.  At 512 MiB a 2-panel calibrate's peak grew by 494 MiB (stale entries of the calibrated
#: species fill it before they go) while its reused entries are far smaller; a 3-loading match at 41 bands,
#: n = 40 grew by 165 MiB (docs/fit-speed.md).
DEFAULT_BUDGET_BYTES = 256 * 2**20


def array_key(a) -> tuple:
    """A hashable key of an array's dtype, shape and bytes (blake2b digest): equal keys, equal arrays.

    >>> array_key(np.arange(3.0)) == array_key([0.0, 1.0, 2.0]), array_key(np.arange(3.0)) == array_key(np.arange(3))
    (True, False)
    """
    a = np.asarray(a)
    if a.dtype.hasobject:  # (None, a list of objects): their text
        return ("object", a.shape, repr(a.tolist()))
    a = np.ascontiguousarray(a)
    return (a.dtype.str, a.shape, hashlib.blake2b(a.tobytes(), digest_size=16).hexdigest())


def _nbytes(value) -> int:
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, (tuple, list)):
        return sum(_nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values())
    return int(getattr(value, "nbytes", 0))


class ReuseCache:
    """A bounded map key → computed value (arrays, or tuples / dicts of them), least recently used dropped
    first when the values' bytes exceed ``budget_bytes``; thread-safe (the solver projects in threads).
    Counts ``hits`` and ``misses`` (what the tests and the benchmark read)."""

    def __init__(self, budget_bytes=DEFAULT_BUDGET_BYTES):
        self.budget_bytes = int(budget_bytes)
        self._items: OrderedDict = OrderedDict()
        self._sizes: dict = {}
        self.nbytes = 0
        self.hits = 0
        self.misses = 0
        self._lock = threading.Lock()

    def __len__(self):
        return len(self._items)

    def get(self, key):
        """The value stored under ``key`` (None when absent; counted as a hit or a miss)."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                self.hits += 1
                return self._items[key]
            self.misses += 1
            return None

    def put(self, key, value):
        """Store ``value`` (read-only arrays: a cached value is shared by every later evaluation) and drop
        the least recently used entries beyond the budget; a value larger than the whole budget is not kept."""
        size = _nbytes(value)
        _freeze(value)
        with self._lock:
            if key in self._items:
                self.nbytes -= self._sizes.pop(key)
                del self._items[key]
            if size > self.budget_bytes:
                return value
            self._items[key] = value
            self._sizes[key] = size
            self.nbytes += size
            while self.nbytes > self.budget_bytes:
                old, _ = self._items.popitem(last=False)
                self.nbytes -= self._sizes.pop(old)
        return value

    def get_or_compute(self, key, compute):
        """The value under ``key``, else ``compute()`` stored under it."""
        value = self.get(key)
        return self.put(key, compute()) if value is None else value


def _freeze(value):
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, (tuple, list)):
        for v in value:
            _freeze(v)
    elif isinstance(value, dict):
        for v in value.values():
            _freeze(v)


_ACTIVE: list = []
_ACTIVE_LOCK = threading.Lock()


def active_cache():
    """The innermost :func:`reusing` scope's cache, or None outside any (nothing is then kept)."""
    with _ACTIVE_LOCK:
        return _ACTIVE[-1] if _ACTIVE else None


@contextmanager
def reusing(cache=None, budget_bytes=DEFAULT_BUDGET_BYTES):
    """Make ``cache`` (a new :class:`ReuseCache` of ``budget_bytes`` when None) the active one for the block;
    its entries are released with it when the block ends (the fit's scope).  Process-wide (the solver's
    worker threads see it), so one fit at a time per process is the intended use.

    >>> with reusing() as c:
    ...     a = c.get_or_compute(("x",), lambda: np.ones(3)); b = c.get_or_compute(("x",), lambda: np.zeros(3))
    >>> b is a, c.hits, c.misses, active_cache() is None
    (True, 1, 1, True)
    """
    cache = ReuseCache(budget_bytes) if cache is None else cache
    with _ACTIVE_LOCK:
        _ACTIVE.append(cache)
    try:
        yield cache
    finally:
        with _ACTIVE_LOCK:
            _ACTIVE.remove(cache)


def reuse_per_call(fit):
    """Decorate a fit (:func:`flakedb.match.fit.match`, :func:`flakedb.match.calibrate.calibrate`) so that each
    call runs in its own :func:`reusing` scope: what its evaluations share is kept for that call only."""

    @functools.wraps(fit)
    def scoped(*args, **kwargs):
        with reusing():
            return fit(*args, **kwargs)

    return scoped
