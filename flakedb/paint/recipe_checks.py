"""A schema-valid recipe's semantic checks: what the schema cannot say (spectral coverage, layer order,
binder indices, loadings and packing, custom species, the primer and metal base), each problem one line
naming the field path, the value and the allowed range.  :func:`semantic_problems` runs them all.
"""

from __future__ import annotations

import copy
import difflib

import numpy as np

from flakedb.colour.colorimetry import spectral_grid
from flakedb.paint.catalog import (
    MAX_PIGMENT_BYTES,
    TINTER_TABLES,
    expand_sweeps,
    load_catalog,
    pigment_memory_bytes,
)
from flakedb.paint.formulation import cpvc_oil_absorption, film_density_g_cm3, volume_fractions, weight_fractions
from flakedb.paint.limits import roughness_problem
from flakedb.paint.materials import material_names, refractive_index
from flakedb.paint.recipe_model import (
    DEFAULT_SPECTRAL,
    DILUTE_WARNING,
    PIGMENT_PACKING_LIMIT,
    PRIMER_ALBEDO,
    Basecoat,
    CatalogParticle,
    Clearcoat,
    CustomFlake,
    CustomMedium,
    FlakeTable,
    MetalBase,
    Primer,
    Spectrum,
)
from flakedb.paint.recipe_schema import json_short
from flakedb.paint.species import species_density_g_cm3
from flakedb.rt.scattering.media import vmf_kappa_from_mean_cosine
from flakedb.rt.scattering.microflake import DEFAULT_DISTRIBUTION, STUDENT_T_SHAPE_RANGE, flake_distribution


def _spectrum_problems(path, spec, grid, lo_val=None, hi_val=None, what="value"):
    out = []
    wl = np.asarray(spec["wavelength_nm"], float)
    val = np.asarray(spec["value"], float)
    if wl.size != val.size:
        out.append(f"{path}: wavelength_nm has {wl.size} entries and value {val.size}; give one value per wavelength")
        return out
    if np.any(np.diff(wl) <= 0):
        out.append(f"{path}.wavelength_nm: must be strictly increasing, got {wl.tolist()}")
        return out
    if grid is not None and (wl[0] > grid[0] + 1e-9 or wl[-1] < grid[-1] - 1e-9):
        out.append(f"{path}.wavelength_nm: covers {wl[0]:g}-{wl[-1]:g} nm but the recipe's grid is "
                   f"{grid[0]:g}-{grid[-1]:g} nm; extend the table (nothing is extrapolated) or narrow spectral.range_nm")
    if lo_val is not None and np.any(val < lo_val):
        k = int(np.argmin(val))
        out.append(f"{path}.value[{k}]: value {val[k]:g} is outside the allowed range "
                   f"{lo_val:g} ≤ {what}" + (f" ≤ {hi_val:g}" if hi_val is not None else ""))
    if hi_val is not None and np.any(val > hi_val):
        k = int(np.argmax(val))
        out.append(f"{path}.value[{k}]: value {val[k]:g} is outside the allowed range "
                   f"{lo_val:g} ≤ {what} ≤ {hi_val:g}")
    return out


def _flake_table(spec) -> FlakeTable:
    if isinstance(spec, (int, float)):
        return FlakeTable(np.array([0.0, 1.0]), np.array([float(spec)] * 2))
    return FlakeTable(np.asarray(spec["c"], float), np.asarray(spec["value"], float))


def _flake_table_problems(path, spec):
    if isinstance(spec, (int, float)):
        return []
    c, v = np.asarray(spec["c"], float), np.asarray(spec["value"], float)
    if c.size != v.size:
        return [f"{path}: c has {c.size} entries and value {v.size}; give one value per c"]
    if np.any(np.diff(c) <= 0):
        return [f"{path}.c: must be strictly increasing in [0, 1] (c = |cos| between light and flake normal), got {c.tolist()}"]
    return []


def spectral_grid_of(doc) -> tuple[str, np.ndarray | None, list[str]]:
    """(mode, grid or None, problems) of a schema-valid document's ``spectral`` block.

    The default is 380–780 nm every 10 nm (41 bands); a range that ends before it starts is a problem:

    >>> mode, grid, problems = spectral_grid_of({})
    >>> mode, grid.size, float(grid[0]), float(grid[-1]), problems
    ('spectral', 41, 380.0, 780.0, [])
    >>> spectral_grid_of({"spectral": {"range_nm": [700, 400]}})[2]
    ['spectral.range_nm: value [700.0, 400.0] must be increasing (first < last band, nm)']
    """
    sp = {**DEFAULT_SPECTRAL, **(doc.get("spectral") or {})}
    mode = sp["mode"]
    lo, hi = (float(v) for v in sp["range_nm"])
    step = float(sp["step_nm"])
    if mode == "mono":
        return mode, None, []
    if hi <= lo:
        return mode, None, [f"spectral.range_nm: value {[lo, hi]} must be increasing (first < last band, nm)"]
    try:
        grid = spectral_grid((lo, hi), step)
    except ValueError:
        return mode, None, [f"spectral.step_nm: value {step:g} does not divide the range {lo:g}-{hi:g} nm "
                            f"(hint: choose a step such that (last - first) / step is an integer, e.g. 5, 10 or 20)"]
    if grid.size < 3:
        return mode, None, [f"spectral: the grid {grid.tolist()} nm has fewer than 3 bands; colour needs the visible range "
                            f"(hint: range_nm [380, 780])"]
    return mode, grid, []


