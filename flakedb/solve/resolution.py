"""The node count n of every solve, decided here and nowhere else (docs/resolution.md).

Precedence (:func:`resolve_node_count`): the caller's ``n`` (``--n``), else the recipe's ``resolution``, else
``resolution: auto`` (:func:`auto_resolution`) from accuracy targets and measured error envelopes; every n is
checked against :func:`flakedb.paint.limits.check_node_count`.  Auto's rules ask the solver's own test of a rough
inner interface solved as a smooth one (:func:`flakedb.rt.adding.stack.inner_interface_verdicts`), so auto and the solver
never disagree.  Auto then checks its result (:func:`refine_auto_n`) against the report's discretisation estimate,
made from a second solve at :func:`second_solve_n`.  Compose, compare, match, calibrate, texture and build ask
:func:`resolve_node_count` (or :func:`flakedb.solve.pipeline.solve_recipe`, which does).
"""

from __future__ import annotations

import numpy as np

from flakedb.colour.colorimetry import delta_E_2000
from flakedb.paint.limits import NODE_COUNT_MAX, check_node_count
from flakedb.paint.mapping import recipe_interfaces
from flakedb.paint.components import recipe_alpha, recipe_distribution
from flakedb.paint.recipe import CatalogParticle, CustomFlake, CustomMedium, RecipeError
from flakedb.rt.scattering.microflake import flake_lobe_alpha
from flakedb.rt.adding.stack import InnerRough, inner_interface_verdicts

#: Default accuracy targets of ``resolution: auto`` (a recipe's ``resolution: {albedo_error: …,
#: lobe_error: …, colour_error: …}`` overrides them; why these values: docs/resolution.md "colour_error").
AUTO_TARGETS = {"albedo_error": 0.03, "lobe_error": 0.05, "colour_error": 0.1}
#: The largest n the *default* colour_error may ask for (a recipe's own colour_error goes to
#: :data:`AUTO_MAX_N`): below the measured metal roughness 0.1 its n scales as 0.1/α (α 0.05 → 288,
#: α 0.02 → 512), a cost cliff a default must not have; the report's own estimate states the rest.
AUTO_COLOUR_MAX_N = 192
#: The largest node count auto may choose: the largest allowed (:data:`flakedb.paint.limits.NODE_COUNT_MAX`).
AUTO_MAX_N = NODE_COUNT_MAX
#: Measured envelopes (docs/resolution.md), (h·α, worst error at that h·α or above), h = n/2:
#: * rough coat lobe: reflection of the interface at normal incidence binned in 5° θ_o bins (Σ |Δ| per bin
#:   over the reflected total, the Monte Carlo criterion of issue 12) against n = 384, α ∈ {0.02, 0.05,
#:   0.1, 0.3}, η ∈ {1.3, 1.5, 1.7};
#: * directional albedo (θ_i ≤ 80°, relative) of coat / flake slab / diffuse primer against n = 192, by the
#:   flakes' α_f, over coat α ∈ {0.01 … 0.3}, η ∈ {1.3, 1.5, 1.7}, flake α_f ∈ {0.1, 0.2}.
COAT_LOBE_ERROR = ((1.6, 0.105), (2.4, 0.034), (3.2, 0.019), (4.8, 0.005), (6.4, 0.004), (9.6, 0.0015))
FLAKE_ALBEDO_ERROR = ((1.6, 0.051), (2.4, 0.033), (3.2, 0.028), (4.8, 0.019), (6.4, 0.012), (9.6, 0.008))
#: von Mises–Fisher media: the lobe's angular width is ≈ 1/√κ rad, so h ≥ VMF_H_PER_SQRT_KAPPA·√κ.
#: Measured (coat η 1.5 / vMF slab τ 2, ϖ 0.9 / diffuse 0.5, against n = 256, κ 10–1000): directional
#: albedo error (θ_i ≤ 80°) ≤ 2.3e-4 (the comparison's floor) for h/√κ ≥ 1.7; 1.4e-3 at 1.1, 3.6e-3 at 0.57.
VMF_H_PER_SQRT_KAPPA = 1.7
#: Directional albedo error (θ_i ≤ 80°) without flakes (coat α 0.01–0.3 / HG g 0.7, 0.9 slab / diffuse,
#: η 1.3–1.7) by n, against n = 192.
PLAIN_ALBEDO_ERROR = ((32, 0.0061), (48, 0.0026), (64, 0.0014), (96, 0.0007))
#: Metal base lobe (docs/resolution.md "Metal base"): reflection at normal incidence of a rough conductor
#: (N = 1.2 + 7i) under a smooth coat of η 1.5 or none, binned in 5° θ_o bins (per bin over the total),
#: against n = 384, worst over α ∈ {0.05, 0.1, 0.2, 0.3} at that n or above, by n.  The errors do not
#: collapse on h·α (the smooth coat's Snell-mapped binder grid), hence a table in n.
METAL_LOBE_ERROR = ((48, 0.048), (96, 0.021), (128, 0.013), (192, 0.0095))
#: Smallest metal roughness of those measurements; below it n is scaled by METAL_ALPHA_MEASURED / α
#: (the lobe's width is proportional to α), a stated extrapolation named in the reason.
METAL_ALPHA_MEASURED = 0.05
#: ``colour_error`` envelopes, CIEDE2000 worst over the report geometries (how each was measured:
#: docs/resolution.md "colour_error").  Metal base, by n, against the converged answer.
METAL_COLOUR_ERROR = ((48, 0.875), (64, 0.530), (96, 0.253), (128, 0.152), (144, 0.125), (160, 0.102),
                      (176, 0.084), (192, 0.070), (256, 0.038))
