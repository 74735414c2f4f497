"""Creating a tinter (a new colourant) from a user's drawdowns (docs/calibration.md, "Tinters from drawdowns").

Usage card::

    name, meta, seed, panels = read_tinter_ladder("ladder.yaml")        # manifest, recipes, spectral targets
    res = fit_tinter(name, panels, catalog, meta=meta, seed=seed)        # TinterResult; res.entry: the tinter
    write_user_catalog("user.yaml", catalog, name, res.entry)            # flakedb.match.calibrate's writer

A *tinter* is a catalogue species of kind ``tinter`` (schemas/catalog.schema.json): its absorption and
scattering per unit volume fraction, σ_a/φ and σ_s/φ [1/µm], tabulated in wavelength, and a
Henyey–Greenstein mean cosine g; :mod:`flakedb.paint.mapping` turns it into a
:class:`flakedb.rt.scattering.media.PhaseMedium` (σ = φ · σ/φ) like every species, so a recipe names it and it mixes
with catalogue pigments and flakes.

The model fitted (all smooth in wavelength, so that a ladder of a few panels determines it)
-----------------------------------------------------------------------------------------
    ln σ_a/φ (λ)  = Σ_{j=0}^{D} a_j P_j(x),    ln σ_s′/φ (λ) = Σ_{j=0}^{D} b_j P_j(x),    g,
    x = 2 (λ − λ_lo)/(λ_hi − λ_lo) − 1 over the panels' band range [λ_lo, λ_hi], P_j Legendre polynomials,
    σ_s′ = σ_s (1 − g) the reduced scattering (σ_s = σ_s′ / (1 − g)).

The reduced scattering is the parameter, not σ_s: a diffuse reflectance depends on σ_s (1 − g) almost
alone (:mod:`flakedb.optics.kubelka_munk`), so (b, g) are far less correlated than (ln σ_s, g); g is then
what the angular shape of the multi-angle readings adds.  Bounds: |a_j|, |b_j| ≤ :data:`COEFF_BOUND` for
j ≥ 1, a_0, b_0 within :data:`LN_LEVEL_BOUNDS`, g within :data:`G_BOUNDS`.

The fit
-------
Residuals 100 (R_pred − R_meas) per band, geometry and panel (spectral targets only: three CIELAB
numbers cannot separate K from S), the prediction linearly interpolated onto the target's bands.
Bounded trust-region least squares (scipy ``least_squares(method="trf")``) at degree D, from
:data:`DEFAULT_START` or from a seed (Kubelka–Munk data, :func:`seed_from_km`, its curves projected at
degree D); optional continuation stages of lower degree first (:data:`DEGREE_STEPS`).

Cheap derivatives: the bands of a solve are independent (one adding-doubling solve per channel), so
one solve with ln σ_a/φ raised by h in *every* band gives ∂R_λ/∂ln σ_a(λ) for every band λ at once;
the chain rule through the series, ∂R_λ/∂a_j = ∂R_λ/∂ln σ_a(λ) · P_j(x_λ), then gives every column.  A
Jacobian therefore costs three solves per panel (ln σ_a, ln σ_s′, g) whatever the degree, and nothing
but the tinter's medium is rebuilt: each panel's other species (the white's Mie optics, the primer) are
built once (:func:`flakedb.paint.mapping.with_media`).  The node count of each panel is fixed for the fit
(:func:`flakedb.solve.pipeline.settle_node_count`).  After the fit every panel is composed once more
through the ordinary path with the written entry (:func:`flakedb.match.fit.predict`): the ΔE00 reported
are those of the user catalogue, not of the fit's shortcut.

Standard errors: the Gauss–Newton covariance s² (JᵀJ)⁻¹ with s² = Σ r²/(m − p) (independent residuals
of equal variance), propagated to ln σ_a/φ(λ) and ln σ_s′/φ(λ) band by band (``res.ln_sigma_stderr``).
"""

from __future__ import annotations

import copy
import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.polynomial import legendre
from scipy.optimize import least_squares