def _material_coverage_problems(path, entry, grid):
    """The catalogue materials of a species must cover the grid (nothing is extrapolated silently)."""
    mats = []
    if entry["kind"] == "interference_flake":
        mats = [entry["substrate"]["material"]] + [f["material"] for f in entry["coating"]]
    elif entry["kind"] == "pigment":
        mats = [entry["material"]]
    out = []
    for m in mats:
        try:
            refractive_index(m, np.array([grid[0], grid[-1]]))
        except ValueError as exc:
            out.append(f"{path}: {exc} (hint: narrow spectral.range_nm)")
    if entry["kind"] == "tinter":
        for key in TINTER_TABLES:
            wl = entry[key]["wavelength_nm"]
            if grid[0] < wl[0] - 1e-9 or grid[-1] > wl[-1] + 1e-9:
                out.append(f"{path}: the tinter's {key} covers {wl[0]:g}-{wl[-1]:g} nm, the grid "
                           f"{grid[0]:g}-{grid[-1]:g} nm (hint: narrow spectral.range_nm)")
    if entry["kind"] == "mirror_flake" and "wavelength_nm" in entry["albedo"]:
        wl = entry["albedo"]["wavelength_nm"]
        if grid[0] < wl[0] or grid[-1] > wl[-1]:
            out.append(f"{path}: the albedo spectrum covers {wl[0]:g}-{wl[-1]:g} nm, the grid {grid[0]:g}-{grid[-1]:g} nm "
                       f"(hint: narrow spectral.range_nm)")
    return out


def _order_problems(kinds) -> list[str]:
    """At most one clearcoat, first; at most one primer or metal base, last."""
    problems = []
    for i, k in enumerate(kinds):
        if k == "clearcoat" and i != 0:
            problems.append(f"layers[{i}].clearcoat: a clear coat must be the first (top) layer; layers go top to bottom "
                            f"(hint: move it to layers[0])")
        if k == "primer" and i != len(kinds) - 1:
            problems.append(f"layers[{i}].primer: the primer must be the last (bottom) layer; layers go top to bottom "
                            f"(hint: move it to the end)")
        if k == "metal" and i != len(kinds) - 1:
            problems.append(f"layers[{i}].metal: the metal base must be the last (bottom) layer; layers go top to "
                            f"bottom (hint: move it to the end)")
    if kinds.count("clearcoat") > 1:
        problems.append(f"layers: {kinds.count('clearcoat')} clear coats; at most one (the top layer)")
    if kinds.count("primer") > 1:
        problems.append(f"layers: {kinds.count('primer')} primers; at most one (the bottom layer)")
    if kinds.count("metal") > 1:
        problems.append(f"layers: {kinds.count('metal')} metal bases; at most one (the bottom layer)")
    if "metal" in kinds and "primer" in kinds:
        problems.append("layers: a primer and a metal base; the bottom is one or the other (hint: remove the "
                        "primer over the metal, or the metal)")
    return problems


def _binder_index_problems(layers, kinds) -> list[str]:
    """Binder indices below the top interface: each change (a rise or a fall) is a smooth inner interface
    (docs/model.md §4 "Inner interface"); an index-matched top binder (ior 1: no top interface) cannot sit
    over one (the solver's output rule is then the top binder's own)."""
    problems = []
    iors = [(f"layers[{i}].{k}.ior", float(layers[i][k]["ior"])) for i, k in enumerate(kinds)
            if k not in ("primer", "metal")]
    for (p_above, above), (pth, v) in zip(iors, iors[1:]):
        if v > above and above == 1.0:
            problems.append(
                f"{pth}: value {v:g} under {p_above} = 1 (index-matched): an inner interface needs a binder above it "
                f"(hint: give {p_above} the binder's index, or set {pth} to 1)")
    return problems


def _interface_roughness_warnings(layers, kinds) -> list[str]:
    """A basecoat's ``interface_roughness`` acts only where its ior differs from the binder above."""
    out = []
    above = None
    for i, k in enumerate(kinds):
        if k in ("primer", "metal"):
            continue
        ior = float(layers[i][k]["ior"])
        if k == "basecoat" and float(layers[i][k].get("interface_roughness", 0.0)) > 0 and (above is None or ior == above):
            out.append(f"layers[{i}].basecoat.interface_roughness: ignored, the basecoat's ior {ior:g} equals the "
                       f"binder's above it (no inner interface there)")
        above = ior
    return out


def _clearcoat_checks(base, L, mode, grid):
    """(problems, warnings, Clearcoat) of a clearcoat layer ``L``."""
    problems, warnings = [], []
    ab = L.get("absorption_per_um")
    if isinstance(ab, dict):
        if mode == "mono":
            problems.append(f"{base}.absorption_per_um: a spectrum needs spectral or rgb mode; mono mode takes "
                            f"wavelength-independent inputs only (hint: give a number, or set spectral.mode)")
        else:
            problems += _spectrum_problems(f"{base}.absorption_per_um", ab, grid, 0.0, None, "absorption_per_um")
        ab = Spectrum(np.asarray(ab["wavelength_nm"], float), np.asarray(ab["value"], float))
    rough = float(L.get("roughness", 0.0))
    problem = roughness_problem(rough)
    if problem:
        problems.append(f"{base}.roughness: {problem}")
    if float(L["ior"]) == 1.0 and rough > 0:
        problems.append(f"{base}.roughness: value {rough:g} with ior 1: an index-matched coat has no interface "
                        f"to be rough (hint: set roughness to 0, or ior > 1)")
    return problems, warnings, Clearcoat(float(L["thickness_um"]), float(L["ior"]), rough, ab, base)


