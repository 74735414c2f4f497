"""Tolerance bands per CIELAB coordinate: how far L*, a* or b* alone may move from a reference before a
colour-difference formula reaches its limit (the shaded bands of ``flakedb report``).

:func:`coordinate_bands` returns, per reference colour and coordinate c ∈ (L*, a*, b*), the steps
t₋ ≤ 0 ≤ t₊ with ΔE(ref, ref + t e_c) = limit, the other two coordinates held at the reference: the
intersection of the formula's tolerance body with the line through the reference along that axis.
For ΔE*ab the body is a sphere of radius ``limit`` and t± = ±limit exactly; for ΔE00 along L* it is
±limit·S_L with S_L evaluated at the mean lightness (Sharma et al. 2005, eq. 13), an implicit
equation, hence the root finder.  The band is what a coordinate plot can show of a three-dimensional
tolerance: a colour inside every band can still fail when it moves on two coordinates at once.

Root finding: along each half-line ΔE grows from 0; the step is bracketed by doubling from
``limit`` (at most :data:`MAX_STEP`) and refined by bisection to ``BISECTION_STEPS`` halvings of
the bracket (2⁻⁶⁰ of it: at the float resolution of the step).  A half-line on which ΔE stays below
the limit up to :data:`MAX_STEP` gives ±MAX_STEP.

>>> from flakedb.colour.tolerance import parse_formula
>>> coordinate_bands(parse_formula("deab"), [[50.0, 10.0, -5.0]], 1.5).round(12).tolist()
[[[-1.5, 1.5], [-1.5, 1.5], [-1.5, 1.5]]]
"""

from __future__ import annotations

import numpy as np

#: The largest step searched along a coordinate (CIELAB units): beyond the span of any real colour.
MAX_STEP = 400.0
#: Bisection halvings of the bracket.
BISECTION_STEPS = 60


def coordinate_bands(formula, lab_ref, limit) -> np.ndarray:
    """Steps (..., 3, 2) = (t₋, t₊) along L*, a*, b* from ``lab_ref`` (..., 3) at which ``formula``'s ΔE
    (an object with ``delta_E(lab_ref, lab_sample)``, e.g. :class:`flakedb.colour.tolerance.Formula`)
    reaches ``limit`` (scalar or (...,), ≥ 0), the other coordinates at the reference (module docstring)."""
    ref = np.asarray(lab_ref, float)
    lim = np.broadcast_to(np.asarray(limit, float), ref.shape[:-1])[..., None, None]   # (..., 1, 1)
    axes = np.eye(3)[:, None, :] * np.array([-1.0, 1.0])[None, :, None]                # (3, 2, 3): ±e_c
    r = ref[..., None, None, :]                                                          # (..., 1, 1, 3)

    def de(t):   # ΔE at step |t| along each signed axis, (..., 3, 2)
        return formula.delta_E(np.broadcast_to(r, t.shape + (3,)), r + t[..., None] * axes)

    shape = ref.shape[:-1] + (3, 2)
    hi = np.broadcast_to(np.maximum(lim, 1e-12), shape).copy()
    for _ in range(int(np.ceil(np.log2(MAX_STEP / max(float(np.min(hi)), 1e-12)))) + 1):
        low = de(hi) < lim
        if not np.any(low):
            break
        hi = np.where(low, np.minimum(2.0 * hi, MAX_STEP), hi)
    lo = np.zeros(shape)
    for _ in range(BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        below = de(mid) < lim
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    t = 0.5 * (lo + hi)
    t = np.where(np.broadcast_to(lim, shape) == 0.0, 0.0, t)
    return t * np.array([-1.0, 1.0])