#: Roughness of that measurement: below it n is scaled by METAL_COLOUR_ALPHA / α (the lobe is α wide).
METAL_COLOUR_ALPHA = 0.1
#: Flakes, ΔE00(n, 2n) by h·α_f.
FLAKE_COLOUR_ERROR = ((3.2, 0.101), (4.0, 0.169), (4.8, 0.045))
#: Stacks without flakes or a metal base, ΔE00(n, 2n) by n.
PLAIN_COLOUR_ERROR = ((32, 0.053),)


#: Convergence order in n assumed by the report's estimate (:func:`flakedb.appearance.report.discretisation_error`)
#: and by :func:`refine_auto_n`: below every order observed in the measured ΔE00(n, 2n) envelopes
#: (docs/resolution.md: coated aluminium 1.7–2.1, metallic silver 1.95–2.0), so the estimate's factor
#: (1 − 2^−p)/(r^p − 1), which falls as p grows, is on the safe side, and so is the n it asks for.
DISCRETISATION_ORDER = 1.5
#: ``resolution: auto`` refines its n at most this many times when the report's own estimate misses the colour
#: target (:func:`refine_auto_n`), each step ×1.5 … ×2.
AUTO_REFINE_STEPS = 3


def auto_colour_target(recipe) -> tuple[float, bool]:
    """``(colour_error, own)``: the recipe's own ``colour_error`` target (own True) or :data:`AUTO_TARGETS`'s."""
    own = getattr(recipe, "targets", None) or {}
    return float(own.get("colour_error", AUTO_TARGETS["colour_error"])), "colour_error" in own