from flakedb.bsdf.convert import stack_to_table
from flakedb.colour.settings import for_target
from flakedb.colour.tolerance import delta_E_2000
from flakedb.match.calibrate import Panel
from flakedb.match.cxf import load_target
from flakedb.match.fit import eval_geometries, predict, recipe_from_doc
from flakedb.match.targets import TargetError
from flakedb.optics.kubelka_munk import km_to_rt
from flakedb.paint.catalog import validate_catalog
from flakedb.paint.checks import YamlFileError, load_yaml_file
from flakedb.paint.mapping import build_paint, solve_paint, with_media
from flakedb.paint.components import tinter_medium
from flakedb.paint.recipe import CatalogParticle
from flakedb.process import available_threads
from flakedb.safeio import FileTooLargeError, read_text_limited
from flakedb.solve.pipeline import memory_budget_bytes, settle_node_count

#: Default Legendre degree D of ln σ_a/φ and of ln σ_s′/φ (D + 1 coefficients each).
TINTER_DEGREE = 6
#: Degrees of continuation stages fitted before D, each started from the previous one's fit.  None by
#: default: on four synthetic tinters (docs/calibration.md) a flat start at the full degree reached the
#: same fit in 156–204 solves, against 410–460 with stages (0, 2).
DEGREE_STEPS = ()
#: Bounds of a_0, b_0 (the mean level of ln σ/φ, σ in 1/µm): 1e-4 … 1e4 per µm per unit volume fraction.
LN_LEVEL_BOUNDS = (math.log(1e-4), math.log(1e4))
#: Bound of |a_j|, |b_j|, j ≥ 1 (a factor e^12 across the range: more than any pigment's contrast).
COEFF_BOUND = 12.0
#: Bounds of the Henyey–Greenstein g (the catalogue schema allows −0.9 … 0.95).
G_BOUNDS = (-0.5, 0.9)
#: Start where no seed is given: σ_a/φ = σ_s′/φ = 1 /µm, g = 0.3 (a mid-range organic pigment).
DEFAULT_START = (0.0, 0.0, 0.3)
#: Derivative steps: in ln σ (all bands at once) and in g.
FD_STEP_LN, FD_STEP_G = 1e-4, 1e-4
#: Largest Kubelka–Munk CSV read [bytes].
MAX_KM_CSV_BYTES = 1_000_000
#: Step of the written tables (nm); the fitted range's ends are always samples.
TABLE_STEP_NM = 5.0
#: Solver stops of the last stage (as :mod:`flakedb.match.calibrate`), and of the continuation stages before
#: it (only a start for the next: a relative change of Σ r² below 1e-3 is enough).
FTOL, XTOL = 1e-8, 1e-6
STAGE_FTOL = 1e-3


def legendre_x(wavelength_nm, span_nm) -> np.ndarray:
    """x = 2 (λ − λ_lo)/(λ_hi − λ_lo) − 1 ∈ [−1, 1] over ``span_nm`` = (λ_lo, λ_hi).

    >>> legendre_x([400.0, 550.0, 700.0], (400.0, 700.0)).tolist()
    [-1.0, 0.0, 1.0]
    """
    lo, hi = span_nm
    return 2.0 * (np.asarray(wavelength_nm, float) - lo) / (hi - lo) - 1.0


def legendre_basis(wavelength_nm, span_nm, degree) -> np.ndarray:
    """P_j(x(λ)) (W, degree + 1)."""
    return legendre.legvander(legendre_x(wavelength_nm, span_nm), int(degree))


@dataclass
class TinterParams:
    """The fitted variables: Legendre coefficients of ln σ_a/φ and ln σ_s′/φ (1/µm) and g."""

    a: np.ndarray
    b: np.ndarray
    g: float

    @property
    def degree(self) -> int:
        return len(self.a) - 1

    def z(self) -> np.ndarray:
        return np.concatenate([self.a, self.b, [self.g]])

    @classmethod
    def from_z(cls, z, degree):
        z = np.asarray(z, float)
        return cls(z[:degree + 1].copy(), z[degree + 1:2 * degree + 2].copy(), float(z[-1]))

    def raised(self, degree):
        """The same curves with zero coefficients up to ``degree``."""
        pad = lambda c: np.concatenate([c, np.zeros(max(0, degree + 1 - len(c)))])[:degree + 1]  # noqa: E731
        return TinterParams(pad(self.a), pad(self.b), self.g)

    def coefficients(self, wavelength_nm, span_nm):
        """(σ_a/φ, σ_s/φ) (W,) each in 1/µm at ``wavelength_nm`` (module docstring)."""
        P = legendre_basis(wavelength_nm, span_nm, self.degree)
        return np.exp(P @ self.a), np.exp(P @ self.b) / (1.0 - self.g)


