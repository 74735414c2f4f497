"""Checks of the solver's inputs at its public edge (:mod:`flakedb.rt.adding.stack` components and
:mod:`flakedb.rt.scattering.media` media): a non-finite or out-of-range parameter is refused with a
``ValueError`` that names the field, the value and the allowed range, instead of reaching the
numerics (where it gave NaN output, a silently wrong BSDF, or a 72 TiB allocation for α < 0).
The recipe layer (:mod:`flakedb.paint.recipe`) checks the same quantities with the recipe's names."""

import numpy as np

#: Beckmann roughness accepted by the rough interfaces and the rough conductor (as the recipe):
#: the flux-cell integration splits cells into sub-intervals of 0.35 α (docs/rough-interfaces.md),
#: so below 0.01 a solve grows fast (measured, n = 16: α 3e-3 2.9 s; α 1e-3 27 s and 3.9 GB).
ALPHA_MIN = 0.01
ALPHA_MAX = 1.0


def check_range(owner, field, value, lo=None, hi=None, lo_open=False, hint=""):
    """Refuse ``value`` (a number or an array of them) unless every entry is finite and in the range:
    ``lo`` ≤ v (``lo_open``: lo < v) and v ≤ ``hi`` (None: unbounded).  Returns ``value`` unchanged.

    >>> check_range("Slab", "thickness_um", 2.0, 0.0)
    2.0
    >>> check_range("Slab", "thickness_um", -1.0, 0.0)
    Traceback (most recent call last):
    ...
    ValueError: Slab.thickness_um = -1.0 is outside the allowed range 0 ≤ thickness_um, finite
    """
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.{field} = {value!r} is not a number") from None
    bad = ~np.isfinite(a)
    if lo is not None:
        bad |= (a <= lo) if lo_open else (a < lo)
    if hi is not None:
        bad |= a > hi
    if np.any(bad):
        v = a[bad].flat[0] if a.ndim else float(a)
        low = "" if lo is None else f"{lo:g} {'<' if lo_open else '≤'} "
        high = "" if hi is None else f" ≤ {hi:g}"
        rng = f"{low}{field}{high}" if (lo is not None or hi is not None) else "finite"
        where = "" if not a.ndim else " (an entry)"
        raise ValueError(f"{owner}.{field} = {v!r}{where} is outside the allowed range {rng}, finite"
                         f"{'; ' + hint if hint else ''}")
    return value


def check_alpha(owner, alpha):
    """A Beckmann roughness in [ALPHA_MIN, ALPHA_MAX] (see there)."""
    return check_range(owner, "alpha", alpha, ALPHA_MIN, ALPHA_MAX,
                       hint=f"a smooth interface is Smooth / InnerSmooth; below {ALPHA_MIN:g} the flux-cell "
                            f"integration needs minutes and gigabytes")


def check_complex_index(owner, field, N):
    """A conductor's complex index n + ik (per channel): finite, n > 0, k ≥ 0."""
    a = np.asarray(N, dtype=complex)
    ok = np.isfinite(a) & (a.real > 0) & (a.imag >= 0)
    if not np.all(ok):
        v = a[~ok].flat[0] if a.ndim else a
        raise ValueError(f"{owner}.{field} = {complex(v)!r} is outside the allowed range: finite n + ik with "
                         f"n > 0 and k ≥ 0")
    return N


__all__ = ["ALPHA_MAX", "ALPHA_MIN", "check_alpha", "check_complex_index", "check_range"]