def refine_auto_n(recipe, n, estimate_dE00):
    """``(n', reason)`` when ``resolution: auto`` chose ``n`` but the report's own estimate of ΔE00(n, 2n)
    (:func:`flakedb.appearance.report.discretisation_error`) exceeds the recipe's colour_error target, else
    ``(None, reason)``: the measured envelopes (:func:`auto_resolution`) do not cover every stack (a rough,
    nearly index-matched inner interface has a transmitted lobe far narrower than its α; docs/resolution.md,
    "Closed loop"), so auto checks its result and solves again.  n' = n (estimate/target)^(1/p), p =
    :data:`DISCRETISATION_ORDER`, kept within ×1.5 … ×2 of n (an estimate from a pre-asymptotic n overshoots),
    rounded up to a multiple of 8, at most :data:`AUTO_COLOUR_MAX_N` for the default target (the recipe's own
    colour_error goes to :data:`AUTO_MAX_N`).

    >>> class R: targets = None
    >>> refine_auto_n(R(), 32, 2.56)[0], refine_auto_n(R(), 64, 0.11)[0], refine_auto_n(R(), 64, 0.09)[0]
    (64, 96, None)
    >>> refine_auto_n(R(), 192, 0.5)
    (None, 'the estimate 0.5 exceeds colour_error 0.1 at n = 192, the largest the default target may take (set colour_error in resolution: to go further)')
    """
    target, own = auto_colour_target(recipe)
    cap = AUTO_MAX_N if own else AUTO_COLOUR_MAX_N
    if not estimate_dE00 > target:
        return None, f"the estimate {estimate_dE00:.3g} meets colour_error {target:g}"
    if n >= cap:
        return None, (f"the estimate {estimate_dE00:.3g} exceeds colour_error {target:g} at n = {n}, the largest the "
                      + ("recipe's target may take" if own else
                         "default target may take (set colour_error in resolution: to go further)"))
    ratio = min(2.0, max(1.5, (estimate_dE00 / target) ** (1.0 / DISCRETISATION_ORDER)))
    n_new = min(cap, 8 * int(np.ceil(n * ratio / 8)))
    return n_new, (f"auto refined n {n} → {n_new}: the report's estimate ΔE00(n, 2n) {estimate_dE00:.3g} exceeded "
                   f"colour_error {target:g}")


def _needed(table, target):
    """Smallest tabulated abscissa whose measured error is ≤ target, and that error (None if none is)."""
    for x, e in table:
        if e <= target:
            return x, e
    return None, None


def _error_at(table, x):
    """Measured error envelope at abscissa ``x`` (the last row at or below it; None below the table)."""
    rows = [e for xx, e in table if xx <= x + 1e-12]
    return rows[-1] if rows else None