def _population_name(pp, dist, shape, dist_field):
    """(problems, name) of one population of flake orientations: ``dist`` (beckmann, ggx, student_t or a
    catalogue's name) with the Student-t ``shape`` where it applies; ``dist_field`` names where ``dist``
    came from in the messages."""
    lo, hi = STUDENT_T_SHAPE_RANGE
    if dist == "student_t":
        if shape is None:
            return [f"{pp}.orientation_shape: missing; {dist_field} student_t needs its tail shape gamma, "
                    f"{lo:g} ≤ gamma ≤ {hi:g} (hint: orientation_shape: 2 is GGX, larger tends to Beckmann, "
                    f"1.5-2 has a heavier tail than GGX)"], None
        return [], f"student_t({float(shape)!r})"
    if shape is not None:
        return [f"{pp}.orientation_shape: value {float(shape):g} applies to the student_t distribution only, "
                f"but {dist_field} is {dist!r} (hint: set {pp}.orientation_distribution to student_t, or remove "
                f"orientation_shape)"], None
    return [], str(dist)


def orientation_name(pp, P, entry=None):
    """(problems, name or None): the flake-normal distribution a particle's orientation fields
    (``orientation_distribution``, ``orientation_shape``, ``orientation_mixture``) ask for, as the canonical
    name of :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS` (``student_t(γ)``, ``mix(first,w,second,α₂)``);
    None where the particle states none of them (the catalogue's, else Beckmann, applies).
    ``entry``: the catalogue entry whose distribution (and Student-t shape) a field the particle leaves
    out takes (None: a custom flake, Beckmann)."""
    own = P.get("orientation_distribution")
    mix = P.get("orientation_mixture")
    shape = P.get("orientation_shape")
    if own is None and shape is None and mix is None:
        return [], None
    entry = entry or {}
    cat_family = entry.get("orientation_distribution", DEFAULT_DISTRIBUTION)
    family = own if own is not None else cat_family
    if shape is None and family == "student_t" and cat_family == "student_t" and "orientation_shape" in entry:
        shape = entry["orientation_shape"]["value"]  # the catalogue's γ where the recipe keeps its family
    field = f"{pp}.orientation_distribution" if own is not None else "the catalogue's orientation_distribution"
    problems, name = _population_name(pp, family, shape, field)
    if mix is not None:
        mp = f"{pp}.orientation_mixture"
        d2 = mix.get("orientation_distribution", DEFAULT_DISTRIBUTION)
        more, name2 = _population_name(mp, d2, mix.get("orientation_shape"), f"{mp}.orientation_distribution")
        problems += more
        if name is not None and name2 is not None:
            name = f"mix({name},{float(mix['weight'])!r},{name2},{float(mix['orientation_alpha'])!r})"
    if problems:
        return problems, None
    try:
        return [], flake_distribution(name).name
    except ValueError as exc:  # the schema bounds every field; this is a last guard naming the particle
        return [f"{pp}: {exc}"], None


def _custom_flake_checks(pp, C, tau):
    """(problems, CustomFlake): tables well formed, R + T ≤ 1, some extinction."""
    problems = []
    for key in ("R", "T"):
        problems += _flake_table_problems(f"{pp}.custom.{key}", C[key])
    R, T = _flake_table(C["R"]), _flake_table(C["T"])
    if R.c.size == R.value.size and T.c.size == T.value.size:
        cc = np.union1d(R.c, T.c)
        s = np.interp(cc, R.c, R.value) + np.interp(cc, T.c, T.value)
        if np.any(s > 1 + 1e-12):
            m = int(np.argmax(s))
            problems.append(
                f"{pp}.custom: R + T = {s[m]:.6g} at c = {cc[m]:g} exceeds 1 (energy conservation: "
                f"allowed R + T ≤ 1, the rest is absorbed) (hint: lower R or T)")
        if np.all(np.interp(cc, T.c, T.value) >= 1.0 - 1e-12):
            problems.append(f"{pp}.optical_depth: value {tau:g} cannot be met: a flake with T = 1 "
                            f"at every c has no extinction (hint: T < 1 somewhere)")
    more, dist = orientation_name(f"{pp}.custom", C)
    problems += more
    return problems, CustomFlake(R, T, float(C["orientation_alpha"]), tau, C.get("name", "custom-flake"), pp,
                                 dist or DEFAULT_DISTRIBUTION)


def _custom_medium_albedo(pp, C, mode, grid):
    """(problems, albedo): a number, or a spectrum in [0, 1] covering the grid (spectral or rgb mode)."""
    alb = C["albedo"]
    if not isinstance(alb, dict):
        return [], float(alb)
    path = f"{pp}.custom.albedo"
    if mode == "mono":
        problems = [f"{path}: a spectrum needs spectral or rgb mode; mono mode takes wavelength-independent "
                    f"inputs only (hint: give a number in [0, 1], or set spectral.mode)"]
    else:
        problems = [m + " (hint: a single-scattering albedo sigma_s / sigma_t lies in [0, 1])"
                    if "outside the allowed range" in m else m
                    for m in _spectrum_problems(path, alb, grid, 0.0, 1.0, "albedo")]
    return problems, Spectrum(np.asarray(alb["wavelength_nm"], float), np.asarray(alb["value"], float))