def params_from_curves(wavelength_nm, sigma_a_per_phi, sigma_s_per_phi, g, span_nm, degree) -> TinterParams:
    """The least-squares Legendre series of degree ``degree`` of ln σ_a/φ and ln σ_s′/φ = ln(σ_s/φ (1 − g))
    sampled at ``wavelength_nm``: how a seed (e.g. Kubelka–Munk data, :func:`seed_from_km`) starts the fit.

    Curves that are such series come back exactly:

    >>> p = TinterParams(np.array([0.5, -1.0]), np.array([0.2, 0.3]), 0.4)
    >>> wl = np.arange(400.0, 701.0, 20.0)
    >>> q = params_from_curves(wl, *p.coefficients(wl, (400.0, 700.0)), 0.4, (400.0, 700.0), 1)
    >>> np.round(q.a, 12).tolist(), np.round(q.b, 12).tolist(), q.g
    ([0.5, -1.0], [0.2, 0.3], 0.4)
    """
    P = legendre_basis(wavelength_nm, span_nm, degree)
    la = np.log(np.maximum(np.asarray(sigma_a_per_phi, float), 1e-6))
    lb = np.log(np.maximum(np.asarray(sigma_s_per_phi, float) * (1.0 - g), 1e-6))
    a = np.linalg.lstsq(P, la, rcond=None)[0]
    b = np.linalg.lstsq(P, lb, rcond=None)[0]
    return TinterParams(a, b, float(g))


def tinter_entry(params: TinterParams, span_nm, description, source, meta=None, step_nm=TABLE_STEP_NM) -> dict:
    """A catalogue entry of kind ``tinter`` (schemas/catalog.schema.json): the fitted curves tabulated every
    ``step_nm`` over ``span_nm`` (ends included), g, and ``meta``'s colour_index / density_g_cm3."""
    lo, hi = span_nm
    wl = np.unique(np.concatenate([np.arange(lo, hi, step_nm), [hi]]))
    sa, ss = params.coefficients(wl, span_nm)
    coeffs = lambda c: ", ".join(f"{v:.6g}" for v in c)  # noqa: E731
    e = {"kind": "tinter", "description": description, "source": source}
    meta = meta or {}
    if meta.get("colour_index"):
        e["colour_index"] = str(meta["colour_index"])
    if meta.get("density_g_cm3") is not None:
        e["density_g_cm3"] = {"value": float(meta["density_g_cm3"]), "source": "the ladder manifest (user)"}
    e["specific_absorption_per_um"] = {
        "wavelength_nm": [float(w) for w in wl], "value": [float(f"{v:.6g}") for v in sa],
        "source": f"{source}: exp(Legendre series {coeffs(params.a)} over {lo:g}-{hi:g} nm)"}
    e["specific_scattering_per_um"] = {
        "wavelength_nm": [float(w) for w in wl], "value": [float(f"{v:.6g}") for v in ss],
        "source": f"{source}: exp(Legendre series {coeffs(params.b)}) / (1 - g)"}
    e["asymmetry_g"] = {"value": float(f"{params.g:.6g}"), "source": f"{source}: fitted"}
    return e


# ----------------------------------------------------------------------------------------------
# Seeds from Kubelka–Munk data
# ----------------------------------------------------------------------------------------------