def auto_resolution(recipe) -> tuple[int, str]:
    """Node count n for ``resolution: auto`` from accuracy targets, and the reason (docs/resolution.md).

    Targets (``recipe.targets`` over :data:`AUTO_TARGETS`): ``albedo_error``, the relative error of the
    directional albedo for θ_i ≤ 80°, and ``lobe_error``, the rough coat's reflection lobe binned in 5°
    bins (per bin, over the reflected total); ``colour_error``, the CIEDE2000 between n and 2n at
    the report geometries, for a metal base against the converged answer (:func:`_colour_needs`: metal bases by
    n, flakes by h·α_f, other stacks by n; compose
    states the estimate of its own result from a second solve at :func:`second_solve_n`).  Each rule is a measured envelope, not
    a guess:

    * rough coat of roughness α: h α ≥ the smallest h α of :data:`COAT_LOBE_ERROR` meeting lobe_error
      (the flux-cell interface is lossless at every n, so its albedo is not what limits n);
    * flakes of Beckmann spread α_f: h α_f from :data:`FLAKE_ALBEDO_ERROR` for albedo_error, and at
      least the ΔE00 rule h ≥ 3/α_f (metallic-silver, RGB: ΔE00 ≈ 0.1 at h ≈ 2/α_f);
    * HG media: h ≥ 3/(1 − |g|); vMF media: h ≥ 1.7·√κ (:data:`VMF_H_PER_SQRT_KAPPA`); stacks without
      flakes: n from :data:`PLAIN_ALBEDO_ERROR`;
    * a metal base: n from :data:`METAL_LOBE_ERROR` for lobe_error (scaled by 0.05/α below α 0.05).

    The binder index enters through the measurements (η ∈ [1.3, 1.7] measured; outside it a warning
    in the reason).  n = 2h is rounded up to a multiple of 8, at least 32.  Orders: chosen by the
    solver from the BSDF's own Fourier tail (order_tol), the interfaces' lobes capped at 2n with a
    positive (Jackson) φ filter.  Raises :class:`flakedb.paint.recipe.RecipeError` naming the
    target, the n it needs, the largest allowed (:data:`AUTO_MAX_N`) and a suggestion when a target
    cannot be met.
    """
    targets = dict(AUTO_TARGETS)
    targets.update(getattr(recipe, "targets", None) or {})
    t_alb, t_lobe = float(targets["albedo_error"]), float(targets["lobe_error"])
    need = []  # (h, reason, problem-or-None)

    def fail(what, target, table, alpha, label):
        best = _error_at(table, AUTO_MAX_N // 2 * alpha)
        raise RecipeError(getattr(recipe, "source", "<recipe>"), [
            f"resolution: {what} {target:g} for {label} is not reachable: the smallest measured error is "
            f"{table[-1][1]:g} (at h·α = {table[-1][0]:g}; docs/resolution.md) and n ≤ {AUTO_MAX_N} "
            f"(hint: set resolution: {AUTO_MAX_N}" + (f", measured {what} ≤ {best:g}" if best is not None else "")
            + f", or raise {what} to ≥ {table[-1][1]:g})"])

    def add(table, target, alpha, label, what):
        x, err = _needed(table, target)
        if x is None:
            fail(what, target, table, alpha, label)
        h_real = x / alpha - 1e-9
        h = int(np.ceil(h_real)) if np.isfinite(h_real) and h_real < AUTO_MAX_N else AUTO_MAX_N
        if 2 * h > AUTO_MAX_N:
            best = _error_at(table, AUTO_MAX_N // 2 * alpha)
            raise RecipeError(getattr(recipe, "source", "<recipe>"), [
                f"resolution: {what} {target:g} for {label} needs n ≥ {2 * h} (h·α ≥ {x:g}, measured error "
                f"{err:g}; docs/resolution.md), above the largest allowed n = {AUTO_MAX_N} (hint: set "
                f"resolution: {AUTO_MAX_N}" + (f" (measured {what} ≤ {best:g})" if best is not None else "")
                + f", or raise {what})"])
        need.append((h, f"{label}: h·α ≥ {x:g} for {what} ≤ {target:g} (measured {err:g})"))

    cc = recipe.clearcoat
    if cc is not None and cc.roughness > 0:
        add(COAT_LOBE_ERROR, t_lobe, float(cc.roughness), f"rough coat α = {cc.roughness:g}", "lobe_error")
    flakes = False
    flake_alphas = []
    for _, p in recipe.particles():
        a = a0 = None
        if isinstance(p, CatalogParticle) and p.is_flake:  # the narrowest lobe on the Beckmann/GGX α scale
            a0 = recipe_alpha(p)
        elif isinstance(p, CustomFlake):
            a0 = float(p.orientation_alpha)
        if a0 is not None:
            a = flake_lobe_alpha(a0, recipe_distribution(p))
        elif isinstance(p, CustomMedium) and isinstance(p.phase, tuple) and p.phase[0] == "hg":
            hh = int(np.ceil(3.0 / max(1e-3, 1.0 - abs(p.phase[1]))))
            need.append((hh, f"HG lobe g = {p.phase[1]:g} ({p.path}): h ≥ 3/(1 − |g|)"))
        elif isinstance(p, CustomMedium) and isinstance(p.phase, tuple) and p.phase[0] == "vmf":
            hh = int(np.ceil(VMF_H_PER_SQRT_KAPPA * np.sqrt(float(p.phase[1]))))
            need.append((hh, f"vMF lobe κ = {p.phase[1]:g} ({p.path}): h ≥ {VMF_H_PER_SQRT_KAPPA:g}·√κ "
                             f"(measured albedo error ≤ 2.3e-4)"))
        if a is not None:
            flakes = True
            label = f"flakes α = {a0:g} ({p.path})" if a == a0 else (
                f"flakes α = {a0:g} ({p.path}; {recipe_distribution(p)}: a lobe as narrow as α {a:.3g} on the "
                f"Beckmann/GGX scale)")
            flake_alphas.append((a, label))
            add(FLAKE_ALBEDO_ERROR, t_alb, a, label, "albedo_error")
            need.append((int(np.ceil(min(3.0 / a, AUTO_MAX_N))), f"{label}: h ≥ 3/α (ΔE00 ≲ 0.1)"))
    metal = getattr(recipe, "metal", None)
    if metal is not None:
        n_m, err = _needed(METAL_LOBE_ERROR, t_lobe)
        if n_m is None:
            raise RecipeError(getattr(recipe, "source", "<recipe>"), [
                f"resolution: lobe_error {t_lobe:g} for a metal base is not reachable: the smallest measured error "
                f"is {METAL_LOBE_ERROR[-1][1]:g} (at n = {METAL_LOBE_ERROR[-1][0]}; docs/resolution.md) (hint: raise "
                f"lobe_error to ≥ {METAL_LOBE_ERROR[-1][1]:g}, or set resolution: {AUTO_MAX_N})"])
        why = f"metal base α = {metal.roughness:g}: n ≥ {n_m} for lobe_error ≤ {t_lobe:g} (measured {err:g})"
        if metal.roughness < METAL_ALPHA_MEASURED:
            n_m = int(np.ceil(n_m * METAL_ALPHA_MEASURED / metal.roughness))
            why += f", scaled by {METAL_ALPHA_MEASURED:g}/α below the measured α ≥ {METAL_ALPHA_MEASURED:g} → n ≥ {n_m}"
        if n_m > AUTO_MAX_N:
            raise RecipeError(getattr(recipe, "source", "<recipe>"), [
                f"resolution: lobe_error {t_lobe:g} for a metal base of roughness {metal.roughness:g} needs n ≥ {n_m} "
                f"({why}; docs/resolution.md), above the largest allowed n = {AUTO_MAX_N} (hint: set resolution: "
                f"{AUTO_MAX_N}, raise lobe_error, or raise {metal.path}.roughness)"])
        need.append((n_m // 2 + n_m % 2, why))
    t_col = targets.get("colour_error")
    if t_col is not None:
        col = _colour_needs(recipe, float(t_col), flake_alphas, metal)
        if "colour_error" not in (getattr(recipe, "targets", None) or {}):  # the default target: bounded cost
            h_cap = AUTO_COLOUR_MAX_N // 2
            col = [(hh, why) if hh <= h_cap else
                   (h_cap, why + f"; the default colour_error stops at n = {AUTO_COLOUR_MAX_N} (set colour_error "
                                 "in resolution: to go further; the report states the estimate)") for hh, why in col]
        need += col
    if not flakes:
        n_alb, err = _needed(PLAIN_ALBEDO_ERROR, t_alb)
        if n_alb is None:
            fail("albedo_error", t_alb, PLAIN_ALBEDO_ERROR, 1.0, "this stack")
        need.append((n_alb // 2, f"albedo_error ≤ {t_alb:g} without flakes: n ≥ {n_alb} (measured {err:g})"))
    notes = _inner_interface_needs(recipe, need, add, t_lobe)
    h = max(hh for hh, _ in need)
    n = _n_of_h(h)
    if n > AUTO_MAX_N:
        raise RecipeError(getattr(recipe, "source", "<recipe>"), [
            f"resolution: auto needs n = {n} ({max(need)[1]}), above the largest allowed n = {AUTO_MAX_N} "
            f"(hint: set resolution: {AUTO_MAX_N}, or relax the targets)"])
    binding = [r for hh, r in need if hh == h] + notes
    eta = float(recipe.binder_ior)
    note = "" if 1.3 <= eta <= 1.7 or eta == 1.0 else f"; binder index {eta:g} outside the measured 1.3–1.7"
    return n, "; ".join(binding) + note + f" → n = {n}"


def _n_of_h(h) -> int:
    """n = 2h rounded up to a multiple of 8, at least 32."""
    return max(32, 8 * int(np.ceil(2 * h / 8)))


def _inner_interface_needs(recipe, need, add, t_lobe):
    """Add the rule of each rough inner interface (the rough coat's measured lobe envelope, not measured for it)
    to ``need``, unless the solver solves it as a smooth one at the n the rest of the stack asks for
    (:func:`flakedb.rt.adding.stack.inner_interface_verdicts`: a nearly index-matched interface, whose lobe no node cell
    resolves): then it asks nothing, and the returned notes say so."""
    top, inner = recipe_interfaces(recipe)
    rough = [k for k, it in enumerate(inner) if isinstance(it, InnerRough)]
    notes = []
    if not rough:
        return notes
    n_rest = _n_of_h(max(hh for hh, _ in need))
    verdicts = inner_interface_verdicts(top, inner, n_rest)
    for k in rough:
        it, path = inner[k], recipe.basecoats[k].path
        if verdicts[k] is None:
            add(COAT_LOBE_ERROR, t_lobe, float(it.alpha),
                f"rough inner interface α = {it.alpha:g} ({path}; the rough coat's envelope)", "lobe_error")
        else:
            notes.append(f"rough inner interface α = {it.alpha:g} ({path}) nearly index-matched (normal Fresnel "
                         f"{verdicts[k]['normal_fresnel']:.1e}): the solver solves it as a smooth one at n = {n_rest}, "
                         "so it asks for no nodes")
    return notes


def resolve_node_count(recipe, n=None) -> tuple[int, str]:
    """The node count a solve of ``recipe`` uses and why: ``n`` (the command line's ``--n``), else the recipe's
    ``resolution``, else :func:`auto_resolution`; checked against :func:`flakedb.paint.limits.check_node_count`.
    The one place this precedence is decided (compose, match and build call it)."""
    if n is not None:
        n_used, reason = n, "--n"
    elif recipe.n is not None:
        n_used, reason = recipe.n, "recipe resolution"
    else:
        n_used, reason = auto_resolution(recipe)
    try:
        return check_node_count(n_used), reason
    except ValueError as e:
        raise ValueError(f"{reason} {e}") from None


def _colour_needs(recipe, target, flake_alphas, metal):
    """(h, reason) of the ``colour_error`` target (ΔE00 at the report geometries: against the converged answer for a
    metal base, between n and 2n otherwise) for ``flake_alphas`` ((Beckmann/GGX-scale α, label) per flake
    population) and ``metal`` from the measured envelopes :data:`METAL_COLOUR_ERROR`, :data:`FLAKE_COLOUR_ERROR`, :data:`PLAIN_COLOUR_ERROR`
    (docs/resolution.md "colour_error"); raises :class:`RecipeError` when no measured n meets it."""
    def refuse(what, table, unit):
        raise RecipeError(getattr(recipe, "source", "<recipe>"), [
            f"resolution: colour_error {target:g} for {what} is not reachable: the smallest measured ΔE00 is "
            f"{table[-1][1]:g} (at {unit} {table[-1][0]:g}; docs/resolution.md) (hint: raise colour_error to ≥ "
            f"{table[-1][1]:g}, or set resolution: n)"])

    out = []
    if metal is not None:
        n_m, err = _needed(METAL_COLOUR_ERROR, target)
        if n_m is None:
            refuse("a metal base", METAL_COLOUR_ERROR, "n =")
        why = (f"metal base α = {metal.roughness:g}: n ≥ {n_m} for colour_error ≤ {target:g} (measured ΔE00 {err:g} "
               f"against the converged answer)")
        if metal.roughness < METAL_COLOUR_ALPHA:
            n_m = int(np.ceil(n_m * METAL_COLOUR_ALPHA / metal.roughness))
            why += f", scaled by {METAL_COLOUR_ALPHA:g}/α → n ≥ {n_m}"
        out.append(((min(n_m, AUTO_MAX_N) + 1) // 2, why))
    for a, label in flake_alphas:  # a: the lobe's Beckmann/GGX-scale α; label names the recipe's own
        x, err = _needed(FLAKE_COLOUR_ERROR, target)
        if x is None:
            refuse(label, FLAKE_COLOUR_ERROR, "h·α =")
        out.append((min(int(np.ceil(x / a - 1e-9)), AUTO_MAX_N // 2),
                    f"{label}: h·α ≥ {x:g} for colour_error ≤ {target:g} (measured ΔE00 {err:g})"))
    if metal is None and not flake_alphas:
        n_p, err = _needed(PLAIN_COLOUR_ERROR, target)
        if n_p is None:
            refuse("this stack", PLAIN_COLOUR_ERROR, "n =")
        out.append((n_p // 2, f"colour_error ≤ {target:g}: n ≥ {n_p} (measured ΔE00 {err:g})"))
    return out


#: From this n on, the report's second solve is at n/2 instead of 3n/4 (:func:`second_solve_n`): there the
#: n/2 solve is in the error's asymptotic range and its estimate is on the safe side, where 3n/4's fell below
#: the true ΔE00(n, 2n) (docs/resolution.md, "The report's own estimate"; bench/estimate_accuracy.json).
SECOND_SOLVE_HALF_FROM = 96


def second_solve_n(n) -> int:
    """The node count of the report's second solve, always even: n/2 for n ≥ :data:`SECOND_SOLVE_HALF_FROM`,
    else 3n/4 (at least 8).  Below it n/2 can be pre-asymptotic (metallic silver: ΔE00(16, 32) was 21×
    ΔE00(32, 64)); from it on the n/2 solve costs about half the 3n/4 one and its estimate is the
    conservative one (docs/resolution.md).

    >>> [second_solve_n(n) for n in (16, 30, 32, 48, 94, 96, 100, 128, 200)]
    [12, 22, 24, 36, 70, 48, 50, 64, 100]
    """
    n = int(n)
    if n >= SECOND_SOLVE_HALF_FROM:
        return 2 * int(round(n / 4))
    return max(8, 2 * int(round(3 * n / 8)))


def discretisation_error(report, report_second, n, n_second):
    """The estimated ΔE00(n, 2n) of a report's own discretisation (and, ``estimate_dE00_converged``, against the
    converged answer: d/(r^p − 1) = c n^−p), from a second solve at ``n_second`` < n
    (:func:`second_solve_n`; docs/resolution.md, "colour_error"): d = max over the report geometries of
    ΔE00(n', n), times (1 − 2^−p)/(r^p − 1), r = n/n', p = :data:`DISCRETISATION_ORDER` (an error c·n^−p:
    ΔE00(n', n) = c n^−p (r^p − 1) and ΔE00(n, 2n) = c n^−p (1 − 2^−p)).  Its ratio to the true ΔE00(n, 2n):
    docs/resolution.md ("The report's own estimate").  Returns a JSON-able dict.

    >>> g = lambda L: {"geometries": [{"L": L, "a": 0.0, "b": 0.0}]}
    >>> round(discretisation_error(g(50.0), g(51.0), 32, 24)["estimate_dE00"], 3)      # ΔE00 1 between them
    1.197
    """
    lab = np.array([[g["L"], g["a"], g["b"]] for g in report["geometries"]])
    lab_second = np.array([[g["L"], g["a"], g["b"]] for g in report_second["geometries"]])
    d = delta_E_2000(lab_second, lab)
    r, p = float(n) / float(n_second), DISCRETISATION_ORDER
    factor = (1.0 - 2.0**-p) / (r**p - 1.0)
    return {"method": f"second solve at n = {n_second}: max dE00(n', n) over the report geometries times "
                      f"(1 - 2^-p)/(r^p - 1) = {factor:.3f} (r = n/n' = {r:.3f}, convergence of order p >= {p:g} "
                      "assumed), an estimate of dE00(n, 2n); times 1/(1 - 2^-p) against the converged answer",
            "n": int(n), "n_second": int(n_second), "order_assumed": p, "factor": float(factor),
            "dE00_second_vs_n": [float(v) for v in d], "estimate_dE00": float(factor * d.max()),
            "estimate_dE00_converged": float(d.max() / (r**p - 1.0))}