def _custom_medium_checks(pp, C, tau, mode=None, grid=None):
    """(problems, CustomMedium): an albedo number or spectrum (:func:`_custom_medium_albedo`); a vMF
    phase given by κ or by its mean cosine g; a phase table from -1 to 1, not all zero."""
    problems, albedo = _custom_medium_albedo(pp, C, mode, grid)
    ph = C["phase"]
    if ph == "isotropic":
        phase = "isotropic"
    elif "hg" in ph:
        phase = ("hg", float(ph["hg"]))
    elif "vmf" in ph:
        v = ph["vmf"]
        phase = ("vmf", float(v["kappa"]) if "kappa" in v else float(vmf_kappa_from_mean_cosine(float(v["g"]))))
    else:
        ct = np.asarray(ph["table"]["cos_theta"], float)
        pv = np.asarray(ph["table"]["value"], float)
        phase = ("table", ct, pv)
        tp = f"{pp}.custom.phase.table"
        if ct.size != pv.size:
            problems.append(f"{tp}: cos_theta has {ct.size} entries and value {pv.size}")
        elif np.any(np.diff(ct) <= 0) or ct[0] != -1.0 or ct[-1] != 1.0:
            problems.append(f"{tp}.cos_theta: must increase strictly from -1 to 1 (both ends "
                            f"included), got {json_short(ct.tolist())}")
        elif not np.any(pv > 0):
            problems.append(f"{tp}.value: all zero; a phase function must integrate to 1 "
                            f"(hint: give relative values; compose normalises them)")
    return problems, CustomMedium(albedo, phase, tau, C.get("name", "custom-medium"), pp)


def _pigment_cost_problem(pp, name, P, entry, grid, ior):
    """A pigment whose Mie size average would need more than :data:`MAX_PIGMENT_BYTES`, naming the field
    that drives it (the recipe's override or the catalogue's entry), or None."""
    dm = float(P.get("median_diameter_um", entry["median_diameter_um"]["value"]))
    g = float(P.get("gsd", entry["gsd"]["value"]))
    wl = grid if grid is not None else np.arange(380.0, 781.0, 5.0)
    need = pigment_memory_bytes(dm, g, wl, ior)
    if need <= MAX_PIGMENT_BYTES:
        return None
    sigma = np.log(g)
    x_max = np.pi * ior * dm * np.exp(5.0 * sigma + 6.0 * sigma ** 2) / (np.min(wl) * 1e-3)
    fields = [f"{pp}.{k}" if k in P else f"catalogue particles.{name}.{k}" for k in ("median_diameter_um", "gsd")]
    return (f"{fields[0]} = {dm:g} µm with {fields[1]} = {g:g}: its Mie size average needs about "
            f"{need / 2**30:,.0f} GiB (size parameters up to {x_max:,.0f} "
            f"resolved in {np.size(wl)} bands); the limit is {MAX_PIGMENT_BYTES / 2**30:.0f} GiB (hint: a smaller "
            f"median diameter or gsd: pigments are 0.05-5 µm with gsd 1.2-2; the node count --n does not change "
            f"this)")


#: A recipe's overrides of an interference flake's films (applied by :func:`flake_entry_with_films`).
FILM_OVERRIDES = ("coating_thickness_nm", "coating_thickness_rel_sd", "substrate_thickness_nm",
                  "substrate_thickness_rel_sd")


def flake_entry_with_films(entry: dict, overrides: dict, source: str = "recipe") -> dict:
    """A copy of interference-flake ``entry`` with a recipe's :data:`FILM_OVERRIDES` set (mean thicknesses
    in nm, relative standard deviations) and ``thickness_um`` recomputed from the stack (the loading
    aρ = volume fraction / thickness follows it).  ``overrides['coating_thickness_nm']`` has one value per
    coating film (checked by the caller)."""
    e = copy.deepcopy(entry)
    for i, t in enumerate(overrides.get("coating_thickness_nm", ())):
        e["coating"][i]["thickness_nm"] = {"value": float(t), "source": source}
    if "coating_thickness_rel_sd" in overrides:
        for film in e["coating"]:
            film["thickness_rel_sd"] = {"value": float(overrides["coating_thickness_rel_sd"]), "source": source}
    if "substrate_thickness_nm" in overrides:
        e["substrate"]["thickness_nm"] = {"value": float(overrides["substrate_thickness_nm"]), "source": source}
    if "substrate_thickness_rel_sd" in overrides:
        e["substrate"]["thickness_rel_sd"] = {"value": float(overrides["substrate_thickness_rel_sd"]), "source": source}
    total_nm = 2 * sum(f["thickness_nm"]["value"] for f in e["coating"]) + e["substrate"]["thickness_nm"]["value"]
    e["thickness_um"] = {"value": total_nm / 1000.0, "source": "total of the film stack"}
    return e