def read_km_csv(path):
    """(wavelength_nm, K, S) from a CSV with a header ``wavelength_nm,K,S`` (specific K and S: per unit
    volume fraction, in 1/µm).  Raises ValueError naming the line."""
    p = Path(path)
    try:  # a regular file, size-limited (flakedb.safeio), as every file a user names
        rows = list(csv.reader(read_text_limited(p, MAX_KM_CSV_BYTES).splitlines()))
    except FileNotFoundError:
        raise ValueError(f"{p}: no such file") from None
    except FileTooLargeError:
        raise ValueError(f"{p}: larger than {MAX_KM_CSV_BYTES:,} bytes (a K, S table is a few kB)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{p}: cannot read it as UTF-8 text ({exc})") from None
    if not rows or [c.strip() for c in rows[0]] != ["wavelength_nm", "K", "S"]:
        raise ValueError(f"{p}: the first line must be the header wavelength_nm,K,S (K and S per unit volume "
                         f"fraction, 1/µm)")
    out = []
    for i, r in enumerate(rows[1:], start=2):
        if not r or not "".join(r).strip():
            continue
        try:
            w, K, S = (float(c) for c in r)
        except ValueError:
            raise ValueError(f"{p}: line {i}: three numbers wavelength_nm,K,S expected, got {r!r}") from None
        if not (np.isfinite([w, K, S]).all() and w > 0 and K >= 0 and S >= 0):
            raise ValueError(f"{p}: line {i}: wavelength > 0 and K, S >= 0 (finite) required, got {r!r}")
        out.append((w, K, S))
    a = np.array(out, float).reshape(-1, 3)
    if a.shape[0] < 2 or np.any(np.diff(a[:, 0]) <= 0):
        raise ValueError(f"{p}: at least two rows with strictly increasing wavelength_nm are needed")
    return a[:, 0], a[:, 1], a[:, 2]


def seed_from_km(wavelength_nm, K, S, g):
    """(wavelength_nm, σ_a/φ, σ_s/φ, g) from specific KM K, S (1/µm per unit volume fraction) at a chosen
    g (:func:`flakedb.optics.kubelka_munk.km_to_rt`, Star et al. 1988)."""
    sa, ss = km_to_rt(K, S, g)
    return np.asarray(wavelength_nm, float), np.asarray(sa, float), np.asarray(ss, float), float(g)


def seed_entry(seed, description, source, meta=None) -> dict:
    """A tinter entry of a seed as it is (its own samples, no fit): published KM data used directly."""
    wl, sa, ss, g = seed
    e = {"kind": "tinter", "description": description, "source": source}
    meta = meta or {}
    if meta.get("colour_index"):
        e["colour_index"] = str(meta["colour_index"])
    if meta.get("density_g_cm3") is not None:
        e["density_g_cm3"] = {"value": float(meta["density_g_cm3"]), "source": "the ladder manifest (user)"}
    e["specific_absorption_per_um"] = {"wavelength_nm": [float(w) for w in wl], "value": [float(v) for v in sa],
                                       "source": f"{source}: sigma_a = K / 2 (Star et al. 1988)"}
    e["specific_scattering_per_um"] = {"wavelength_nm": [float(w) for w in wl], "value": [float(v) for v in ss],
                                       "source": f"{source}: sigma_s = (S + K / 8) 4 / (3 (1 - g)) (Star et al. 1988)"}
    e["asymmetry_g"] = {"value": float(g), "source": f"{source}: chosen (Kubelka-Munk data do not determine it)"}
    return e


# ----------------------------------------------------------------------------------------------
# The fast evaluator: each panel's paint built once, the tinter's medium swapped
# ----------------------------------------------------------------------------------------------


