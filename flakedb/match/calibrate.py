"""Calibrating a catalogue species from measured panels of known recipes (docs/calibration.md).

A formulation system is set up per colourant from a *ladder*: drawdowns of known recipes, the
colourant alone (masstone) and let down with white in steps, each measured at the multi-angle
geometries.  :func:`calibrate` fits the species' free optical parameters so that flakedb's
predictions of every panel match the measurements, and :func:`calibrated_entry` writes the result
as a catalogue entry that recipes use like any other species (``--catalog`` with the user catalogue
:func:`write_user_catalog` writes).

Free parameters (fitted variables z, all 0 at the catalogue's values)
---------------------------------------------------------------------
* **pigment**: a smooth spectral factor on the material's extinction coefficient,
  k(λ) → k(λ) · exp(Σ_{j=0}^{D} a_j P_j(x)), x = 2 (λ − 380 nm) / 400 nm − 1, P_j the Legendre
  polynomials (D = :data:`ABSORPTION_DEGREE` by default; bounds |a_j| ≤ 3, a factor e³ ≈ 20), and
  its size, d → d · e^s (|s| ≤ ln 3).  Size is the scattering parameter: at a fixed volume fraction
  the Mie scattering per volume follows the particle size, while the absorption factor moves K.
  A masstone alone fixes only K/S (Kubelka–Munk's R∞); the let-downs with white, whose scattering
  is the white's, separate K from S (docs/calibration.md, "Experimental design").
  Written as ``absorption_factor`` (sampled every 10 nm, 380–780 nm; times any factor the base
  entry already had) and ``median_diameter_um``.
* **interference_flake**: the outer coating film's thickness t → t · e^s (|s| ≤ ln 1.5) and the
  orientation α → α · e^u (|u| ≤ ln 4).
* **mirror_flake**: a constant albedo a → a · e^s (kept ≤ 1) and the orientation α → α · e^u.

The fit
-------
Residuals over every panel and geometry: spectral reflectance factors when the target has them
(100 (R_pred − R_target) per band, the prediction linearly interpolated onto the target's grid,
which it must cover), else the three CIEDE2000 components (:func:`flakedb.colour.tolerance.ciede2000_residuals`).
Bounded trust-region least squares (scipy ``least_squares(method="trf")``), forward-difference
Jacobian (step :data:`FD_STEP` in z), one compose per panel per evaluation (:func:`flakedb.match.fit.predict`).
A pigment's absorption columns come from one step: the k-factor acts band by band and the bands of a solve
are independent, so the step of a_0 (ln k raised by h in every band) gives ∂R_λ/∂ln k(λ) for every band, and
column j is ∂ln k(λ)/∂a_j times it (:func:`band_chained_columns`; spectral panels; the chain rule of
:mod:`flakedb.match.tinter`): a Jacobian costs two composes per panel whatever the degree;
the other species' optics and projections (and the calibrated species' optics across its panels) are computed once per
fit (:mod:`flakedb.rt.common.reuse`, docs/fit-speed.md).
Standard errors: the Gauss–Newton covariance s² (JᵀJ)⁻¹ at the solution with the residual variance
s² = Σ r² / (m − p) (m residuals, p parameters), the usual estimate when the measurement noise is
not known beforehand; it assumes independent residuals of equal variance.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from numpy.polynomial import legendre
from scipy.optimize import least_squares

from flakedb.atomic import atomic_write_text
from flakedb.colour.settings import for_target
from flakedb.colour.tolerance import ciede2000_residuals, delta_E_2000
from flakedb.match.cxf import load_target
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.match.targets import Target, TargetError
from flakedb.paint.catalog import CatalogError, get_species, species_name_problem, validate_catalog
from flakedb.paint.checks import YamlFileError, load_yaml_file, value_problems
from flakedb.paint.recipe import RecipeError
from flakedb.paint.species import absorption_factor
from flakedb.solve.pipeline import settle_node_count
from flakedb.rt.common.reuse import reuse_per_call

#: Degree D of the Legendre series of ln(absorption factor) (D + 1 coefficients).
ABSORPTION_DEGREE = 2
#: The wavelength span the Legendre variable x ∈ [−1, 1] covers, and the written factor's samples (nm).
FACTOR_RANGE_NM = (380.0, 780.0)
FACTOR_STEP_NM = 10.0
#: Forward-difference step in the fitted variables.
FD_STEP = 1e-3
#: Solver stops: relative change of Σ r² and of z below these (an instrument's noise sets the floor
#: of Σ r² long before; smaller values only add iterations that move z by less than its standard error).
FTOL, XTOL = 1e-8, 1e-6


@dataclass
class Panel:
    """One measured panel: a recipe document (naming the species) and its target."""

    name: str
    recipe_doc: dict
    target: Target
    #: the files it was read from (recipe, target), for the command's output plan
    paths: tuple = ()


@dataclass
class CalParam:
    name: str
    lo: float
    hi: float
    description: str


def free_parameters(entry, free=None, degree=ABSORPTION_DEGREE) -> list:
    """The fitted variables of a species of this kind (module docstring); ``free``: a subset of the
    groups ("absorption", "size" for a pigment; "thickness", "alpha" for an interference flake;
    "albedo", "alpha" for a mirror flake), default all."""
    kind = entry["kind"]
    groups = {"pigment": ("absorption", "size"), "interference_flake": ("thickness", "alpha"),
              "mirror_flake": ("albedo", "alpha")}[kind]
    chosen = groups if free is None else tuple(free)
    bad = [g for g in chosen if g not in groups]
    if bad:
        raise ValueError(f"free parameter group(s) {bad} do not apply to a {kind}; use {', '.join(groups)}")
    out = []
    for g in chosen:
        if g == "absorption":
            out += [CalParam(f"absorption_a{j}", -3.0, 3.0, f"Legendre coefficient {j} of ln k-factor")
                    for j in range(degree + 1)]
        elif g == "size":
            out.append(CalParam("size_ln", -math.log(3.0), math.log(3.0), "ln(d / d_catalogue)"))
        elif g == "thickness":
            out.append(CalParam("thickness_ln", -math.log(1.5), math.log(1.5), "ln(t / t_catalogue), outer coating"))
        elif g == "alpha":
            out.append(CalParam("alpha_ln", -math.log(4.0), math.log(4.0), "ln(α / α_catalogue)"))
        elif g == "albedo":
            a0 = float(entry["albedo"]["value"]) if "value" in entry["albedo"] and not isinstance(
                entry["albedo"]["value"], list) else None
            if a0 is None:
                raise ValueError("albedo calibration needs a constant catalogue albedo")
            out.append(CalParam("albedo_ln", math.log(0.02 / a0), math.log(1.0 / a0), "ln(a / a_catalogue)"))
    return out


def factor_grid() -> np.ndarray:
    lo, hi = FACTOR_RANGE_NM
    return np.arange(lo, hi + 0.5 * FACTOR_STEP_NM, FACTOR_STEP_NM)


def ln_absorption_factor(coeffs, wavelength_nm) -> np.ndarray:
    """ln of the calibrated k-factor, Σ a_j P_j(x) (module docstring), at ``wavelength_nm``.

    No coefficients leave the absorption as it is (factor 1); a_0 alone scales it evenly:

    >>> ln_absorption_factor([0.0], [400.0, 550.0]).tolist(), ln_absorption_factor([0.5], [400.0, 700.0]).tolist()
    ([0.0, 0.0], [0.5, 0.5])
    """
    lo, hi = FACTOR_RANGE_NM
    x = 2.0 * (np.asarray(wavelength_nm, float) - lo) / (hi - lo) - 1.0
    return legendre.legval(x, np.asarray(coeffs, float))


def calibrated_entry(entry, params, z, source="flakedb calibrate") -> dict:
    """A new catalogue entry: ``entry`` with the fitted variables ``z`` applied (module docstring)."""
    e = copy.deepcopy(entry)
    val = {p.name: float(v) for p, v in zip(params, z)}
    coeffs = [val[k] for k in sorted(val) if k.startswith("absorption_a")]
    if coeffs:
        wl = factor_grid()
        f = np.exp(ln_absorption_factor(coeffs, wl))
        if "absorption_factor" in entry:
            f = f * absorption_factor(entry["absorption_factor"], wl)
        e["absorption_factor"] = {"wavelength_nm": wl.tolist(), "value": [float(f"{v:.6g}") for v in f],
                                  "source": f"{source}: exp(Legendre series {', '.join(f'{c:.5g}' for c in coeffs)})"}
    if "size_ln" in val:
        d = float(entry["median_diameter_um"]["value"]) * math.exp(val["size_ln"])
        e["median_diameter_um"] = {"value": float(f"{d:.6g}"), "source": f"{source}: fitted (catalogue "
                                   f"{entry['median_diameter_um']['value']:g} µm)"}
    if "thickness_ln" in val:
        film = e["coating"][0]
        t = float(film["thickness_nm"]["value"]) * math.exp(val["thickness_ln"])
        film["thickness_nm"] = {"value": float(f"{t:.6g}"), "source": f"{source}: fitted"}
        total_nm = 2 * sum(f["thickness_nm"]["value"] for f in e["coating"]) + e["substrate"]["thickness_nm"]["value"]
        e["thickness_um"] = {"value": total_nm / 1000.0, "source": "total of the film stack"}
    if "alpha_ln" in val:
        a = float(entry["orientation_alpha"]["value"]) * math.exp(val["alpha_ln"])
        e["orientation_alpha"] = {"value": float(f"{a:.6g}"), "source": f"{source}: fitted"}
    if "albedo_ln" in val:
        a = min(1.0, float(entry["albedo"]["value"]) * math.exp(val["albedo_ln"]))
        e["albedo"] = {"value": float(f"{a:.6g}"), "source": f"{source}: fitted"}
    e["description"] = f"{entry['description']} (calibrated)"
    return e


#: The absorption column whose step the others are chained from (P_0 = 1: ln k raised by the step in every band).
LEAD_ABSORPTION = "absorption_a0"


def band_chained_columns(params, entry, z, predictions) -> dict:
    """Which Jacobian columns follow from the lead absorption step (module docstring, "The fit"), with the
    weights that give them: ``{column: [w per panel, (C,)]}``, w_j(λ) = ∂ln k(λ)/∂a_j = interp(F P_j) / interp(F)
    (F the k-factor on its 10 nm samples, interpolated onto each panel's bands as compose does), so that the
    column's change of reflectance is w_j(λ) times the lead step's, band by band.  Empty where the chain rule
    does not hold: a species other than a pigment, no absorption parameters, or a panel not in spectral mode
    (an RGB channel mixes bands).

    >>> ps = free_parameters({"kind": "pigment"}, ["absorption"], degree=1)
    >>> w = band_chained_columns(ps, {"kind": "pigment"}, [0.0, 0.0], [_Bands([380.0, 580.0, 780.0])])
    >>> list(w), w[1][0].round(12).tolist()        # a1's weight: P_1(x) = x, −1 … 1 over 380–780 nm
    ([1], [-1.0, 0.0, 1.0])
    """
    names = [p.name for p in params]
    if entry["kind"] != "pigment" or LEAD_ABSORPTION not in names:
        return {}
    if any(pr.mode != "spectral" for pr in predictions):
        return {}
    val = {p.name: float(v) for p, v in zip(params, z)}
    order = [k for k in sorted(val) if k.startswith("absorption_a")]  # the coefficient order of calibrated_entry
    grid = factor_grid()
    f = np.exp(ln_absorption_factor([val[k] for k in order], grid))
    if "absorption_factor" in entry:
        f = f * absorption_factor(entry["absorption_factor"], grid)
    lo, hi = FACTOR_RANGE_NM
    x = 2.0 * (grid - lo) / (hi - lo) - 1.0
    out = {}
    for j, name in enumerate(names):
        if name in order and name != LEAD_ABSORPTION:
            fp = f * legendre.legval(x, np.eye(len(order))[order.index(name)])
            out[j] = [np.interp(pr.wavelength_nm, grid, fp) / np.interp(pr.wavelength_nm, grid, f)
                      for pr in predictions]
    return out


@dataclass
class _Bands:  # a prediction's bands only (the doctest above)
    wavelength_nm: list
    mode: str = "spectral"


@dataclass
class CalibrationResult:
    species: str
    params: list
    z: np.ndarray
    stderr: np.ndarray
    entry: dict
    panels: list
    de_start: list           # per panel (G,) ΔE00 at the catalogue's values
    de_fit: list             # per panel (G,) at the fit
    rms_residual: float
    n_compose: int
    nfev: int
    message: str
    history: list = field(default_factory=list)


def _catalog_with(catalog, species, entry) -> dict:
    """``catalog`` with ``species``'s entry replaced (the rest shared: a recipe check copies what it uses)."""
    return {**catalog, "particles": {**catalog["particles"], species: entry}}


def _residuals(pred, target, lab_pred, cs):
    if target.spectral:
        wl_t = target.wavelength_nm
        wl_p = pred.wavelength_nm
        if pred.mode != "spectral" or wl_t[0] < wl_p[0] - 1e-9 or wl_t[-1] > wl_p[-1] + 1e-9:
            raise ValueError(f"{target.source}: spectral target on {wl_t[0]:g}-{wl_t[-1]:g} nm needs a spectral-mode "
                             f"recipe covering it")
        R = np.stack([np.interp(wl_t, wl_p, r) for r in pred.rf])
        return 100.0 * (R - target.reflectance)
    return ciede2000_residuals(target.lab_under(cs.observer, cs.illuminant), lab_pred)


@reuse_per_call
def calibrate(species, panels, catalog, free=None, degree=ABSORPTION_DEGREE, n=None, log=None,
              max_nfev=40, band_jacobian=True) -> CalibrationResult:
    """Fit ``species``'s free parameters (module docstring) to ``panels`` (a list of :class:`Panel`).

    ``band_jacobian``: the absorption columns beyond the first from the first's step, band by band
    (:func:`band_chained_columns`); False: a compose per column (the path before, for the benchmark)."""
    log = log or (lambda s: None)
    if not panels:
        raise ValueError("calibrate: no panels")
    base = copy.deepcopy(get_species(species, catalog))
    params = free_parameters(base, free, degree)
    for p in panels:
        rec = recipe_from_doc(p.recipe_doc, p.name, catalog)  # valid before any computation (and before its layers
        uses = [c for c in rec.doc.get("layers", [])  # are walked: a list of lists is refused, not a crash)
                for pt in ((c.get("basecoat") or {}).get("particles") or [] if isinstance(c, dict) else [])
                if isinstance(pt, dict) and pt.get("species") == species]
        if not uses:
            raise ValueError(f"panel {p.name}: its recipe does not use species {species!r}")
    # one n per panel for every evaluation (auto checked and refined once, at the base entry, as compose would)
    n_panel = [settle_node_count(recipe_from_doc(p.recipe_doc, p.name, catalog), n, catalog) for p in panels]
    calls = [0]
    cache = {}

    def evaluate(z):
        key = tuple(float(v) for v in z)
        if key not in cache:
            cat = _catalog_with(catalog, species, calibrated_entry(base, params, z))
            out = []
            for p, n_p in zip(panels, n_panel):  # a recipe holds its species' entries: parse it against the modified catalogue
                pred = predict(recipe_from_doc(p.recipe_doc, p.name, cat), p.target.geometries, n_p, cat)
                calls[0] += 1
                cs = for_target(pred.mode, p.target)  # the target's own conditions (no caller's choice here)
                out.append((pred, pred.lab(cs.observer, cs.illuminant), cs))
            cache[key] = out
        return cache[key]

    def resid(z):
        return np.concatenate([_residuals(pr, p.target, lab, cs).ravel()
                               for p, (pr, lab, cs) in zip(panels, evaluate(z))])

    def de(z):
        return [delta_E_2000(p.target.lab_under(cs.observer, cs.illuminant), lab)
                for p, (_, lab, cs) in zip(panels, evaluate(z))]

    history = []

    jacobians = {}

    def jac(z):
        r0 = resid(z)
        key = tuple(float(v) for v in z)
        if key not in jacobians:  # the solver's last Jacobian is at its solution: the standard errors' one
            jacobians[key] = jacobian(z, r0)
        d = np.concatenate(de(z))
        history.append({"z": z.tolist(), "cost": float(r0 @ r0), "max_dE00": float(d.max())})
        log(f"iteration {len(history) - 1}: sum r^2 = {float(r0 @ r0):.4g}, max dE00 = {d.max():.3f}; "
            + ", ".join(f"{p.name} = {v:+.4f}" for p, v in zip(params, z)) + f"  [{calls[0]} compose calls]")
        return jacobians[key].copy()

    def jacobian(z, r0):
        J = np.empty((r0.size, len(params)))
        chained = band_chained_columns(params, base, z, [pr for pr, _, _ in evaluate(z)]) if band_jacobian else {}
        for j, prm in enumerate(params):
            if j in chained:
                continue  # from the lead step below (the chain rule through the bands)
            h = FD_STEP if z[j] + FD_STEP <= prm.hi else -FD_STEP
            zj = z.copy()
            zj[j] += h
            J[:, j] = (resid(zj) - r0) / h
            if prm.name == LEAD_ABSORPTION and chained:
                for k, weights in chained.items():
                    J[:, k] = (chained_residuals(evaluate(z), evaluate(zj), weights) - r0) / h
        return J

    def chained_residuals(at_z, at_step, weights):
        """The residuals with each panel's reflectance moved by ``weights`` (per panel, (C,)) times the lead
        step's change, band by band."""
        out = []
        for p, (pr0, _, cs), (pr1, _, _), w in zip(panels, at_z, at_step, weights):
            pr = dataclasses.replace(pr0, rf=pr0.rf + w[None, :] * (pr1.rf - pr0.rf))
            out.append(_residuals(pr, p.target, pr.lab(cs.observer, cs.illuminant), cs).ravel())
        return np.concatenate(out)

    z0 = np.zeros(len(params))
    lb = np.array([p.lo for p in params])
    ub = np.array([p.hi for p in params])
    de0 = de(z0)
    sol = least_squares(resid, z0, jac=jac, bounds=(lb, ub), method="trf", x_scale="jac", ftol=FTOL, xtol=XTOL,
                        gtol=1e-10, max_nfev=max_nfev)
    z = sol.x
    r = resid(z)
    J = jac(z)
    dof = max(r.size - len(params), 1)
    s2 = float(r @ r) / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
        stderr = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        stderr = np.full(len(params), np.inf)
    entry = calibrated_entry(base, params, z, source=f"flakedb calibrate from {len(panels)} panel(s)")
    d1 = de(z)
    log(f"done: {str(sol.message).strip()}; max dE00 {np.concatenate(d1).max():.3f} (start "
        f"{np.concatenate(de0).max():.3f}); {calls[0]} compose calls")
    return CalibrationResult(species=species, params=params, z=z, stderr=stderr, entry=entry, panels=panels,
                             de_start=de0, de_fit=d1, rms_residual=math.sqrt(float(r @ r) / r.size),
                             n_compose=calls[0], nfev=int(sol.nfev), message=str(sol.message), history=history)


# ----------------------------------------------------------------------------------------------
# Files: the ladder manifest and the user catalogue
# ----------------------------------------------------------------------------------------------


#: Largest ladder manifest read [bytes] (a list of panels: a few kB).
MAX_LADDER_BYTES = 1_000_000
#: Most panels of a ladder (each is a compose per fit evaluation; a ladder is a masstone and a few let-downs).
MAX_PANELS = 200


def read_ladder(path):
    """``(species, name, free, panels)`` from a ladder manifest YAML (docs/calibration.md)::

        species: cadmium-yellow          # the catalogue species the panels use
        name: cadmium-yellow-lab         # the calibrated species' name in the user catalogue
        free: [absorption, size]         # optional (default: all of the kind's groups)
        panels:
          - {recipe: masstone.yaml, target: masstone.csv}
          - {recipe: letdown-1-4.yaml, target: ladder.cxf, cxf_object: LD-1:4}

    Paths are relative to the manifest.  The manifest and every panel recipe are read by the one strict
    loader (:func:`flakedb.paint.checks.load_yaml_file`: a regular file only, at most a limit of bytes,
    duplicate keys, alias bombs and unknown tags refused); ``name`` is checked as a species name here, before
    any work.  Raises ValueError naming the file and the field.
    """
    p = Path(path)
    try:
        _, doc = load_yaml_file(p, "ladder manifest", MAX_LADDER_BYTES)
    except YamlFileError as exc:
        raise ValueError(str(exc)) from None
    if not isinstance(doc, dict):
        raise ValueError(f"{p}: a ladder manifest is a YAML mapping (species, name, panels)")
    problems = value_problems(doc)
    if problems:
        raise ValueError(f"{p}: {problems[0]}")
    extra = set(doc) - {"species", "name", "free", "panels", "description"}
    if extra:
        raise ValueError(f"{p}: unknown key(s) {_short(sorted(map(str, extra)))} (allowed: species, name, free, "
                         f"panels, description)")
    for k in ("species", "name", "panels"):
        if k not in doc:
            raise ValueError(f"{p}: '{k}' is missing")
    for k in ("species", "name"):
        if not isinstance(doc[k], str):
            raise ValueError(f"{p}: {k}: a species name (text), not {type(doc[k]).__name__}")
    problem = species_name_problem(doc["name"])
    if problem:
        raise ValueError(f"{p}: name: {problem}; it names the calibrated species in --out-catalog")
    free = doc.get("free")
    if free is not None and (not isinstance(free, list) or not all(isinstance(g, str) for g in free)):
        raise ValueError(f"{p}: free: a list of parameter groups (e.g. [absorption, size])")
    if not isinstance(doc["panels"], list) or not doc["panels"]:
        raise ValueError(f"{p}: panels must be a non-empty list of {{recipe: R.yaml, target: T.csv}}")
    if len(doc["panels"]) > MAX_PANELS:
        raise ValueError(f"{p}: panels: {len(doc['panels']):,} panels; the limit is {MAX_PANELS} (each is a compose "
                         f"in every fit evaluation)")
    panels = []
    for i, e in enumerate(doc["panels"]):
        where = f"{p}: panels[{i}]"
        if not isinstance(e, dict) or "recipe" not in e or "target" not in e:
            raise ValueError(f"{where}: give recipe: R.yaml and target: T.csv (or .cxf)")
        unknown = set(e) - {"recipe", "target", "cxf_object", "name"}
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {_short(sorted(map(str, unknown)))} (allowed: recipe, target, "
                             f"cxf_object, name)")
        for k in ("recipe", "target"):
            if not isinstance(e[k], str) or not e[k]:
                raise ValueError(f"{where}.{k}: a file path (text)")
        rp = p.parent / e["recipe"]
        try:
            _, rdoc = load_yaml_file(rp, "recipe")
        except YamlFileError as exc:
            raise ValueError(f"{where}.recipe: {exc}") from None
        if not isinstance(rdoc, dict):
            raise ValueError(f"{where}.recipe: {rp}: a recipe is a YAML mapping (flakedb, name, layers, ...), "
                             f"not {type(rdoc).__name__}")
        try:
            tgt = load_target(p.parent / e["target"], object_name=e.get("cxf_object"))
        except TargetError as exc:
            raise ValueError(f"{where}.target: {exc}") from None
        panels.append(Panel(name=_short(e.get("name") or rp.stem, 60), recipe_doc=rdoc, target=tgt,
                            paths=(rp, p.parent / e["target"])))
    return doc["species"], doc["name"], (None if free is None else list(free)), panels


def _short(text, limit=100) -> str:
    t = str(text)
    return t if len(t) <= limit else t[:limit - 3] + "..."


def write_user_catalog(path, base_catalog, name, entry, note="") -> str:
    """Write ``base_catalog`` plus ``name: entry`` to ``path`` (atomically), validated first."""
    atomic_write_text(Path(path), format_user_catalog(path, base_catalog, name, entry, note))
    return str(path)


def format_user_catalog(path, base_catalog, name, entry, note="") -> str:
    """The text of the user catalogue ``base_catalog`` plus ``name: entry``, validated (CatalogError naming
    ``path`` when the result is not a valid catalogue)."""
    cat = copy.deepcopy(base_catalog)
    if name in cat["particles"]:
        raise ValueError(f"a species named {name!r} is already in the base catalogue; choose another name")
    cat["particles"][name] = entry
    problems = validate_catalog(cat)
    if problems:
        raise CatalogError(f"{path}: the calibrated catalogue is invalid:\n  " + "\n  ".join(problems))
    text = ("# flakedb user catalogue: the base catalogue plus species calibrated by `flakedb calibrate`"
            + (f"\n# {note}" if note else "") + "\n" + yaml.safe_dump(cat, sort_keys=False, allow_unicode=True))
    return text


__all__ = ["ABSORPTION_DEGREE", "CalParam", "CalibrationResult", "Panel", "RecipeError", "calibrate",
           "calibrated_entry", "format_user_catalog", "free_parameters", "ln_absorption_factor", "read_ladder", "write_user_catalog"]