#: A recipe's grating fields of a flake (applied by :func:`flake_entry_with_grating`): the period and amplitude of
#: a sinusoidal grating embossed on it (flakedb.rt.scattering.grating_flake).
GRATING_OVERRIDES = ("grating_period_nm", "grating_amplitude_nm")


def flake_entry_with_grating(entry: dict, overrides: dict, source: str = "recipe") -> dict:
    """A copy of flake ``entry`` with the recipe's :data:`GRATING_OVERRIDES` in its ``grating`` (both given, or
    one over the catalogue's grating: checked by the caller)."""
    e = copy.deepcopy(entry)
    g = e.setdefault("grating", {})
    for key, field in (("grating_period_nm", "period_nm"), ("grating_amplitude_nm", "amplitude_nm")):
        if key in overrides:
            g[field] = {"value": float(overrides[key]), "source": source}
    return e


def _catalog_particle_checks(pp, base, P, d, mode, grid, allsp, ior=1.5):
    """(problems, warnings, CatalogParticle or None): species known, overrides of its kind, grid
    covered, particle thinner than the layer ``d`` [µm]."""
    problems, warnings = [], []
    name = P["species"]
    vf = float(P["volume_fraction"])
    if name not in allsp:
        close = difflib.get_close_matches(name, list(allsp), n=3)
        problems.append(f"{pp}.species: unknown species {name!r}"
                        + (f" (did you mean {', '.join(map(repr, close))}?)" if close else "")
                        + " (hint: `flakedb species list` shows the catalogue; a species of your own "
                          "catalogue needs --catalog FILE.yaml (or $FLAKEDB_CATALOG); or describe it inline "
                          "with `custom:` and an optical_depth)")
        return problems, warnings, None
    entry = allsp[name]
    is_flake = entry["kind"] not in ("pigment", "tinter")
    flake_only = ("orientation_alpha", "orientation_distribution", "orientation_shape", "orientation_mixture",
                  "diameter_um", "opaque", "diameter_gsd") + GRATING_OVERRIDES
    pig_only = ("median_diameter_um", "gsd")
    for key in (pig_only if is_flake else flake_only + (pig_only if entry["kind"] == "tinter" else ())):
        if key in P:
            problems.append(f"{pp}.{key}: {name!r} is a {entry['kind']}; {key} applies to "
                            f"{'pigments' if key in pig_only else 'flakes'} only (hint: remove it"
                            + ("; a tinter has no particle size: its optics are per unit volume fraction)"
                               if entry["kind"] == "tinter" else ")"))
    films = {k: P[k] for k in FILM_OVERRIDES if k in P}
    if films and entry["kind"] != "interference_flake":
        for k in films:
            problems.append(f"{pp}.{k}: {name!r} is a {entry['kind']}; {k} applies to interference flakes only "
                            f"(hint: remove it, or choose an interference flake such as an aluminium grade)")
        films = {}
    nc = len(entry["coating"]) if entry["kind"] == "interference_flake" else 0
    if isinstance(films.get("coating_thickness_nm"), (int, float)):  # one number: a one-film coating
        films["coating_thickness_nm"] = [films["coating_thickness_nm"]]
    if "coating_thickness_nm" in films and len(films["coating_thickness_nm"]) != nc:
        problems.append(f"{pp}.coating_thickness_nm: {len(films['coating_thickness_nm'])} value(s) but {name!r} has "
                        f"{nc} coating film(s) ({', '.join(f['material'] for f in entry['coating'])}, outside in) "
                        f"(hint: give one thickness per film)")
        films.pop("coating_thickness_nm")
    if films:
        entry = flake_entry_with_films(entry, films, source=f"recipe {pp}")
    grating = {k: P[k] for k in GRATING_OVERRIDES if k in P} if is_flake else {}
    if grating and "grating" not in entry and len(grating) < len(GRATING_OVERRIDES):
        missing = next(k for k in GRATING_OVERRIDES if k not in grating)
        problems.append(f"{pp}.{missing}: missing; {name!r} has no grating, so embossing it needs both "
                        f"{' and '.join(GRATING_OVERRIDES)} (hint: e.g. grating_period_nm: 690, grating_amplitude_nm: 50)")
        grating = {}
    if grating:
        entry = flake_entry_with_grating(entry, grating, source=f"recipe {pp}")
    if is_flake and "grating" in entry and mode != "spectral":
        problems.append(f"{pp}.species: {name!r} is a grating (diffractive) flake: its orders' directions depend on "
                        f"the wavelength, which a {mode} channel does not have (hint: set spectral.mode: spectral)")
    if mode == "mono":
        problems.append(f"{pp}.species: catalogue species have spectral optics; mono mode takes "
                        f"wavelength-independent inputs only (hint: set spectral.mode to spectral or rgb)")
    elif grid is not None:
        problems += _material_coverage_problems(f"{pp}.species ({name})", entry, grid)
    if is_flake:
        t_flake = float(entry["thickness_um"]["value"])
        if t_flake > d:
            problems.append(f"{pp}: the flake is {t_flake:g} µm thick but {base}.thickness_um is {d:g} µm "
                            f"(hint: a layer must be thicker than its flakes)")
        if "diameter_um" in P and float(P["diameter_um"]) <= t_flake:
            problems.append(f"{pp}.diameter_um: {float(P['diameter_um']):g} µm is not wider than {name!r}'s thickness "
                            f"{t_flake:g} µm: the flake model takes platelets (flat facets; the texture model's "
                            f"discs) (hint: a diameter above {t_flake:g} µm; effect pigments are 5-100 µm across)")
        if P.get("opaque") and entry["kind"] == "mirror_flake":
            warnings.append(f"{pp}.opaque: a mirror flake is opaque already (T = 0)")
    elif entry["kind"] == "pigment":
        dm = float(P.get("median_diameter_um", entry["median_diameter_um"]["value"]))
        if dm > d:
            problems.append(f"{pp}: median particle diameter {dm:g} µm exceeds {base}.thickness_um = {d:g} µm "
                            f"(hint: a layer must be thicker than its pigment particles)")
        elif mode != "mono":
            cost = _pigment_cost_problem(pp, name, P, entry, grid, ior)
            if cost:
                problems.append(cost)
    dist = None
    if is_flake:
        more, dist = orientation_name(pp, P, entry)
        problems += more
    particle = CatalogParticle(
        name, entry, vf, P.get("orientation_alpha"), P.get("diameter_um"), bool(P.get("opaque", False)),
        P.get("median_diameter_um"), P.get("gsd"), pp, dist, P.get("diameter_gsd"), film_overrides=films,
        grating_overrides=grating)
    return problems, warnings, particle