class _PanelModel:
    """One panel: its paint with the tinter at a placeholder, the tinter's particle paths and volume
    fractions, the node count, and the interpolation matrix from the recipe's bands to the target's."""

    def __init__(self, panel, name, catalog, n):
        recipe = recipe_from_doc(panel.recipe_doc, panel.name, catalog)
        if recipe.mode != "spectral":
            raise ValueError(f"panel {panel.name}: a tinter is fitted to spectra; set spectral.mode: spectral "
                             f"in its recipe")
        self.panel, self.recipe = panel, recipe
        self.uses = [(p.path, p.volume_fraction) for _, p in recipe.particles()
                     if isinstance(p, CatalogParticle) and p.species == name]
        if not self.uses:
            raise ValueError(f"panel {panel.name}: its recipe does not use the tinter {name!r} (name it as "
                             f"species: {name} in its particles)")
        self.n = settle_node_count(recipe, n, catalog)
        self.paint = build_paint(recipe, catalog)
        self.wl = np.asarray(recipe.wavelength_nm, float)
        t = panel.target
        if not t.spectral:
            raise ValueError(f"panel {panel.name}: target {t.source} has no spectra; a tinter needs spectral "
                             f"reflectance factors (R_… columns or CxF3 ReflectanceSpectrum)")
        wt = np.asarray(t.wavelength_nm, float)
        if wt[0] < self.wl[0] - 1e-9 or wt[-1] > self.wl[-1] + 1e-9:
            raise ValueError(f"panel {panel.name}: the target's spectrum {wt[0]:g}-{wt[-1]:g} nm is not inside the "
                             f"recipe's grid {self.wl[0]:g}-{self.wl[-1]:g} nm (widen spectral.range_nm)")
        eye = np.eye(self.wl.size)
        self.W = np.stack([np.interp(wt, self.wl, eye[b]) for b in range(self.wl.size)], axis=1)  # (T, B)
        self.target = np.asarray(t.reflectance, float)  # (G, T)
        self.geometries = np.asarray(t.geometries, float)

    def rf(self, sa, ss, g) -> np.ndarray:
        """Reflectance factors (G, B) at the recipe's bands with the tinter's σ_a/φ, σ_s/φ (B,) and g."""
        paint = with_media(self.paint, {path: tinter_medium(sa, ss, g, vf) for path, vf in self.uses})
        stack = solve_paint(paint, self.n, memory_budget_bytes=memory_budget_bytes(), threads=available_threads())
        table = stack_to_table(stack, paint.channels, paint.eta, None, paint.delta, {"recipe": self.recipe.name})
        return eval_geometries(table, self.geometries)

    def residual(self, rf) -> np.ndarray:
        """100 (R_pred − R_meas) (G, T) on the target's bands."""
        return 100.0 * (rf @ self.W.T - self.target)


@dataclass
class TinterResult:
    name: str
    params: TinterParams
    span_nm: tuple
    stderr: np.ndarray               # of z = (a, b, g)
    ln_sigma_stderr: dict            # {"wavelength_nm", "ln_sigma_a", "ln_sigma_s_reduced"} (W,) each
    entry: dict
    panels: list
    de_fit: list                     # per panel (G,): ΔE00 of the written entry, composed the ordinary way
    rms_residual: float              # in % reflectance (100 ΔR)
    n_solves: int
    nfev: int
    message: str
    history: list = field(default_factory=list)


