"""The one path from a recipe to a checked, solved stack and its full-precision table, shared by compose, compare,
match, calibrate and texture (docs/resolution.md).

* :func:`solve_recipe`: the node count from :func:`flakedb.solve.resolution.resolve_node_count`, the species'
  optics (computed, or the store's factors: :class:`flakedb.solve.store_context.StoreContext`), the
  adding-doubling solve, :func:`check_physical` and the solver's convergence notes, the table.
* :func:`solve_reported`: :func:`solve_recipe` plus the colour report and the discretisation estimate (a second
  solve at :func:`flakedb.solve.resolution.second_solve_n`), and, for ``resolution: auto``, the refinement loop
  (:func:`flakedb.solve.resolution.refine_auto_n`) until the estimate meets the colour target.
* :func:`settle_node_count`: the n a series of solves of one recipe family uses (match, calibrate): the refined
  n of :func:`solve_reported` for ``auto``, else the fixed one.

A result that fails the product's physical check raises :class:`UnphysicalResultError` (no file is written), or
with ``allow_unphysical`` becomes a loud warning.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from flakedb import __version__
from flakedb.appearance.report import colour_report
from flakedb.bsdf.convert import stack_to_table
from flakedb.bsdf.table import ENERGY_SLACK, energy_albedo
from flakedb.conventions import fourier_weight
from flakedb.paint.mapping import build_paint, catalog_species, solve_paint
from flakedb.process import available_threads, memory_budget_bytes
from flakedb.solve.resolution import (
    AUTO_REFINE_STEPS,
    auto_colour_target,
    discretisation_error,
    refine_auto_n,
    resolve_node_count,
    second_solve_n,
)
from flakedb.solve.store_context import StoreContext
from flakedb.store import versions as st

#: What the outputs record as the store version until the precomputed store (issue #5) exists.
STORE_NONE = "none: computed directly"



class UnphysicalResultError(ValueError):
    """The solved BSDF fails :func:`check_physical` (compose writes nothing)."""


#: A passive stack may not reflect more than 1 + ALBEDO_SLACK of the incident flux.
ALBEDO_SLACK = 1e-3
#: Negative cosine-weighted BSDF values below −NEGATIVE_SLACK × its maximum are errors.  Measured
#: (2026-12-01, 181 azimuths, product settings): every catalogue recipe at n = 16, 32 and auto ≥ −2.4e-5
#: (coated aluminium; all others ≥ 0); mirror flakes α 0.05–0.15 at n 32–48 ≥ −3.3e-5, also with every
#: order kept; rough coats α 0.02–0.3 over white or an HG slab, n 32–128, ≥ −9e-6 (Jackson-filtered
#: where the 2n cap binds, docs/rough-interfaces.md "Positivity"); a medium kernel cut by the cap
#: (perfect mirror flakes α 0.15 in air at n 32 rang to −3.5 %) is Jackson-filtered the same way
#: (flakedb.rt.scattering.medium_projection.damp_if_capped): −2.4e-5.  So the threshold is 1e-3, 30× the worst measured value.
NEGATIVE_SLACK = 1e-3


def check_physical(stack, n_phi=37):
    """Problems of a solved (passive) stack, as one-line strings (empty: none).

    * directional albedo (table + delta) above 1 + :data:`ALBEDO_SLACK` at any node and channel;
    * a negative cosine-weighted BSDF f μ_i μ_o (node pairs × ``n_phi`` azimuths in [0, π]) below
      −:data:`NEGATIVE_SLACK` × its maximum;
    * the order choice did not converge (``info['order_converged']`` False) or the rough interface's
      energy scaling failed (non-finite values).
    """
    problems = []
    A = stack.albedo()
    if not np.all(np.isfinite(A)) or not np.all(np.isfinite(_solved_channels(stack.Rt))):
        return ["the BSDF has non-finite values (solver failure)"]
    amax = float(A.max())
    if amax > 1.0 + ALBEDO_SLACK:
        c, i = np.unravel_index(int(np.argmax(A)), A.shape)
        problems.append(f"albedo {amax:.6f} > 1 + {ALBEDO_SLACK:g} at θ_i = {np.degrees(np.arccos(stack.x[i])):.1f}° "
                        f"(channel {c}) for a passive stack")
    gmax, gmin = _bsdf_range(stack, np.linspace(0.0, np.pi, n_phi))
    if gmax > 0 and gmin < -NEGATIVE_SLACK * gmax:
        problems.append(f"negative BSDF value: f·μ_i·μ_o = {gmin:.3g} (max {gmax:.3g}, allowed down to "
                        f"−{NEGATIVE_SLACK:g} × max)")
    if stack.info.get("order_converged") is False:
        problems.append(f"Fourier orders did not converge (dropped tail {stack.info.get('order_tail', float('nan')):.2g} "
                        f"> order_tol {stack.info.get('order_tol')})")
    return problems


#: Channels per block of :func:`_bsdf_range` (issue 26 item 5: the whole (L, C, h, h) coefficient array
#: and its f copy held 1.15 GB each for a rough 0.1 coat over 41 bands at n = 200, 351 orders).
CHECK_CHANNEL_BLOCK = 4


def _solved_channels(Rt):
    """``Rt`` (L, C, h, h) with a channel axis solved once (broadcast, stride 0) cut to one channel."""
    return Rt[:, :1] if Rt.shape[1] > 1 and Rt.strides[1] == 0 else Rt


def _bsdf_range(stack, phi):
    """(max, min) of the cosine-weighted BSDF f μ_i μ_o of reflection over the node pairs and azimuths ``phi``,
    a few channels at a time (:data:`CHECK_CHANNEL_BLOCK`), so no copy of the coefficient array is made."""
    Rt, x, w = _solved_channels(stack.Rt), stack.x, stack.w
    L, C = Rt.shape[0], Rt.shape[1]
    # f_l μ_i μ_o = S_l μ_o / (c_l w_i) (conventions; StackBSDF.f_coefficients times μ_i μ_o): the series
    # Σ_l S_l cos(l φ) / c_l as one product over the orders, then the node pair's factor μ_o / w_i
    cos = np.cos(np.arange(L)[:, None] * phi[None, :]) / fourier_weight(np.arange(L))[:, None]  # (L, P)
    pair = (x[:, None] / w[None, :])[None, :, :, None]
    gmax, gmin = -np.inf, np.inf
    for c0 in range(0, C, CHECK_CHANNEL_BLOCK):
        blk = Rt[:, c0:c0 + CHECK_CHANNEL_BLOCK]
        g = (blk.reshape(L, -1).T @ cos).reshape(blk.shape[1:] + (phi.size,)) * pair  # (c, o, i, P)
        gmax, gmin = max(gmax, float(g.max())), min(gmin, float(g.min()))
    return gmax, gmin


@dataclass
class SolvedRecipe:
    """A recipe solved through the one path (:func:`solve_recipe`): its solver inputs, the solved stack, the
    full-precision table and what was decided on the way."""

    paint: object
    stack: object
    table: object
    n: int
    n_reason: str
    warnings: list
    timings_s: dict
    version: object = None
    store_label: str = STORE_NONE
    stored: object = None  # the StoreContext the optics came from (None: computed directly)
    before: object = None  # what ``before_solve`` returned (compose: the discretisation's second report)


def solve_recipe(recipe, n=None, raw=False, catalog=None, log=None, store=None, verify=True, progress=None,
                 allow_unphysical=False, generator="flakedb compose", n_reason=None, on_stored=None,
                 before_solve=None) -> SolvedRecipe:
    """Recipe → checked solution → full-precision table: the one orchestration that compose and match share.

    The node count from :func:`flakedb.solve.resolution.resolve_node_count` (``n`` > the recipe's > auto; ``n_reason``
    replaces the reason, for auto's refinement);
    ``store``: None, a store URL or an open :class:`flakedb.store.versions.StoreVersion` (checked against the
    recipe, its checksums verified with ``verify``); the solve with every core and the memory budget
    (``FLAKEDB_MEMORY_BUDGET`` bytes, else the solver's default); the result checked by
    :func:`check_physical` (a problem raises :class:`UnphysicalResultError`, or with ``allow_unphysical``
    becomes a warning) and the solver's convergence notes (:func:`solver_warnings`) added to the warnings.
    ``on_stored``: called with the open :class:`StoreContext` (None without a store) before the optics are
    built (compose starts the texture model there, to run beside the solve).  ``before_solve``: called with
    ``(paint, n, version)`` after the optics are built and before the solve, its result kept as ``before``
    (compose makes its discretisation's second solve there: :func:`second_report`).
    """
    log = log or (lambda s: None)
    progress = progress or (lambda stage, detail: None)
    n_used, reason = resolve_node_count(recipe, n)
    reason = n_reason or reason  # auto's refinement (compose) names its own reason
    warnings = list(recipe.warnings)
    t = {}
    version = stored = None
    store_label = STORE_NONE
    if store is not None and catalog_species(recipe):
        t0 = time.perf_counter()
        if isinstance(store, st.StoreVersion):
            version, stored = store, StoreContext.for_recipe(store, recipe, n_used, raw)
        else:
            stored = StoreContext.open_for_recipe(str(store), recipe, n_used, raw)
            version = stored.version
        if verify:  # the checksums of every file this recipe reads, V's order chunks as read (docs/store.md)
            version.verify(stored.prefixes(recipe))
        t["store_open"] = time.perf_counter() - t0
        store_label = f"{version.url} version {version.version} ({'raw' if raw else 'compressed'})"
        log(f"store: {store_label}, opened{' and verified' if verify else ''} in {t['store_open']:.2f} s")
    if on_stored is not None:
        on_stored(stored)
    t0 = time.perf_counter()
    progress("optics", {"start": True})
    paint = build_paint(recipe, catalog, stored=stored)
    t["optics"] = time.perf_counter() - t0
    log(f"optics: {len(paint.components)} component(s), {paint.n_channels} channel(s) ({paint.mode}), "
        f"{t['optics']:.2f} s")
    progress("optics", {"seconds": t["optics"], "channels": paint.n_channels})
    before = None if before_solve is None else before_solve(paint, n_used, version)
    t0 = time.perf_counter()
    stack = solve_paint(paint, n_used, memory_budget_bytes=memory_budget_bytes(),  # units parsed (flakedb.process)
                        threads=available_threads(), progress=progress)
    t["solve"] = time.perf_counter() - t0
    log(f"solve: n = {n_used} ({reason}), {stack.info.get('orders')} Fourier orders, {t['solve']:.2f} s")
    problems = check_physical(stack)
    if problems and not allow_unphysical:
        raise UnphysicalResultError(
            f"recipe {recipe.name}: unphysical result at n = {n_used}: " + "; ".join(problems)
            + "; nothing written.  Raise the resolution (--n) or rerun with --allow-unphysical to write it anyway.")
    for p in problems:
        warnings.append(f"UNPHYSICAL RESULT (written because of --allow-unphysical): {p}")
    solver_notes = solver_warnings(stack.info, n_used)
    for w in solver_notes:
        progress("warning", {"message": w})
    warnings += solver_notes
    md = {"recipe": recipe.name, "flakedb_version": __version__, "mode": paint.mode, "n_nodes": n_used,
          "store": store_label, "generator": generator}
    if recipe.description:
        md["description"] = " ".join(str(recipe.description).split())
    flakes = {c["path"]: c["orientation_distribution"] for c in paint.components if "orientation_distribution" in c}
    if flakes:  # the flakes' normal distribution (flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS), by recipe path
        md["flake_distributions"] = flakes
    t0 = time.perf_counter()
    table = stack_to_table(stack, paint.channels, paint.eta, None, paint.delta, md)  # α from the solved stack
    t["table"] = time.perf_counter() - t0
    # what `flakedb info` checks on the written file (issue 38), for an opaque paint (primer or metal base): a table
    # with transmission (a research stack without a bottom) holds the unscattered beam as a one-node spike that
    # the Catmull-Rom integral overshoots (an index-matched HG slab: 1.033 at n = 16 where the quadrature's is 1)
    written = float(energy_albedo(table).max()) if table.reflection_only else 0.0
    if written > 1.0 + ENERGY_SLACK:
        problem = (f"the written table's albedo reaches {written:.4f} > 1 + {ENERGY_SLACK:g} (the Catmull-Rom integral "
                   f"over its {table.n} nodes that renderers and `flakedb info` use; the solver's own albedo "
                   f"{float(stack.albedo().max()):.4f}): a lobe narrower than the node spacing (a metal or coat "
                   f"roughness near 0.01, aligned flakes)")
        if not allow_unphysical:
            raise UnphysicalResultError(
                f"recipe {recipe.name}: unphysical result at n = {n_used}: {problem}; nothing written.  Raise the "
                f"resolution (--n), make the narrowest surface rougher, or rerun with --allow-unphysical to write it "
                f"anyway.")
        warnings.append(f"UNPHYSICAL RESULT (written because of --allow-unphysical): {problem}")
    return SolvedRecipe(paint=paint, stack=stack, table=table, n=n_used, n_reason=reason, warnings=warnings,
                        timings_s=t, version=version, store_label=store_label, stored=stored, before=before)


def second_report(paint, n, version, colour_settings=None, progress=None, threads=None):
    """``(n', colour report at n')`` of the discretisation's second solve at n' = :func:`flakedb.solve.resolution.second_solve_n`
    (n/2 from n = 96 on, else ≈ 3n/4), or a dict saying why there is none: n < 16, or a store (it holds the species' factors at its own n
    only).  Made before the solve at n (:func:`solve_recipe`'s ``before_solve``), so that its arrays are freed
    before those of n exist: made after, while n's R^t and table were held, it set the compose's peak (cadmium
    yellow under a rough 0.1 coat, 41 bands, n = 200: 3.95 GB, of which 1.6 GB the second solve's).  ``threads``:
    the solver's threads (default :func:`flakedb.process.available_threads`; 1 beside the solve at n, so that its rough top is built in its own
    thread and the solver's background thread is the solve at n's)."""
    if version is not None:
        return {"method": "not estimated: species factors from the store exist at n only"}
    if n < 16:
        return {"method": f"not estimated: n = {n} < 16"}
    progress = progress or (lambda stage, detail: None)
    n2 = second_solve_n(n)
    t0 = time.perf_counter()
    progress("discretisation", {"start": True, "n": n2})
    second = solve_paint(paint, n2, memory_budget_bytes=memory_budget_bytes(), threads=threads or available_threads())
    table = stack_to_table(second.scattered(), paint.channels, paint.eta, None, paint.delta, {})
    x, albedo = second.x, second.albedo(include_delta=False)
    del second  # its R^t, before the report's evaluation
    report = colour_report(table, paint.mode, paint.wavelength_nm, x, albedo, paint.eta if paint.delta else None, "",
                           settings=colour_settings)
    progress("discretisation", {"seconds": time.perf_counter() - t0, "n": n2})
    return n2, report


def discretisation_estimate(solved, report, log=None) -> dict:
    """The estimated ΔE00 of the solve's own discretisation: the report against the second solve at
    n' = :func:`flakedb.solve.resolution.second_solve_n` (n/2 or 3n/4; :func:`flakedb.appearance.report.discretisation_error`,
    docs/resolution.md) that :func:`second_report` made before the solve (``solved.before``), for n ≥ 16 without
    a store (a store holds the species' factors at its own n only)."""
    n, second = solved.n, solved.before
    if isinstance(second, Future):  # made beside the solve (:data:`CONCURRENT_SECOND_BYTES`)
        second = second.result()
    if isinstance(second, dict):
        return second
    n2, report_second = second
    est = discretisation_error(report, report_second, n, n2)
    if log:
        log(f"discretisation: estimated dE00(n, 2n) {est['estimate_dE00']:.3f}, at most "
            f"{est['estimate_dE00_converged']:.3f} against the converged answer, at n = {n} (second solve at n = {n2})")
    return est


#: Above this, the kernel renormalisation (flakedb.rt.adding.stack.project_medium: σ_s of the discrete kernel made equal to
#: the accurately integrated one) is reported as a warning: the nodes under-resolve the kernel's peaks.
RENORM_WARN = 0.01


def solver_warnings(info, n) -> list:
    """Convergence problems in the solver's ``info`` (:func:`flakedb.rt.adding.stack.solve_stack`), as one-line
    warnings in words: a kernel whose azimuthal projection stopped at its sampling limit before its
    tolerance, a renormalisation larger than :data:`RENORM_WARN`, an order choice that did not converge.
    The same text goes to the terminal, the ``.h5`` (``warnings``) and the colour report."""
    out = []
    groups = info.get("groups") or [info]
    seen = set()
    for g in groups:
        for k in sorted(key for key in g if key.startswith("slab")):
            sl = g[k]
            layer = int(k[4:]) + 1
            if sl.get("converged") is False and ("conv", layer) not in seen:
                seen.add(("conv", layer))
                out.append(f"basecoat layer {layer}: the azimuthal projection of its scattering kernel stopped at "
                           f"{sl.get('n_phi')} azimuth samples before reaching its tolerance (tail "
                           f"{sl.get('tail', 0):.1e}); orders are capped at {sl.get('orders')} for n = {n}: "
                           f"a larger --n resolves narrower lobes")
            dev = sl.get("renorm_max_dev")
            if dev is not None and dev > RENORM_WARN and ("renorm", layer) not in seen:
                seen.add(("renorm", layer))
                out.append(f"basecoat layer {layer}: the kernel was renormalised by up to {100 * dev:.1f}% to "
                           f"conserve its scattering (nodes coarser than its peaks at n = {n}); a larger --n "
                           f"reduces it")
        if g.get("order_converged") is False and "orders" not in seen:
            seen.add("orders")
            out.append(f"Fourier orders: the dropped tail {g.get('order_tail', float('nan')):.1e} is above the "
                       f"tolerance {g.get('order_tol', float('nan')):.0e} at the cap of {g.get('orders_available')} "
                       f"orders (n = {n})")
    return out


@dataclass
class Reported:
    """A recipe solved and reported through :func:`solve_reported`: the last solve, its colour report (with the
    discretisation estimate), the node count's reason (auto's refinements appended), the warnings and timings."""

    solved: SolvedRecipe
    report: dict
    n_reason: str
    warnings: list
    timings_s: dict

    @property
    def n(self):
        return self.solved.n


def report_of(solved, colour_settings=None, name=""):
    """The colour report (:func:`flakedb.appearance.report.colour_report`) of a solved recipe; aspecular geometries
    never hit an inner mirror, so its smoothed series is kept out of the report (docs/model.md §4)."""
    paint, stack, table = solved.paint, solved.stack, solved.table
    report_table = table if stack.specular is None else stack_to_table(
        stack.scattered(), paint.channels, paint.eta, None, paint.delta, dict(table.metadata))
    return colour_report(report_table, paint.mode, paint.wavelength_nm, stack.x, stack.albedo(include_delta=False),
                         paint.eta if paint.delta else None, name, settings=colour_settings)


#: The discretisation's second solve (at n/2 or 3n/4) runs beside the main solve when the main solve's R^t, about
#: 4·C·n³ bytes (2n orders × C channels × (n/2)² float64), is at most this; above it, before the main solve, so
#: that the two never hold their arrays at once (cadmium yellow under a rough 0.1 coat, 41 bands, n = 200: a
#: 1.3 GB R^t; made after the solve, the second solve had set the peak at 3.95 GB, made before it 2.97 GB).
#: The solve itself keeps about one of two cores busy (docs/compose-overhead.md), so beside it the estimate's
#: time is mostly hidden; beside it the second solve runs on one thread (its rough top too), leaving the solver's
#: background thread to the solve at n.
CONCURRENT_SECOND_BYTES = 256e6


def solve_reported(recipe, n=None, raw=False, catalog=None, log=None, store=None, verify=True, progress=None,
                   allow_unphysical=False, colour_settings=None, on_stored=None,
                   generator="flakedb compose") -> Reported:
    """:func:`solve_recipe`, its colour report and the discretisation estimate (:func:`second_report`, made before
    each solve); for ``resolution: auto`` (neither ``n`` nor the recipe's resolution) solved again at
    :func:`flakedb.solve.resolution.refine_auto_n`'s n while the estimate misses the colour target, at most
    :data:`flakedb.solve.resolution.AUTO_REFINE_STEPS` times.  Timings: the last solve's, its ``report`` time,
    ``discretisation`` (its second solve) and ``refinement`` (every earlier solve)."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="flakedb-second-solve") as pool:
        return _solve_reported(recipe, n, raw, catalog, log, store, verify, progress, allow_unphysical,
                               colour_settings, on_stored, generator, pool)


def _solve_reported(recipe, n, raw, catalog, log, store, verify, progress, allow_unphysical, colour_settings,
                    on_stored, generator, pool) -> Reported:
    """:func:`solve_reported`'s body; ``pool`` runs the discretisation's second solve beside the main one."""
    second_s = []

    def timed(paint, n_solve, version, threads=None):
        t0 = time.perf_counter()
        try:
            return second_report(paint, n_solve, version, colour_settings, progress, threads)
        finally:
            second_s.append(time.perf_counter() - t0)

    def second(paint, n_solve, version):  # the discretisation's second solve, beside or before the solve at n_solve
        if version is None and 4.0 * paint.n_channels * float(n_solve) ** 3 <= CONCURRENT_SECOND_BYTES:
            return pool.submit(timed, paint, n_solve, version, 1)
        return timed(paint, n_solve, version)

    solved = solve_recipe(recipe, n, raw, catalog, log, store, verify, progress, allow_unphysical,
                          generator=generator, on_stored=on_stored, before_solve=second)
    auto_reason, refined, spent = solved.n_reason, [], 0.0
    colour_target = auto_colour_target(recipe)[0]
    fixed = n is not None or recipe.n is not None
    while True:
        t0 = time.perf_counter()
        report = report_of(solved, colour_settings, recipe.name)
        report["discretisation"] = discretisation_estimate(solved, report, log)
        t_report = time.perf_counter() - t0
        est = report["discretisation"].get("estimate_dE00")
        if fixed or est is None:
            break
        n_new, why = refine_auto_n(recipe, solved.n, est)
        if n_new is None or len(refined) >= AUTO_REFINE_STEPS:
            if refined or est > colour_target:
                refined.append(why if n_new is None else f"stopped after {AUTO_REFINE_STEPS} refinements: {why}")
            break
        if log:
            log(why)
        refined.append(why)
        spent += t_report + sum(solved.timings_s.values()) + (second_s[-1] if second_s else 0.0)
        solved = solve_recipe(recipe, n_new, raw, catalog, log, store, verify, progress, allow_unphysical,
                              generator=generator, n_reason=why, before_solve=second)
    warnings = list(solved.warnings)
    if refined and est is not None and est > colour_target:
        warnings.append(f"resolution auto: {refined[-1]}")
    t = dict(solved.timings_s, report=t_report)
    if spent:
        t["refinement"] = spent
    if second_s and second_s[-1] > 0.0:  # the last solve's discretisation solve (earlier ones are in "refinement")
        t["discretisation"] = second_s[-1]
    reason = auto_reason if not refined else auto_reason + "; " + "; ".join(refined)
    return Reported(solved=solved, report=report, n_reason=reason, warnings=warnings, timings_s=t)


def settle_node_count(recipe, n=None, catalog=None, store=None, raw=False, log=None) -> int:
    """The node count every solve of a fit (match, calibrate) uses, so that the objective does not jump with n:
    ``n`` or the recipe's own resolution, else ``resolution: auto`` checked and refined on ``recipe`` (the fit's
    start) by :func:`solve_reported`, as compose would.

    >>> class Fixed:
    ...     n, name = 48, "fixed"
    >>> settle_node_count(Fixed()), settle_node_count(Fixed(), 32)     # the recipe's own n; --n wins
    (48, 32)
    """
    if n is not None or recipe.n is not None:
        return resolve_node_count(recipe, n)[0]
    return solve_reported(recipe, None, raw, catalog, log, store, verify=False, generator="flakedb match").n