def _packing_checks(base, particles):
    """(problems, warnings) of a basecoat's catalogue particles' Σ volume fractions (module docstring)."""
    problems, warnings = [], []
    sum_pig = sum(p.volume_fraction for p in particles if not p.is_flake)
    sum_all = sum(p.volume_fraction for p in particles)
    if sum_pig > PIGMENT_PACKING_LIMIT:
        problems.append(f"{base}.particles: the pigments' volume fractions add up to {sum_pig:.4g}, above the "
                        f"random close packing of spheres {PIGMENT_PACKING_LIMIT} (allowed range: Σ ≤ "
                        f"{PIGMENT_PACKING_LIMIT}) (hint: lower the volume_fraction values)")
    if sum_all >= 1.0:
        problems.append(f"{base}.particles: the volume fractions add up to {sum_all:.4g}; they must stay below 1 "
                        f"(the particles cannot fill more than the layer) (hint: lower them)")
    elif sum_all > DILUTE_WARNING:
        warnings.append(f"{base}.particles: volume fractions add up to {sum_all:.3g} > {DILUTE_WARNING}: the "
                        f"independent-scattering model (eq. 2 adds cross-sections) is doubtful this dense")
    return problems, warnings


def _density(entry):
    """A species' density (g/cm³; :func:`flakedb.paint.species.species_density_g_cm3`: its own, or a flake's
    film-stack mean), NaN where none applies."""
    rho = species_density_g_cm3(entry)[0] if entry is not None else None
    return np.nan if rho is None else float(rho)


def _binder_density(binder):
    d = (binder or {}).get("density_g_cm3")
    return np.nan if d is None else float(d["value"])


def _loadings(base, particles, allsp, binder):
    """(problems, {j: volume fraction}) of a basecoat's catalogue particles: each given by
    ``volume_fraction`` or ``weight_fraction`` (converted, :func:`flakedb.paint.formulation.volume_fractions`)."""
    problems, cat = [], []
    for j, P in enumerate(particles):
        if "custom" in P:
            continue
        pp = f"{base}.particles[{j}]"
        given = [k for k in ("volume_fraction", "weight_fraction") if k in P]
        if len(given) != 1:
            problems.append(f"{pp}: give the loading as volume_fraction or as weight_fraction, exactly one (got "
                            f"{' and '.join(given) or 'neither'})")
            continue
        cat.append((j, pp, P))
    by_w = [(j, pp, P) for j, pp, P in cat if "weight_fraction" in P]
    if not by_w:
        return problems, {j: float(P["volume_fraction"]) for j, _, P in cat}
    if any("custom" in P for P in particles):
        problems.append(f"{base}.particles: weight_fraction needs the volume of every particle in the layer; a custom "
                        f"particle (optical_depth) has none (hint: give this layer's loadings as volume_fraction)")
    rho_b = _binder_density(binder)
    if np.isnan(rho_b):
        problems.append(f"{base}.particles: weight_fraction needs the binder's density: the catalogue's binder has no "
                        f"density_g_cm3 (hint: add density_g_cm3: {{value, source}} to its binder, or give "
                        f"volume_fraction)")
    for j, pp, P in cat:
        entry = allsp.get(P["species"])
        if entry is not None and np.isnan(_density(entry)):
            field = "weight_fraction" if "weight_fraction" in P else "species"
            problems.append(f"{pp}.{field}: species {P['species']!r} has no density_g_cm3 in the catalogue, which "
                            f"a layer with weight fractions needs for every particle (hint: give this layer's "
                            f"loadings as volume_fraction, or add density_g_cm3 {{value, source}} to the species)")
    if problems or any(P["species"] not in allsp for _, _, P in cat):
        return problems, {j: float(P.get("volume_fraction", np.nan)) for j, _, P in cat}
    phi = volume_fractions([float(P.get("volume_fraction", np.nan)) for _, _, P in cat],
                           [float(P.get("weight_fraction", np.nan)) for _, _, P in cat],
                           [_density(allsp[P["species"]]) for _, _, P in cat], rho_b) \
        if sum(float(P["weight_fraction"]) for _, _, P in by_w) < 1.0 else None
    if phi is None:
        problems.append(f"{base}.particles: the weight fractions add up to "
                        f"{sum(float(P['weight_fraction']) for _, _, P in by_w):.4g}; they must stay below 1 "
                        f"(the binder is the rest of the dry film) (hint: lower them)")
        return problems, {}
    return problems, {j: float(v) for (j, _, _), v in zip(cat, phi)}


