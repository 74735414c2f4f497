"""Fitting a recipe to a multi-angle colour target: predict, compare, bounded least squares.

Fit parameters in a base recipe
-------------------------------
Any numeric recipe field may be written ``{fit: [min, max]}``, optionally with ``start: x`` (default:
the geometric mean of the bounds when min > 0, else their midpoint) and ``scale: log | linear``
(default log when min > 0).  :func:`find_fit_parameters` walks the YAML document and returns the
parameters with their field paths (``layers[1].basecoat.particles[0].volume_fraction``);
:func:`substitute` returns a concrete document for given values, which is then validated exactly
like any recipe (:func:`flakedb.recipe.parse_recipe`), so ``{fit: …}`` never reaches the schema.

Prediction at the target's geometries
-------------------------------------
:func:`compose_table` is the one compose call: compose's own path (:func:`flakedb.solve.pipeline.solve_recipe`,
with its physical check, threads and memory budget): recipe → paint → adding-doubling → the full-precision
table (:func:`flakedb.export.stack_to_table`), from the store when one is given.  Everything else here
calls it and nothing else, so a faster compose makes matching faster by itself.
:func:`eval_geometries` evaluates the table at any in-plane geometry (illumination θ_i, aspecular γ):
reflectance factor π f(ω_i, ω_o) with μ_i = cos θ_i, μ_o = −cos|θ_i − γ|, φ_d = 0 on the specular side
and π on the illuminator's side (:func:`flakedb.report.multiangle_geometry`, generalised from the
report's 45° to any θ_i) by the readers' Catmull–Rom interpolation (:func:`flakedb.report.eval_table`).

The fit (docs/colour-matching.md)
---------------------------------
Minimise Σ_g w_g ΔE00(target_g, predicted_g)² over the target's geometries g, with the CIEDE2000
residual split into three smooth components per geometry
(:func:`flakedb.colour.tolerance.ciede2000_residuals`), by scipy's bounded trust-region reflective
least squares (``least_squares(method="trf")``).  Parameters are optimised as ln p when their scale
is log: loadings act on the colour nearly linearly in ln p over a wide range (optical depth ∝ loading;
reflectance saturates), and a factor-3 error is then a fixed distance.  The Jacobian is a forward
difference, one compose call per parameter (step 10⁻³ in ln p, or 10⁻³ of the range for linear
parameters), so an iteration costs P + 1 compose calls; results are cached by parameter values.  Each fit
reuses what its evaluations share (:mod:`flakedb.rt.common.reuse`, docs/fit-speed.md): every species' optics and
projected kernel per unit loading, so an evaluation that moves only loadings recomputes neither.
The sensitivities reported at the solution are ∂(L*, a*, b*)/∂p per geometry, forward differences
with the same steps (cache hits when the last Jacobian was taken there).

Resolution of a fit
-------------------
Every evaluation of one fit stage uses one n, so the objective does not jump with n.  With a given n (``--n``,
the recipe's ``resolution: N``) that n; with ``resolution: auto`` and loadings only, the auto resolution settled
on the start values (:func:`flakedb.solve.pipeline.settle_node_count`); the same for other fields that leave the
auto resolution alone.  With ``resolution: auto`` and a fitted field that sets it (:data:`RESOLUTION_FIELDS`: a
flake's orientation α, an interface's roughness; each evaluation then also recomputes a projection,
docs/fit-speed.md), the fit first *searches* at a coarser n (:func:`search_node_count`: half the auto
resolution's first choice for the start values), then settles the auto resolution on the searched values and
*refines* there from the searched values with the same solver and stopping rules.  The result is the fit at the
n that compose picks for the fitted recipe (a fit from a narrow start α ran at the start's larger n, and its
colours then differed from its fitted recipe's by up to ΔE00 0.03 in the α bench); the search only supplies the
refine's start, so its coarser n does not enter the result.

Texture (docs/colour-matching.md, "Texture"): when the target has texture columns
(:mod:`flakedb.match.texture`), each compose call also predicts the texture indices
(:func:`flakedb.paint.texture_inputs.texture_report`, the composed BSDF as the ground) and the
residual vector gains u · (p_k − t_k)/δ_k per index (u the scheme's default ΔE00 limit): an index at
its tolerance δ_k costs as much as a geometry at its ΔE00 limit.  The flake diameter does not enter
the mean BSDF (ρ a = φ/t, docs/texture.md §6), so only such a target determines it; a parameter that
changes neither the colour nor a texture index is named in :attr:`MatchResult.undetermined`.

The outcome (docs/colour-matching.md, "Outcome")
-------------------------------------------------
A fit ends with the best values the bounded solver found; whether that is a match is a separate
question, answered against a tolerance (a :class:`flakedb.colour.tolerance.PerAngleLimits` or
:class:`~flakedb.colour.tolerance.WeightedLCH`; default: ΔE00 ≤
:data:`flakedb.colour.settings.DEFAULT_MAX_DE00` at every geometry).  :attr:`MatchResult.reached`
says whether every geometry (and every texture index) passes; :attr:`MatchResult.at_bound` names the parameters whose fitted
value lies within :data:`BOUND_FRACTION` of its range (in the fitted variable, ln p or p) from a
bound: the solver wanted to go further, so widening that bound (or another species) is the next
step; :attr:`MatchResult.outcome` says it in a sentence.  ``flakedb match`` exits non-zero when the
target is not reached.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass, field

import numpy as np
import yaml
from scipy.optimize import least_squares

from flakedb.colour.colorimetry import XYZ_to_Lab
from flakedb.colour.geometry import as_geometry_array, compact
from flakedb.colour.geometry import directions as directions_of
from flakedb.colour.geometry import cells as geometry_cells
from flakedb.colour.geometry import label as geometry_label
from flakedb.colour.settings import DEFAULT_MAX_DE00, for_target, resolve
from flakedb.colour.tolerance import (
    PerAngleLimits,
    ciede2000_residuals,
    delta_E_2000,
    lch,
    reflectance_to_Lab,
    shade_words,
)
from flakedb.solve.pipeline import settle_node_count, solve_recipe, solve_reported
from flakedb.appearance.report import (
    channels_to_XYZ,
    eval_table,
    reference_white,
    texture_ground,
)
from flakedb.match.texture import (
    DEFAULT_TEXTURE_TOLERANCE,
    evaluate_texture,
    format_texture_rows,
    predict_texture,
)
from flakedb.solve.resolution import resolve_node_count
from flakedb.paint.recipe import RecipeError, fmt_path, parse_recipe
from flakedb.rt.common.reuse import reuse_per_call

#: Forward-difference step: in ln p for log parameters, as a fraction of the range for linear ones.
FD_STEP = 1e-3
#: Default early stop: every geometry's ΔE00 at or below this (far below a visible difference).
DE_TOL = 0.01
#: A fitted value this close to a bound (fraction of the fitted variable's range) is "at the bound".
BOUND_FRACTION = 1e-3


class _Converged(Exception):
    """Raised inside the Jacobian when every ΔE00 is at or below ``de_tol``: stop there."""

    def __init__(self, z):
        self.z = z


# ----------------------------------------------------------------------------------------------
# {fit: [min, max]} parameters
# ----------------------------------------------------------------------------------------------


@dataclass
class FitParam:
    """One fitted recipe field: its path in the document, bounds, start value and scale."""

    path: tuple
    lo: float
    hi: float
    start: float
    log: bool

    @property
    def name(self) -> str:
        return fmt_path(list(self.path))

    def to_z(self, p):
        return math.log(p) if self.log else float(p)

    def from_z(self, z):
        return math.exp(z) if self.log else float(z)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _fit_param(path, spec, source) -> FitParam:
    extra = set(spec) - {"fit", "start", "scale"}
    if extra:
        raise RecipeError(source, [f"{fmt_path(list(path))}: unknown key(s) {sorted(extra)} in a fit field "
                                   f"(allowed: fit: [min, max], start: x, scale: log|linear)"])
    b = spec["fit"]
    if not (isinstance(b, list) and len(b) == 2 and all(_is_number(v) for v in b) and b[0] < b[1]):
        raise RecipeError(source, [f"{fmt_path(list(path))}: fit must be [min, max] with min < max, got {b!r} "
                                   f"(e.g. {{fit: [0.01, 0.1]}})"])
    lo, hi = float(b[0]), float(b[1])
    scale = spec.get("scale", "log" if lo > 0 else "linear")
    if scale not in ("log", "linear"):
        raise RecipeError(source, [f"{fmt_path(list(path))}: scale must be log or linear, got {scale!r}"])
    if scale == "log" and lo <= 0:
        raise RecipeError(source, [f"{fmt_path(list(path))}: scale: log needs min > 0, got {lo:g}"])
    if "start" in spec:
        s = spec["start"]
        if not (_is_number(s) and lo <= s <= hi):
            raise RecipeError(source, [f"{fmt_path(list(path))}: start {s!r} must be a number in [{lo:g}, {hi:g}]"])
        start = float(s)
    else:
        start = math.sqrt(lo * hi) if scale == "log" else 0.5 * (lo + hi)
    return FitParam(tuple(path), lo, hi, start, scale == "log")


def find_fit_parameters(doc, source="<base recipe>") -> list:
    """Every ``{fit: [min, max], …}`` field of a recipe document, in document order."""
    found = []

    def walk(node, path):
        if isinstance(node, dict):
            if "fit" in node:
                found.append(_fit_param(path, node, source))
                return
            for k, v in node.items():
                walk(v, path + (k,))
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, path + (i,))

    walk(doc, ())
    return found


def substitute(doc, params, values) -> dict:
    """A deep copy of ``doc`` with each parameter's field set to the matching value.

    The ``{fit: …}`` fields of a base recipe, found with their bounds and start (the geometric mean on a
    log scale unless given), and a concrete document made from values for them:

    >>> doc = {"layers": [{"basecoat": {"thickness_um": {"fit": [5, 20]},
    ...                                 "particles": [{"species": "metallic", "volume_fraction": {"fit": [0.01, 0.1], "start": 0.03}}]}}]}
    >>> params = find_fit_parameters(doc)
    >>> [(p.name, p.lo, p.hi, p.start, p.log) for p in params]
    [('layers[0].basecoat.thickness_um', 5.0, 20.0, 10.0, True), ('layers[0].basecoat.particles[0].volume_fraction', 0.01, 0.1, 0.03, True)]
    >>> substitute(doc, params, [12.0, 0.05])["layers"][0]["basecoat"]
    {'thickness_um': 12.0, 'particles': [{'species': 'metallic', 'volume_fraction': 0.05}]}
    """
    out = copy.deepcopy(doc)
    for p, v in zip(params, values):
        node = out
        for k in p.path[:-1]:
            node = node[k]
        node[p.path[-1]] = float(v)
    return out


def recipe_from_doc(doc, source="<recipe>", catalog=None):
    """Validate a concrete document as a recipe (:func:`flakedb.recipe.parse_recipe` on its YAML)."""
    return parse_recipe(yaml.safe_dump(doc, sort_keys=False, allow_unicode=True), source=source, catalog=catalog)


# ----------------------------------------------------------------------------------------------
# Prediction at multi-angle geometries
# ----------------------------------------------------------------------------------------------


def compose_solved(recipe, n, catalog=None, store=None, raw=False):
    """``recipe`` solved at ``n`` nodes through compose's own path
    (:func:`flakedb.solve.pipeline.solve_recipe`: its physical check, threads and memory budget);
    ``store``: an open :class:`flakedb.store.versions.StoreVersion` (verified once by the caller) or None."""
    return solve_recipe(recipe, n, raw=raw, catalog=catalog, store=store, verify=False, generator="flakedb match")


def compose_table(recipe, n, catalog=None, store=None, raw=False):
    """``(paint, table)`` of ``recipe`` at ``n`` nodes (:func:`compose_solved`)."""
    solved = compose_solved(recipe, n, catalog, store, raw)
    return solved.paint, solved.table


def geometry_directions(geometries):
    """(mu_i, mu_o, phi_d) arrays (G,) of geometries (G, 2) = (illumination_deg, aspecular_deg) or (G, 3) with
    an azimuth (out of plane, :mod:`flakedb.colour.geometry`)."""
    g = as_geometry_array(geometries)
    bad = [(i, a, z) for i, a, z in g if (z == 0.0 and not (0.0 <= i < 90.0 and abs(i - a) < 90.0))]
    if bad:
        raise ValueError(f"geometry (illumination {bad[0][0]:g}°, aspecular {bad[0][1]:g}°): the source must be within "
                         f"[0, 90)° and the detector within ±90° of the normal")
    mu_i, mu_o, phi_d, _ = directions_of(g)
    return mu_i, mu_o, phi_d


def eval_geometries(table, geometries) -> np.ndarray:
    """Reflectance factors π f (G, C) of a table at geometries, in plane or out of plane (module docstring)."""
    mu_i, mu_o, phi_d = geometry_directions(geometries)
    return np.pi * eval_table(table, mu_i, mu_o, phi_d) / np.abs(mu_o)[:, None]


def channels_to_Lab(rf, mode, wavelength_nm, observer=None, illuminant=None) -> np.ndarray:
    """CIELAB (G, 3) of reflectance factors in a paint's channels under ``observer`` / ``illuminant``
    (None: the defaults for ``mode``, :func:`flakedb.colour.settings.resolve`).

    Spectral: any observer / illuminant the grid allows.  RGB mode is defined under D65 / 2° only
    (its channels are white-normalised linear sRGB; anything else raises ValueError); mono is a
    grey, the same under any conditions.
    """
    cs = resolve(observer, illuminant, mode=mode)
    if mode == "spectral":
        return reflectance_to_Lab(rf, wavelength_nm, cs.observer, cs.illuminant)
    return XYZ_to_Lab(channels_to_XYZ(rf, mode, wavelength_nm), white=reference_white(mode, wavelength_nm))


@dataclass
class Prediction:
    """A recipe's reflectance factors at geometries: ``rf`` (G, C) in ``mode``'s channels."""

    geometries: np.ndarray
    rf: np.ndarray
    mode: str
    wavelength_nm: np.ndarray | None
    n: int
    #: the smooth BSDF's luminance factors for the texture indices (:func:`flakedb.appearance.report.texture_ground`)
    ground: object = None

    def lab(self, observer=None, illuminant=None):
        return channels_to_Lab(self.rf, self.mode, self.wavelength_nm, observer, illuminant)


def predict(recipe, geometries, n=None, catalog=None, store=None, raw=False) -> Prediction:
    """Compose ``recipe`` once and evaluate it at ``geometries`` (G, 2): at ``n`` or the recipe's resolution, else
    at ``resolution: auto`` checked and refined as compose does (:func:`flakedb.solve.pipeline.solve_reported`), so
    compare and compose use the same n."""
    if n is None and recipe.n is None:
        solved = solve_reported(recipe, None, raw, catalog, store=store, verify=False, generator="flakedb match").solved
    else:
        solved = compose_solved(recipe, resolve_node_count(recipe, n)[0], catalog, store, raw)
    n = solved.n
    paint, table, stack = solved.paint, solved.table, solved.stack
    g = compact(geometries)
    ground = texture_ground(table, paint.mode, paint.wavelength_nm, stack.x, stack.albedo(include_delta=False),
                            paint.eta if paint.delta else None)   # as compose's report (docs/texture.md §4)
    return Prediction(g, eval_geometries(table, g), paint.mode, paint.wavelength_nm, n, ground)


def compare_texture(recipe, prediction, target, rel=DEFAULT_TEXTURE_TOLERANCE):
    """``(rows, sparkle)``: :func:`flakedb.match.texture.evaluate_texture` of ``recipe``'s predicted texture
    against ``target``'s texture columns (the BSDF of ``prediction`` as the ground), and whether the
    recipe has flakes that sparkle at all; ``([], None)`` for a target without texture columns."""
    if not target.texture:
        return [], None
    pred, rep = predict_texture(recipe, list(target.texture), target.texture_observer, prediction.ground)
    return evaluate_texture(pred, target.texture, rel), bool(rep["sparkle"])


# ----------------------------------------------------------------------------------------------
# The fit
# ----------------------------------------------------------------------------------------------


@dataclass
class MatchResult:
    params: list
    start: np.ndarray
    values: np.ndarray
    geometries: np.ndarray
    weights: np.ndarray
    lab_target: np.ndarray
    lab_start: np.ndarray
    lab_fit: np.ndarray
    de_start: np.ndarray
    de_fit: np.ndarray
    sensitivities: np.ndarray           # (G, 3, P): d(L*, a*, b*)/dp in the parameter's units
    fitted_doc: dict
    prediction: Prediction
    n: int
    observer: str
    illuminant: str
    n_compose: int
    compose_s: float
    iterations: int
    nfev: int
    status: int
    message: str
    history: list = field(default_factory=list)
    tolerance: dict | None = None       # the scheme's evaluation at the fit (PerAngleLimits.evaluate)
    at_bound: list = field(default_factory=list)   # [(parameter name, "lower" | "upper", bound value)]
    texture_start: list = field(default_factory=list)   # evaluate_texture rows at the start ([]: no texture columns)
    texture_fit: list = field(default_factory=list)     # … at the fit
    texture_sensitivities: np.ndarray | None = None     # (K, P): d(index)/dp in the parameter's units
    texture_tolerance: float = DEFAULT_TEXTURE_TOLERANCE
    sparkle: bool | None = None                         # the fitted recipe sparkles (None: no texture columns)
    undetermined: list = field(default_factory=list)    # parameters that change nothing the target measures

    @property
    def texture_passed(self) -> bool:
        return all(r["passed"] for r in self.texture_fit)

    @property
    def compose_s_per_call(self) -> float:
        return self.compose_s / max(self.n_compose, 1)

    @property
    def reached(self) -> bool:
        """Every geometry within the tolerance and every texture index within its own (module docstring,
        "The outcome")."""
        return bool(self.tolerance is not None and self.tolerance["passed_all"] and self.texture_passed)

    @property
    def outcome(self) -> str:
        """One sentence: reached or not, where it fails, and which parameters sit at a bound."""
        tol = self.tolerance
        bound = "; ".join(f"{name} at its {side} bound {v:g}" for name, side, v in self.at_bound)
        loose = "; ".join(f"{name} changes neither the colour nor a texture index of the target: not determined by "
                          f"it (left at its start value)" for name in self.undetermined)
        tex = (f" and every texture index within {self.texture_tolerance:.0%} (or its floor)"
               if self.texture_fit else "")
        notes = "; ".join(x for x in (bound, loose) if x)
        if self.reached:
            return (f"target reached: every geometry within {tol['scheme']}{tex}"
                    + (f" (note: {notes})" if notes else ""))
        parts = []
        fail = [i for i, ok in enumerate(tol["passed"]) if not ok]
        if fail:
            worst = max(fail, key=lambda i: tol["value"][i])
            g = self.geometries[worst]
            parts.append(f"{len(fail)} of {len(tol['passed'])} geometries outside {tol['scheme']} "
                         f"(worst {geometry_label(g)}: {tol['value'][worst]:.2f} > {tol['limit'][worst]:.2f})")
        tfail = [r for r in self.texture_fit if not r["passed"]]
        if tfail:
            parts.append(f"{len(tfail)} of {len(self.texture_fit)} texture indices outside tolerance ("
                         + ", ".join(f"{r['index']} {r['predicted']:.4g} vs {r['target']:.4g}" for r in tfail) + ")"
                         + ("; the fitted recipe has no flakes: no sparkle" if self.sparkle is False else ""))
        why = (f"parameters at a bound: {bound}; widen the bound or use another species" if bound else
               "no parameter is at a bound: the species in the base recipe cannot reach this target together "
               "(or the fit stopped in a local minimum / at the evaluation limit: " + self.message.strip() + ")")
        return f"target NOT reached: {'; '.join(parts)}; {why}" + (f" (note: {loose})" if loose else "")


class _Evaluator:
    """Compose-and-evaluate with a cache on the parameter values; counts compose calls and time."""

    def __init__(self, doc, params, geometries, n, observer, illuminant, catalog, store, raw, source, target=None,
                 texture_tol=DEFAULT_TEXTURE_TOLERANCE):
        self.doc, self.params, self.geometries = doc, params, geometries
        self.n, self.observer, self.illuminant = n, observer, illuminant
        self.catalog, self.store, self.raw, self.source = catalog, store, raw, source
        self.target = target if target is not None and target.texture else None
        self.texture_tol = texture_tol
        self.cache = {}
        self.calls = 0
        self.seconds = 0.0

    def prediction(self, values) -> Prediction:
        key = tuple(float(v) for v in values)
        if key not in self.cache:
            rec = recipe_from_doc(substitute(self.doc, self.params, key), self.source, self.catalog)
            t0 = time.perf_counter()
            pred = predict(rec, self.geometries, self.n, self.catalog, self.store, self.raw)
            tex = (compare_texture(rec, pred, self.target, self.texture_tol) if self.target is not None
                   else ([], None))
            self.seconds += time.perf_counter() - t0
            self.calls += 1
            self.cache[key] = (pred, pred.lab(self.observer, self.illuminant), tex)
        return self.cache[key][0]

    def lab(self, values) -> np.ndarray:
        self.prediction(values)
        return self.cache[tuple(float(v) for v in values)][1]

    def texture(self, values) -> tuple:
        """(:func:`flakedb.match.texture.evaluate_texture` rows, sparkle) at ``values``."""
        self.prediction(values)
        return self.cache[tuple(float(v) for v in values)][2]

    def texture_residuals(self, values) -> np.ndarray:
        """r_k = (p_k − t_k)/δ_k of the target's texture columns (empty without them).  An index the model
        cannot predict at these values (graininess of a thick, dense flake layer) ends the fit with a
        ValueError naming it: a least-squares residual must be a number."""
        rows = self.texture(values)[0]
        missing = [r["index"] for r in rows if r["residual"] is None]
        if missing:
            raise ValueError(f"target texture column(s) {', '.join(missing)}: not predicted for this recipe at "
                             f"{', '.join(f'{v:.4g}' for v in values)} (the hiding term cancels the single-flake term: "
                             f"outside the texture model, docs/texture.md §4); match without them")
        return np.array([r["residual"] for r in rows], float)


#: The last field of the paths that set the auto resolution (:func:`flakedb.solve.resolution.auto_resolution`:
#: a flake's orientation spread, an interface's roughness) and change a projection at every evaluation.
RESOLUTION_FIELDS = ("orientation_alpha", "roughness")
#: Smallest node count a search runs at (module docstring, "Resolution of a fit").
SEARCH_MIN_N = 16


def search_node_count(recipe, n, params):
    """The coarser node count a fit searches at before it settles the resolution on the searched values
    (module docstring, "Resolution of a fit"), or None (the fit settles n at its start and runs there): only
    with ``resolution: auto`` (no ``n``, no recipe resolution) and a fitted field that sets the auto resolution
    (:data:`RESOLUTION_FIELDS`); half the auto resolution's first choice for the start values, even, at least
    :data:`SEARCH_MIN_N`, and None when that is not coarser."""
    if n is not None or recipe.n is not None:
        return None
    if not any(p.name.rsplit(".", 1)[-1] in RESOLUTION_FIELDS for p in params):
        return None
    n_auto = resolve_node_count(recipe)[0]
    n_s = max(SEARCH_MIN_N, 2 * (n_auto // 4))
    return n_s if n_s < n_auto else None


def _fd_steps(params, z, lb, ub):
    h = np.array([FD_STEP if p.log else FD_STEP * (p.hi - p.lo) for p in params])
    return np.where(z + h > ub, -h, h)


@reuse_per_call
def match(doc, target, observer=None, illuminant=None, weights=None, n=None, catalog=None, store=None, raw=False,
          log=None, max_nfev=50, de_tol=DE_TOL, source="<base recipe>", tolerance=None,
          texture_tolerance=DEFAULT_TEXTURE_TOLERANCE) -> MatchResult:
    """Fit the ``{fit: …}`` fields of recipe document ``doc`` to ``target`` (a
    :class:`flakedb.colour.targets.Target`); see the module docstring.

    ``observer`` / ``illuminant``: the colour conditions of the fit (default: the target's);
    ``weights`` (G,): w_g per geometry (default 1); ``store``: an open store version; ``log``: a
    callable taking one progress line per iteration; ``de_tol``: stop as soon as every geometry's
    ΔE00 ≤ de_tol (0 or None: run scipy's own tests to the end); ``tolerance``: the scheme the outcome
    is judged by (an object with ``evaluate(geometries, lab_ref, lab_sample)``; default ΔE00 ≤
    :data:`flakedb.colour.settings.DEFAULT_MAX_DE00` everywhere).  Raises RecipeError before any
    computation when the recipe is invalid at the start values or at the bounds.

    A target with texture columns (:mod:`flakedb.match.texture`) adds one residual per index,
    u · (p_k − t_k)/δ_k with δ_k = max(``texture_tolerance`` · |t_k|, floor_k) and u the scheme's default
    ΔE00 limit (1 for a scheme without one): an index at its tolerance costs as much as one geometry at
    its ΔE00 limit; "reached" then also needs every |p_k − t_k| ≤ δ_k (docs/colour-matching.md, "Texture").
    """
    log = log or (lambda s: None)
    params = find_fit_parameters(doc, source)
    if not params:
        raise RecipeError(source, ["no field to fit: write one or more numeric fields as {fit: [min, max]}"])
    for label, vals in (("start values", [p.start for p in params]), ("lower bounds", [p.lo for p in params]),
                        ("upper bounds", [p.hi for p in params])):
        try:
            rec = recipe_from_doc(substitute(doc, params, vals), source, catalog)
        except RecipeError as exc:
            raise RecipeError(source, [f"with every fit field at its {label}: {p}" for p in exc.problems]) from None
        if label == "start values":
            rec0 = rec
    n_search = search_node_count(rec0, n, params)
    if n_search is None:
        n = settle_node_count(rec0, n, catalog, store, raw, log)  # one n for every evaluation of the fit
    cs = for_target(rec0.mode, target, observer, illuminant)
    obs, ill = cs.observer, cs.illuminant
    geoms = compact(target.geometries)
    G = geoms.shape[0]
    w = np.ones(G) if weights is None else np.asarray(weights, float)
    if w.shape != (G,) or np.any(w < 0):
        raise ValueError(f"weights: need {G} non-negative values, one per target geometry")
    sw = np.sqrt(w)
    lab_t = target.lab_under(obs, ill)
    scheme = tolerance if tolerance is not None else PerAngleLimits(default=DEFAULT_MAX_DE00)
    unit = float(getattr(scheme, "default", DEFAULT_MAX_DE00))  # a texture index at δ_k weighs one ΔE00 limit
    to_p = lambda z: np.array([p.from_z(v) for p, v in zip(params, z)])
    lb = np.array([p.to_z(p.lo) for p in params])
    ub = np.array([p.to_z(p.hi) for p in params])
    z0 = np.clip(np.array([p.to_z(p.start) for p in params]), lb, ub)
    history = []

    residuals = getattr(scheme, "residuals", ciede2000_residuals)  # the scheme's formula (--formula), else ΔE00
    de_label = getattr(getattr(scheme, "formula", None), "label", "dE00")

    def solve(ev, z_start, stage=""):
        """Bounded least squares with ``ev``'s compositions from ``z_start``: (z, nfev, status, message)."""
        def resid(z):
            colour = (sw[:, None] * residuals(lab_t, ev.lab(to_p(z)))).ravel()
            return np.concatenate([colour, unit * ev.texture_residuals(to_p(z))])

        def jac(z):
            r0 = resid(z)
            h = _fd_steps(params, z, lb, ub)
            J = np.empty((r0.size, len(params)))
            for j in range(len(params)):
                zj = z.copy()
                zj[j] += h[j]
                J[:, j] = (resid(zj) - r0) / h[j]
            de = np.linalg.norm(residuals(lab_t, ev.lab(to_p(z))), axis=-1)
            rt = np.abs(ev.texture_residuals(to_p(z)))
            line = (f"{stage}iteration {len(history)}: "
                    f"{'cost (colour + texture)' if rt.size else f'sum w*{de_label}^2'} = "
                    f"{float(r0 @ r0):.4g}, max {de_label} = {de.max():.3f}"
                    + (f", max |texture difference|/tolerance = {rt.max():.3f}" if rt.size else "") + "; "
                    + ", ".join(f"{p.name} = {v:.6g}" for p, v in zip(params, to_p(z)))
                    + f"  [{ev.calls} compose calls, {ev.seconds / max(ev.calls, 1):.2f} s/call]")
            history.append({"values": to_p(z).tolist(), "cost": float(r0 @ r0),
                            "max_dE00": float(delta_E_2000(lab_t, ev.lab(to_p(z))).max())}
                           | ({"max_texture_residual": float(rt.max())} if rt.size else {})
                           | ({"n": ev.n, "stage": "search"} if stage else {}))
            log(line)
            if de_tol and de.max() <= de_tol and np.all(unit * rt <= de_tol):
                raise _Converged(z.copy())
            return J

        try:
            sol = least_squares(resid, z_start, jac=jac, bounds=(lb, ub), method="trf", x_scale="jac",
                                ftol=1e-10, xtol=1e-7, gtol=1e-10, max_nfev=max_nfev)
            return sol.x, int(sol.nfev), int(sol.status), str(sol.message)
        except _Converged as c:
            return (c.z, len(history), 5, f"every {de_label} <= {de_tol:g}"
                    + (" and every texture index within 1 % of its tolerance" if target.texture else ""))

    z_begin, evaluators = z0, []
    if n_search is not None:
        # search at a coarser n, then the resolution settled on the searched values and the fit refined there
        # (module docstring, "Resolution of a fit")
        ev_s = _Evaluator(doc, params, geoms, n_search, obs, ill, catalog, store, raw, source, target,
                          texture_tolerance)
        evaluators.append(ev_s)
        z_begin = solve(ev_s, z0, f"search (n = {n_search}) ")[0]
        rec_s = recipe_from_doc(substitute(doc, params, to_p(z_begin)), source, catalog)
        n = settle_node_count(rec_s, None, catalog, store, raw, log)
        log(f"searched at n = {n_search}: " + ", ".join(f"{p.name} = {v:.6g}" for p, v in zip(params, to_p(z_begin)))
            + f"; resolution at these values: n = {n}; refining there")
    ev = (evaluators[0] if evaluators and evaluators[0].n == n else
          _Evaluator(doc, params, geoms, n, obs, ill, catalog, store, raw, source, target, texture_tolerance))
    if ev not in evaluators:
        evaluators.append(ev)
    lab_start = ev.lab(to_p(z0)).copy()
    z_fit, nfev, status, message = solve(ev, z_begin)
    p_fit = to_p(z_fit)
    pred = ev.prediction(p_fit)
    lab_fit = ev.lab(p_fit)
    # sensitivities d Lab / dp at the solution (natural units)
    h = _fd_steps(params, z_fit, lb, ub)
    sens = np.empty((G, 3, len(params)))
    tex_fit, sparkle = ev.texture(p_fit)
    tex_val = np.array([r["predicted"] for r in tex_fit], float)
    tsens = np.empty((tex_val.size, len(params)))
    for j, p in enumerate(params):
        zj = z_fit.copy()
        zj[j] += h[j]
        pj = to_p(zj)
        sens[:, :, j] = (ev.lab(pj) - lab_fit) / (pj[j] - p_fit[j])
        tsens[:, j] = (np.array([r["predicted"] for r in ev.texture(pj)[0]], float) - tex_val) / (pj[j] - p_fit[j])
    # a parameter that moves neither L*a*b* (by 1e-6 for +1 %) nor a texture index (by 1e-6 of its tolerance)
    tex_tol = np.array([r["tolerance"] for r in tex_fit], float)
    undetermined = [p.name for j, p in enumerate(params)
                    if np.max(np.abs(sens[:, :, j])) * abs(p_fit[j]) / 100.0 < 1e-6
                    and np.all(np.abs(tsens[:, j]) * abs(p_fit[j]) / 100.0 < 1e-6 * tex_tol)]
    de_fit = delta_E_2000(lab_t, lab_fit)
    calls, secs = sum(e.calls for e in evaluators), sum(e.seconds for e in evaluators)
    log(f"done: {message.strip()} after {len(history)} iteration(s); max dE00 {de_fit.max():.3f}; "
        f"{calls} compose calls, {secs / max(calls, 1):.2f} s per call")
    values_out = np.array([float(f"{v:.6g}") for v in p_fit])
    tol = scheme.evaluate(geoms, lab_t, lab_fit)
    span = ub - lb
    at_bound = [(p.name, "lower", p.lo) if z - a <= BOUND_FRACTION * d else (p.name, "upper", p.hi)
                for p, z, a, b, d in zip(params, z_fit, lb, ub, span)
                if z - a <= BOUND_FRACTION * d or b - z <= BOUND_FRACTION * d]
    res = MatchResult(
        params=params, start=to_p(z0), values=p_fit, geometries=geoms, weights=w, lab_target=lab_t,
        lab_start=lab_start, lab_fit=lab_fit, de_start=delta_E_2000(lab_t, lab_start), de_fit=de_fit,
        sensitivities=sens, fitted_doc=substitute(doc, params, values_out), prediction=pred, n=n,
        observer=obs, illuminant=ill, n_compose=sum(e.calls for e in evaluators),
        compose_s=sum(e.seconds for e in evaluators), iterations=len(history),
        nfev=nfev, status=status, message=message, history=history, tolerance=tol, at_bound=at_bound,
        texture_start=ev.texture(to_p(z0))[0], texture_fit=tex_fit, texture_sensitivities=tsens,
        texture_tolerance=float(texture_tolerance), sparkle=sparkle, undetermined=undetermined)
    log(res.outcome)
    return res


def format_match(res: MatchResult) -> str:
    """The text ``flakedb match`` prints: per-geometry ΔE00 before and after, values, sensitivities."""
    lines = [f"fit ({res.observer}° / {res.illuminant}, n = {res.n}): {res.message.strip()}",
             f"{'parameter':<48} {'start':>11} {'fitted':>11} {'bounds':>22}"]
    for p, s, v in zip(res.params, res.start, res.values):
        lines.append(f"{p.name:<48} {s:11.5g} {v:11.5g} {f'[{p.lo:g}, {p.hi:g}]':>22}")
    tol = res.tolerance
    lines.append(f"{'illum':>6} {'aspec':>6} {'dE00 start':>11} {'dE00 fit':>9}"
                 + (f" {tol['formula'] + ' fit':>12}" if tol and "formula" in tol else "")
                 + "   L*a*b* C* h° target -> fitted; shade of the fit")
    for i, (g, d0, d1, lt, lf) in enumerate(zip(res.geometries, res.de_start, res.de_fit, res.lab_target, res.lab_fit)):
        ct, cf = lch(lt), lch(lf)
        lines.append(f"{geometry_cells(g)} {d0:11.3f} {d1:9.3f}"
                     + (f" {tol['value'][i]:12.3f}" if tol and "formula" in tol else "")
                     + f"   ({lt[0]:6.2f} {lt[1]:6.2f} {lt[2]:6.2f} {ct[1]:6.2f} {ct[2]:5.1f}) -> "
                     f"({lf[0]:6.2f} {lf[1]:6.2f} {lf[2]:6.2f} {cf[1]:6.2f} {cf[2]:5.1f}); {shade_words(lt, lf)[0]}")
    lines.append("sensitivities at the fit: d(L*, a*, b*) for a +1 % change of each parameter "
                 "(= p * dLab/dp / 100)")
    for j, (p, v) in enumerate(zip(res.params, res.values)):
        lines.append(f"  {p.name}:")
        for g, s in zip(res.geometries, res.sensitivities[:, :, j]):
            d = s * v / 100.0
            lines.append(f"    {geometry_cells(g)}  dL* {d[0]:+8.4f}  da* {d[1]:+8.4f}  db* {d[2]:+8.4f}")
    if res.texture_fit:
        lines.append(f"texture ({res.texture_tolerance:.0%} tolerance, or the index's floor; start -> fit):")
        for r0, r in zip(res.texture_start, res.texture_fit):
            lines.append(f"  {r['index']:<22} start {r0['predicted']:10.4g}  fit {r['predicted']:10.4g}  target "
                         f"{r['target']:10.4g}  difference {r['difference']:+10.4g}  tolerance {r['tolerance']:8.3g}  "
                         f"{'yes' if r['passed'] else 'NO'}")
        lines.append("  sensitivities: change of each index for a +1 % change of each parameter")
        for j, (p, v) in enumerate(zip(res.params, res.values)):
            lines.append(f"    {p.name}: " + ", ".join(f"{r['index']} {s * v / 100.0:+.4g}"
                                                      for r, s in zip(res.texture_fit, res.texture_sensitivities[:, j])))
        if res.sparkle is False:
            lines.append("  " + format_texture_rows([], sparkle=False)[-1])
    lines.append(f"compose calls: {res.n_compose} ({res.compose_s_per_call:.2f} s per call, "
                 f"{res.compose_s:.1f} s in total), {res.iterations} iteration(s)")
    if res.tolerance is not None:
        lines.append(res.outcome)
    return "\n".join(lines)


def match_report(res: MatchResult) -> dict:
    """A JSON-able record of a match."""
    return {
        "observer": res.observer, "illuminant": res.illuminant, "n": res.n,
        "parameters": [{"path": p.name, "bounds": [p.lo, p.hi], "scale": "log" if p.log else "linear",
                        "start": float(s), "fitted": float(v)} for p, s, v in zip(res.params, res.start, res.values)],
        "geometries": [{"illumination_deg": float(g[0]), "aspecular_deg": float(g[1]),
                        "azimuth_deg": float(g[2]) if len(g) > 2 else 0.0, "weight": float(wt),
                        "lab_target": lt.tolist(), "lab_start": ls.tolist(), "lab_fit": lf.tolist(),
                        "dE00_start": float(d0), "dE00_fit": float(d1),
                        "LCh_target": lch(lt).tolist(), "LCh_fit": lch(lf).tolist(),
                        "shade_fit": shade_words(lt, lf)[0],
                        "dE_fit": None if res.tolerance is None else float(res.tolerance["value"][i]),
                        "dLab_dp": {p.name: res.sensitivities[i, :, j].tolist() for j, p in enumerate(res.params)}}
                       for i, (g, wt, lt, ls, lf, d0, d1) in enumerate(zip(res.geometries, res.weights, res.lab_target,
                                                                             res.lab_start, res.lab_fit, res.de_start,
                                                                             res.de_fit))],
        "compose_calls": res.n_compose, "compose_seconds": res.compose_s, "iterations": res.iterations,
        "nfev": res.nfev, "status": res.status, "message": res.message, "history": res.history,
        "reached": res.reached, "outcome": res.outcome if res.tolerance is not None else None,
        "tolerance": None if res.tolerance is None else res.tolerance["scheme"],
        "formula": None if res.tolerance is None else res.tolerance.get("formula"),
        "passed": None if res.tolerance is None else [bool(v) for v in res.tolerance["passed"]],
        "at_bound": [{"path": n, "side": side, "bound": v} for n, side, v in res.at_bound],
        "undetermined": list(res.undetermined),
        "texture": None if not res.texture_fit else {
            "tolerance_relative": res.texture_tolerance, "sparkle": res.sparkle, "passed": res.texture_passed,
            "indices": [dict(r, start=r0["predicted"],
                             d_dp={p.name: float(res.texture_sensitivities[k, j]) for j, p in enumerate(res.params)})
                        for k, (r0, r) in enumerate(zip(res.texture_start, res.texture_fit))]},
    }