def fit_tinter(name, panels, catalog, meta=None, seed=None, degree=TINTER_DEGREE, n=None, log=None,
               max_nfev=60, fix_g=None) -> TinterResult:
    """Fit a new tinter ``name`` to ``panels`` (:class:`flakedb.match.calibrate.Panel`, recipes naming
    ``name``) over ``catalog`` (module docstring).  ``seed``: (wavelength_nm, σ_a/φ, σ_s/φ, g) to start
    from (:func:`seed_from_km`), else :data:`DEFAULT_START`; ``fix_g``: hold g at this value."""
    log = log or (lambda s: None)
    if not panels:
        raise ValueError("fit_tinter: no panels")
    if name in catalog["particles"]:
        raise ValueError(f"a species named {name!r} is already in the base catalogue; choose another name")
    # the panels' band range is the fitted span (the series is not extrapolated beyond it)
    grids = []
    for p in panels:
        sp = (p.recipe_doc.get("spectral") or {}) if isinstance(p.recipe_doc, dict) else {}
        grids.append(sp.get("range_nm", [380.0, 780.0]))
    span = (float(min(g[0] for g in grids)), float(max(g[1] for g in grids)))
    if seed is not None:
        wl_s, sa_s, ss_s, g_s = seed
        if wl_s[0] > span[0] + 1e-9 or wl_s[-1] < span[1] - 1e-9:
            raise ValueError(f"the seed covers {wl_s[0]:g}-{wl_s[-1]:g} nm; the panels need {span[0]:g}-{span[1]:g} nm")
        # the seed's curves (linear in λ between its samples, as a catalogue table) inside the span, projected
        # at the full degree: a good seed needs no continuation stages
        wl_g = np.linspace(span[0], span[1], 61)
        start = params_from_curves(wl_g, np.interp(wl_g, wl_s, sa_s), np.interp(wl_g, wl_s, ss_s),
                                   g_s if fix_g is None else fix_g, span, degree)
    else:
        start = TinterParams(np.array([DEFAULT_START[0]]), np.array([DEFAULT_START[1]]),
                             DEFAULT_START[2] if fix_g is None else float(fix_g))
    cat = copy.deepcopy(catalog)
    cat["particles"][name] = tinter_entry(start, span, "provisional tinter (fit start)", "flakedb calibrate start")
    problems = validate_catalog(cat)
    if problems:
        raise ValueError("the provisional tinter is invalid: " + "; ".join(problems))
    models = [_PanelModel(p, name, cat, n) for p in panels]
    log(f"tinter {name}: {len(models)} panel(s), {sum(m.target.size for m in models)} readings, span "
        f"{span[0]:g}-{span[1]:g} nm, n = {sorted({m.n for m in models})}")
    solves = [0]
    cache = {}

    def rfs(sa_list, ss_list, g):
        out = []
        for m, sa, ss in zip(models, sa_list, ss_list):
            out.append(m.rf(sa, ss, g))
            solves[0] += 1
        return out

    def curves(par):
        """Per model: (ln σ_a/φ, ln σ_s′/φ) at its bands."""
        return [(legendre_basis(m.wl, span, par.degree) @ par.a, legendre_basis(m.wl, span, par.degree) @ par.b)
                for m in models]

    def state(z, D):
        key = (D,) + tuple(float(v) for v in z)
        if key not in cache:
            par = TinterParams.from_z(z, D) if fix_g is None else TinterParams.from_z(np.append(z, fix_g), D)
            c = curves(par)
            rf = rfs([np.exp(la) for la, _ in c], [np.exp(lb) / (1 - par.g) for _, lb in c], par.g)
            cache[key] = (par, c, rf)
        return cache[key]

    def resid(z, D):
        _, _, rf = state(z, D)
        return np.concatenate([m.residual(r).ravel() for m, r in zip(models, rf)])

    history = []

    def jac(z, D):
        par, c, rf0 = state(z, D)
        h = FD_STEP_LN
        ra = rfs([np.exp(la + h) for la, _ in c], [np.exp(lb) / (1 - par.g) for _, lb in c], par.g)
        rb = rfs([np.exp(la) for la, _ in c], [np.exp(lb + h) / (1 - par.g) for _, lb in c], par.g)
        blocks = []
        if fix_g is None:
            hg = FD_STEP_G if par.g + FD_STEP_G <= G_BOUNDS[1] else -FD_STEP_G
            g2 = par.g + hg
            rg = rfs([np.exp(la) for la, _ in c], [np.exp(lb) / (1 - g2) for _, lb in c], g2)
        for k, m in enumerate(models):
            P = legendre_basis(m.wl, span, D)  # (B, D + 1)
            da = (ra[k] - rf0[k]) / h  # (G, B): ∂R_b/∂ln σ_a(b), each band from its own channel
            db = (rb[k] - rf0[k]) / h
            Ja = 100.0 * np.einsum("tb,gb,bj->gtj", m.W, da, P).reshape(-1, D + 1)
            Jb = 100.0 * np.einsum("tb,gb,bj->gtj", m.W, db, P).reshape(-1, D + 1)
            cols = [Ja, Jb]
            if fix_g is None:
                cols.append(100.0 * (((rg[k] - rf0[k]) / hg) @ m.W.T).reshape(-1, 1))
            blocks.append(np.hstack(cols))
        J = np.vstack(blocks)
        r0 = resid(z, D)
        history.append({"degree": D, "z": [float(v) for v in z], "cost": float(r0 @ r0)})
        log(f"degree {D}, iteration {sum(1 for h_ in history if h_['degree'] == D) - 1}: rms residual "
            f"{math.sqrt(float(r0 @ r0) / r0.size):.4g} % reflectance, g = {par.g:.4f}  [{solves[0]} solves]")
        return J

    par = start
    degrees = ([d for d in DEGREE_STEPS if d < degree] if seed is None else []) + [int(degree)]
    sol = None
    for D in degrees:
        par = par.raised(D)
        z0 = par.z() if fix_g is None else par.z()[:-1]
        lb = [LN_LEVEL_BOUNDS[0]] + [-COEFF_BOUND] * D
        ub = [LN_LEVEL_BOUNDS[1]] + [COEFF_BOUND] * D
        lo = np.array(lb + lb + ([G_BOUNDS[0]] if fix_g is None else []))
        hi = np.array(ub + ub + ([G_BOUNDS[1]] if fix_g is None else []))
        z0 = np.clip(z0, lo + 1e-9, hi - 1e-9)
        last = D == degrees[-1]
        sol = least_squares(resid, z0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                            ftol=FTOL if last else STAGE_FTOL, xtol=XTOL, gtol=1e-12, max_nfev=max_nfev, args=(D,))
        par = TinterParams.from_z(sol.x if fix_g is None else np.append(sol.x, fix_g), D)
    D = degrees[-1]
    z = sol.x
    r = resid(z, D)
    J = jac(z, D)
    dof = max(r.size - z.size, 1)
    s2 = float(r @ r) / dof
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
        stderr = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        cov, stderr = None, np.full(z.size, np.inf)
    wl_all = np.unique(np.concatenate([m.wl for m in models]))
    P = legendre_basis(wl_all, span, D)
    if cov is not None:
        k = D + 1
        se_a = np.sqrt(np.einsum("wi,ij,wj->w", P, cov[:k, :k], P))
        se_b = np.sqrt(np.einsum("wi,ij,wj->w", P, cov[k:2 * k, k:2 * k], P))
    else:
        se_a = se_b = np.full(wl_all.size, np.inf)
    src = f"flakedb calibrate: fitted to {len(panels)} panel(s) ({', '.join(p.name for p in panels)})"
    entry = tinter_entry(par, span, (meta or {}).get("description") or f"tinter {name} (calibrated from drawdowns)",
                         src, meta)
    # every panel composed once more the ordinary way, with the entry as written
    user = copy.deepcopy(catalog)
    user["particles"][name] = entry
    de_fit = []
    for p, m in zip(panels, models):
        pred = predict(recipe_from_doc(p.recipe_doc, p.name, user), p.target.geometries, m.n, user)
        cs = for_target(pred.mode, p.target)
        de_fit.append(delta_E_2000(p.target.lab_under(cs.observer, cs.illuminant), pred.lab(cs.observer, cs.illuminant)))
    log(f"done: {str(sol.message).strip()}; max dE00 of the written tinter {np.concatenate(de_fit).max():.3f}; "
        f"{solves[0]} solves")
    return TinterResult(name=name, params=par, span_nm=span, stderr=stderr,
                        ln_sigma_stderr={"wavelength_nm": wl_all, "ln_sigma_a": se_a, "ln_sigma_s_reduced": se_b},
                        entry=entry, panels=panels, de_fit=de_fit, rms_residual=math.sqrt(float(r @ r) / r.size),
                        n_solves=solves[0], nfev=int(sol.nfev), message=str(sol.message), history=history)