def formulation_record(base, particles, binder):
    """(problems, record) of a basecoat's catalogue particles (:class:`flakedb.paint.recipe_model.CatalogParticle`):
    per particle the volume and weight fractions and density (weight fractions None where a density is
    missing), the PVC, the film density and the CPVC estimate from oil absorption when every species has
    one (:mod:`flakedb.paint.formulation`, docs/formulation.md); a PVC above that estimate is a problem."""
    rho_b = _binder_density(binder)
    rho = np.array([_density(p.entry) for p in particles])
    phi = np.array([p.volume_fraction for p in particles])
    known = bool(particles) and not np.isnan(rho_b) and not np.any(np.isnan(rho))
    w = weight_fractions(phi, rho, rho_b) if known else [None] * len(particles)
    oa = [(p.entry.get("oil_absorption_g_100g") or {}).get("value") for p in particles]
    pvc = float(phi.sum())
    cpvc = basis = None
    if particles and not np.any(np.isnan(rho)) and all(v is not None for v in oa):
        cpvc = cpvc_oil_absorption(phi, rho, oa)
        basis = ("Asbeck & Van Loo (1949) from oil absorption, 1 / (1 + Σφ ρ OA / (93.5 Σφ)): "
                 + ", ".join(f"{p.species} {v:g} g/100 g at {r:g} g/cm³" for p, v, r in zip(particles, oa, rho)))
    missing = sorted({p.species for p, v in zip(particles, oa) if v is None})
    rec = {"binder_density_g_cm3": None if np.isnan(rho_b) else rho_b, "pvc": pvc,
           "film_density_g_cm3": float(film_density_g_cm3(phi, rho, rho_b)) if known else None,
           "cpvc_estimate": cpvc, "cpvc_basis": basis or (
               f"not estimated: no cited oil absorption for {', '.join(missing)}" if missing else None),
           "particles": [{"path": p.path, "species": p.species,
                          "given": "weight_fraction" if p.weight_fraction is not None else "volume_fraction",
                          "volume_fraction": float(f), "weight_fraction": None if x is None else float(x),
                          "density_g_cm3": None if np.isnan(r) else float(r)}
                         for p, f, x, r in zip(particles, phi, w, rho)]}
    problems = []
    if cpvc is not None and pvc > cpvc:
        problems.append(f"{base}.particles: the pigment volume concentration PVC = {pvc:.4g} (Σ volume fractions) is "
                        f"above this mix's critical PVC, estimated {cpvc:.4g} ({basis}): above the CPVC there is "
                        f"not enough binder to fill the voids between the particles, the film holds air, and the "
                        f"model (particles in binder) does not describe it (allowed range: PVC ≤ {cpvc:.4g}) "
                        f"(hint: lower the loadings)")
    return problems, rec


def _basecoat_checks(base, L, mode, grid, allsp, binder=None):
    """(problems, warnings, Basecoat): loadings resolved (by volume or by weight), every particle checked,
    then the packing of the layer and its formulation (PVC against the CPVC estimate)."""
    problems, warnings = [], []
    bc = Basecoat(float(L["thickness_um"]), float(L["ior"]), [], base, float(L.get("interface_roughness", 0.0)))
    problem = roughness_problem(bc.interface_roughness)
    if problem:
        problems.append(f"{base}.interface_roughness: {problem}")
    p, phi = _loadings(base, L["particles"], allsp, binder)
    problems += p
    catalogued = []
    for j, P in enumerate(L["particles"]):
        pp = f"{base}.particles[{j}]"
        if "custom" in P:
            C, tau = P["custom"], float(P["optical_depth"])
            if C["kind"] == "flake":
                p, particle = _custom_flake_checks(pp, C, tau)
            else:
                p, particle = _custom_medium_checks(pp, C, tau, mode, grid)
            problems += p
        else:
            if j not in phi:
                continue   # its loading is refused above (NaN: converted only once every problem is fixed)
            given_w = P.get("weight_fraction")
            P = {k: v for k, v in P.items() if k != "weight_fraction"} | {"volume_fraction": phi[j]}
            p, w, particle = _catalog_particle_checks(pp, base, P, bc.thickness_um, mode, grid, allsp, bc.ior)
            problems += p
            warnings += w
            if particle is None:
                continue
            particle.weight_fraction = None if given_w is None else float(given_w)
            catalogued.append(particle)
        bc.particles.append(particle)
    p, w = _packing_checks(base, catalogued)
    if not p:
        p, bc.formulation = formulation_record(base, catalogued, binder)
    return problems + p, warnings + w, bc


