"""The limits of a paint's numerical settings and the rules derived from them, each stated once (issue #21).

Every path that takes these settings calls the functions here: the recipe checks
(:mod:`flakedb.paint.recipe`), ``resolution: auto`` (:func:`flakedb.solve.resolution.auto_resolution`),
compose, match and build (:func:`flakedb.solve.resolution.resolve_node_count`), the command-line options
(:mod:`flakedb.cli.options`, :mod:`flakedb.cli.build`) and the store checks
(:mod:`flakedb.solve.store_context`).  The recipe schema (schemas/recipe.schema.json) restates the
numbers for editors and validators; ``tests/paint/test_limits.py`` checks that it agrees.

* **Node count** n (quadrature nodes over both hemispheres, n/2 per hemisphere, docs/model.md §5): even,
  :data:`NODE_COUNT_MIN` ≤ n ≤ :data:`NODE_COUNT_MAX`.  Below 8 the Gauss–Radau rule has 3 nodes per
  hemisphere and no catalogue paint is within ΔE00 1; above 512 a solve needs tens of GB
  (docs/resolution.md).  A file reader accepts larger tables (:mod:`flakedb.bsdf.limits`): files are
  not only ours.
* **Interface roughness** α (Beckmann, of a clear coat or an inner interface): 0 (smooth, handled
  exactly) or :data:`ROUGHNESS_MIN` ≤ α ≤ :data:`ROUGHNESS_MAX`.  Below 0.01 the flux-cell
  integration of the lobe (docs/rough-interfaces.md) needs minutes and gigabytes.
* **A rough interface** exists where α > 0 *and* the index changes (η ≠ 1): an index-matched boundary
  has nothing to be rough (:func:`is_rough_interface`).

>>> check_node_count(64)
64
>>> node_count_problem(33)
'33: the node count must be even, 8 ≤ n ≤ 512 (n/2 nodes per hemisphere), e.g. 64'
>>> is_rough_interface(1.5, 0.1), is_rough_interface(1.0, 0.1), is_rough_interface(1.5, 0.0)
(True, False, False)
>>> roughness_problem(0.001) is not None, roughness_problem(0.0), roughness_problem(0.3)
(True, None, None)
"""

from __future__ import annotations

import math
import numbers

from flakedb.rt.common.params import ALPHA_MAX, ALPHA_MIN

#: Smallest node count (4 nodes per hemisphere).
NODE_COUNT_MIN = 8
#: Largest node count: what compose, match, build and ``resolution: auto`` accept.
NODE_COUNT_MAX = 512
#: Smallest non-zero and largest Beckmann roughness of an interface (0 is a smooth interface): the solver's own
#: bounds (:data:`flakedb.rt.common.params.ALPHA_MIN`, :data:`~flakedb.rt.common.params.ALPHA_MAX`), stated once there.
ROUGHNESS_MIN, ROUGHNESS_MAX = ALPHA_MIN, ALPHA_MAX


def node_count_problem(n) -> str | None:
    """What is wrong with node count ``n`` (one line starting with the value), or None."""
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n % 2 or not NODE_COUNT_MIN <= n <= NODE_COUNT_MAX:
        return (f"{n!r}: the node count must be even, {NODE_COUNT_MIN} ≤ n ≤ {NODE_COUNT_MAX} (n/2 nodes per "
                f"hemisphere), e.g. 64")
    return None


def check_node_count(n) -> int:
    """``n`` as an int if it is an allowed node count, else :class:`ValueError` (:func:`node_count_problem`)."""
    problem = node_count_problem(n)
    if problem:
        raise ValueError(problem)
    return int(n)


def roughness_problem(alpha) -> str | None:
    """What is wrong with an interface roughness ``alpha`` (one line, the allowed range), or None."""
    a = float(alpha)
    if a == 0.0 or (ROUGHNESS_MIN <= a <= ROUGHNESS_MAX):
        return None
    if not math.isfinite(a):
        return f"value {a:g} is not a finite number"
    return (f"value {a:g} is outside the allowed range 0 (smooth) or {ROUGHNESS_MIN:g}-{ROUGHNESS_MAX:g} (Beckmann α; "
            f"below {ROUGHNESS_MIN:g} the flux-cell integration needs minutes and gigabytes; hint: write 0 for a smooth "
            f"interface)")


def is_rough_interface(eta, alpha) -> bool:
    """Whether a boundary of relative index ``eta`` and roughness ``alpha`` is a rough interface: α > 0 and η ≠ 1."""
    return float(alpha) > 0.0 and float(eta) != 1.0