# ----------------------------------------------------------------------------------------------
# The tinter ladder manifest
# ----------------------------------------------------------------------------------------------

#: Keys of a tinter ladder manifest (docs/calibration.md, "Tinters from drawdowns").
TINTER_LADDER_KEYS = ("tinter", "description", "colour_index", "density_g_cm3", "seed", "panels")


def read_tinter_ladder(path):
    """``(name, meta, seed, panels)`` from a tinter ladder manifest::

        tinter: my-blue                     # the new species' name
        description: phthalo blue paste, batch 17   # optional
        colour_index: PB15:3                # optional
        density_g_cm3: 1.6                  # optional
        seed: {km: pb15-km.csv, asymmetry_g: 0.3}   # optional: published K, S per unit volume fraction
        panels:                             # recipes naming my-blue, and their measured spectra
          - {recipe: masstone-over-black.yaml, target: masstone-over-black.csv}
          - {recipe: tint-1-10-over-white.yaml, target: ladder.cxf, cxf_object: "1:10 white"}

    ``panels`` may be empty when a seed is given (the seed is then the tinter).  Paths are relative to
    the manifest; every YAML file is read by :func:`flakedb.paint.checks.load_yaml_file`.  ``seed`` is
    returned as (wavelength_nm, σ_a/φ, σ_s/φ, g) or None.  Raises ValueError naming the field.
    """
    p = Path(path)
    try:
        _, doc = load_yaml_file(p, "ladder manifest")
    except YamlFileError as exc:
        raise ValueError(f"{p}: {exc.problem}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{p}: a tinter ladder is a YAML mapping ({', '.join(TINTER_LADDER_KEYS)})")
    extra = set(doc) - set(TINTER_LADDER_KEYS)
    if extra:
        raise ValueError(f"{p}: unknown key(s) {sorted(extra)} (allowed: {', '.join(TINTER_LADDER_KEYS)})")
    if "tinter" not in doc or not isinstance(doc["tinter"], str):
        raise ValueError(f"{p}: 'tinter' (the new colourant's name, e.g. tinter: my-blue) is missing")
    name = doc["tinter"]
    meta = {k: doc[k] for k in ("description", "colour_index", "density_g_cm3") if k in doc}
    seed = None
    if "seed" in doc:
        s = doc["seed"]
        if not isinstance(s, dict) or set(s) - {"km", "asymmetry_g"} or "km" not in s:
            raise ValueError(f"{p}: seed: give {{km: FILE.csv, asymmetry_g: g}} (K, S per unit volume fraction)")
        g = s.get("asymmetry_g", DEFAULT_START[2])
        if not isinstance(g, (int, float)) or not (G_BOUNDS[0] <= g <= G_BOUNDS[1]):
            raise ValueError(f"{p}: seed.asymmetry_g: value {g!r}; allowed {G_BOUNDS[0]} to {G_BOUNDS[1]}")
        seed = seed_from_km(*read_km_csv(p.parent / str(s["km"])), float(g))
    panels_doc = doc.get("panels", [])
    if not isinstance(panels_doc, list) or (not panels_doc and seed is None):
        raise ValueError(f"{p}: panels must be a non-empty list of {{recipe: R.yaml, target: T.csv}} "
                         f"(or give a seed to write the tinter from Kubelka-Munk data alone)")
    panels = []
    for i, e in enumerate(panels_doc):
        where = f"{p}: panels[{i}]"
        if not isinstance(e, dict) or "recipe" not in e or "target" not in e:
            raise ValueError(f"{where}: give recipe: R.yaml and target: T.csv (or .cxf)")
        extra = set(e) - {"recipe", "target", "cxf_object", "name"}
        if extra:
            raise ValueError(f"{where}: unknown key(s) {sorted(extra)} (allowed: recipe, target, cxf_object, name)")
        rp = p.parent / str(e["recipe"])
        try:
            _, rdoc = load_yaml_file(rp, "recipe")
        except YamlFileError as exc:
            raise ValueError(f"{where}.recipe: {exc.problem}") from None
        tp = p.parent / str(e["target"])
        try:
            tgt = load_target(tp, object_name=e.get("cxf_object"))
        except TargetError as exc:
            raise ValueError(f"{where}.target: {exc}") from None
        panels.append(Panel(name=str(e.get("name") or rp.stem), recipe_doc=rdoc, target=tgt, paths=(rp, tp)))
    return name, meta, seed, panels


__all__ = ["TINTER_DEGREE", "TinterParams", "TinterResult", "fit_tinter", "params_from_curves", "read_km_csv",
           "read_tinter_ladder", "seed_entry", "seed_from_km", "tinter_entry"]