def _primer_checks(base, L, mode, grid):
    """(problems, Primer): a colour, an albedo, or a spectrum in [0, 1] covering the grid."""
    problems = []
    if "color" in L:
        return problems, Primer(PRIMER_ALBEDO[L["color"]], L["color"], base)
    if "albedo" in L:
        return problems, Primer(float(L["albedo"]), f"albedo {float(L['albedo']):g}", base)
    if mode == "mono":
        problems.append(f"{base}.spectrum: a spectrum needs spectral or rgb mode; mono mode takes "
                        f"wavelength-independent inputs only (hint: give an albedo)")
    else:
        problems += _spectrum_problems(f"{base}.spectrum", L["spectrum"], grid, 0.0, 1.0, "albedo")
    sp = L["spectrum"]
    return problems, Primer(Spectrum(np.asarray(sp["wavelength_nm"], float), np.asarray(sp["value"], float)),
                            "spectrum", base)


#: Largest extinction coefficient k of a metal base's material below which a warning says it is
#: hardly a metal: the base is opaque by construction (light refracted into it is absorbed), which
#: for a dielectric such as SiO2 (k = 0) is not what a panel of that material would do.
METAL_K_WARNING = 0.5


def _metal_checks(base, L, mode, grid):
    """(problems, warnings, MetalBase): a catalogue material (spectral or rgb mode) that exists and
    covers the grid, or a constant {n, k}."""
    problems, warnings = [], []
    m = L["material"]
    rough = float(L["roughness"])
    comp = bool(L.get("energy_compensation", True))
    if isinstance(m, dict):
        N = complex(float(m["n"]), float(m["k"]))
        k_max = N.imag
        metal = MetalBase(N, rough, comp, f"n = {N.real:g}, k = {N.imag:g}", base)
    else:
        metal = MetalBase(str(m), rough, comp, str(m), base)
        names = material_names()
        if m not in names:
            close = difflib.get_close_matches(str(m), names, n=3)
            problems.append(f"{base}.material: unknown material {json_short(m)}"
                            + (f" (did you mean {', '.join(map(repr, close))}?)" if close else "")
                            + f"; known materials: {', '.join(names)} (hint: name one of them, or give a "
                              f"constant index {{n: …, k: …}})")
            return problems, warnings, metal
        if mode == "mono":
            problems.append(f"{base}.material: {m!r} has a spectral index; mono mode takes wavelength-independent "
                            f"inputs only (hint: give material: {{n: …, k: …}}, or set spectral.mode)")
            return problems, warnings, metal
        try:
            k_max = float(np.max(refractive_index(m, grid).imag))
        except ValueError as exc:
            problems.append(f"{base}.material: {exc} (hint: narrow spectral.range_nm)")
            return problems, warnings, metal
    if k_max < METAL_K_WARNING:
        warnings.append(f"{base}.material: k ≤ {k_max:.3g} < {METAL_K_WARNING:g} on the grid: hardly a metal; the "
                        f"base is modelled as opaque (light refracted into it is absorbed)")
    return problems, warnings, metal


def _stack_problems(clear, basecoats, primer, metal=None) -> list[str]:
    """A transmissive stack (no primer or metal base) only without a top interface; something to compose."""
    problems = []
    top_ior = clear.ior if clear is not None else (basecoats[0].ior if basecoats else 1.0)
    if primer is None and metal is None and top_ior != 1.0:
        problems.append(
            f"layers: no primer, so the stack transmits into a half-space of the binder (index {top_ior:g}); a "
            f"transmissive .bsdf needs one node set above and below, which only an index-matched stack (ior 1, no "
            f"top interface) has (hint: add a primer as the last layer, or set every ior to 1)")
    if not basecoats and clear is None and primer is None and metal is None:
        problems.append("layers: nothing to compose (hint: add a primer, a basecoat or a clearcoat)")
    return problems


def semantic_problems(doc, catalog=None) -> tuple[list[str], list[str], dict]:
    """Checks beyond the schema on a schema-valid document: the dispatcher over the checks above
    (spectral grid, layer order, binder index, then each layer by kind, then the stack).

    Returns ``(problems, warnings, parts)`` where ``parts`` holds the typed pieces built on the way
    (used by :func:`build_recipe` when there are no problems).
    """
    problems, warnings = [], []
    mode, grid, p = spectral_grid_of(doc)
    problems += p
    layers = doc["layers"]
    kinds = [next(iter(item)) for item in layers]
    problems += _order_problems(kinds)
    catalog = catalog if catalog is not None else load_catalog()
    allsp = expand_sweeps(catalog)
    problems += _binder_index_problems(layers, kinds)

    clear, basecoats, primer, metal = None, [], None, None
    for i, k in enumerate(kinds):
        base = f"layers[{i}].{k}"
        L = layers[i][k]
        if k == "clearcoat":
            p, w, clear = _clearcoat_checks(base, L, mode, grid)
        elif k == "basecoat":
            p, w, bc = _basecoat_checks(base, L, mode, grid, allsp, catalog.get("binder"))
            basecoats.append(bc)
        elif k == "metal":
            p, w, metal = _metal_checks(base, L, mode, grid)
        else:  # primer
            (p, primer), w = _primer_checks(base, L, mode, grid), []
        problems += p
        warnings += w

    problems += _stack_problems(clear, basecoats, primer, metal)
    warnings += _interface_roughness_warnings(layers, kinds)
    parts = {"mode": mode, "grid": grid, "clearcoat": clear, "basecoats": basecoats, "primer": primer,
             "metal": metal}
    return problems, warnings, parts
