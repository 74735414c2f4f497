"""Paint recipes: parse, validate and check a recipe YAML into a typed :class:`Recipe`.

A recipe describes a paint as layers, top to bottom (docs/model.md §1)::

    flakedb: 1                       # format version
    name: pearl-white                # names the outputs DIR/NAME.bsdf, .h5, .json
    spectral: {mode: spectral, range_nm: [380, 780], step_nm: 10}     # or rgb / mono
    resolution: auto                 # or the node count n (even), or targets {albedo_error: 0.01, lobe_error: 0.05, colour_error: 0.1}
    layers:
      - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}
      - basecoat:
          thickness_um: 15
          ior: 1.5
          particles:
            - {species: pearlescent, volume_fraction: 0.04, orientation_alpha: 0.2}
            - {species: titanium-white, volume_fraction: 0.02}
      - primer: {color: white}         # or a metal base: metal: {material: Al, roughness: 0.1}

Three stages, each reporting *every* problem with the recipe field path
(``layers[1].basecoat.particles[0].volume_fraction``), the value, the allowed range and a hint:

1. YAML → a document (:func:`parse_recipe`); YAML syntax errors name the line.
2. JSON Schema 2020-12 (``schemas/recipe.schema.json``; unknown keys refused everywhere).
3. Checks a schema cannot express (:func:`semantic_problems`): layer order (at most one clearcoat,
   first; at most one primer or metal base, last), binder indices equal or rising downwards (each
   rise is a smooth inner interface), species that
   exist in the catalogue, overrides that fit the species' kind, packing limits, flake R + T ≤ 1,
   tabulated spectra that cover the grid, optical constants that cover the grid (a metal base's
   material too), a transmissive stack (no primer or metal base) only without a top interface.

Nothing here computes optics; everything is caught before any computation.  The physics mapping
from a :class:`Recipe` to solver inputs is :mod:`flakedb.paint.mapping`.

Limits (stated here, checked in :func:`semantic_problems`)
----------------------------------------------------------
* Spherical pigments: Σ volume_fraction ≤ :data:`PIGMENT_PACKING_LIMIT` = 0.64 per layer, the
  random close packing of equal spheres (Scott & Kilgour, Brit. J. Appl. Phys. 2, 863 (1969));
  a pigment volume concentration above it leaves no room for the binder.
* All particles together: Σ volume_fraction < 1 (space filling).  No published packing limit of
  platelets with an orientation spread was found, so flakes get only this hard limit.
* Above :data:`DILUTE_WARNING` = 0.3 total the model's independent-scattering assumption (eq. 2
  adds the particles' cross-sections) is doubtful: a warning, not an error.
* A particle larger than its layer (flake thickness, or pigment median diameter, above the layer
  thickness) is refused.
"""

from __future__ import annotations

import difflib
import json
from dataclasses import dataclass, field
from pathlib import Path

import jsonschema
import numpy as np

from flakedb.colour.colorimetry import spectral_grid
from flakedb.paint.catalog import MAX_PIGMENT_BYTES, expand_sweeps, load_catalog, pigment_memory_bytes
from flakedb.paint.checks import YamlFileError, load_yaml_file, parse_yaml_text, value_problems
from flakedb.paint.limits import roughness_problem
from flakedb.paint.materials import material_names, refractive_index
from flakedb.resources import PACKAGE_DIR, SCHEMAS_DIR
from flakedb.rt.media import vmf_kappa_from_mean_cosine

#: Recipe format version this flakedb reads (the ``flakedb:`` key).
FORMAT_VERSION = 1
#: Σ volume fraction of spherical pigments per layer: random close packing (module docstring).
PIGMENT_PACKING_LIMIT = 0.64
#: Σ volume fraction above which a warning says the dilute (independent scattering) model is doubtful.
DILUTE_WARNING = 0.3
#: Lambertian albedo of the named primer colours.  black 0.04 (Munsell value ≈ 2.3 by ASTM D1535:
#: a carbon-black primer), gray 0.18 (the photographic 18 % grey card, Munsell ≈ N4.9, middle grey),
#: white 0.9 (Munsell ≈ N9.6, a good white primer; TiO2 whites reach 0.9-0.95).  Munsell values
#: computed with colour.munsell_value(Y, method="ASTM D1535").
PRIMER_ALBEDO = {"black": 0.04, "gray": 0.18, "white": 0.9}

#: Defaults of the ``spectral`` block.
DEFAULT_SPECTRAL = {"mode": "spectral", "range_nm": [380.0, 780.0], "step_nm": 10.0}


class RecipeError(ValueError):
    """An invalid recipe.  ``problems`` lists every problem as ``path: message``."""

    def __init__(self, source, problems):
        self.source = str(source)
        self.problems = list(problems)
        super().__init__(f"{self.source}: invalid recipe ({len(self.problems)} problem"
                         f"{'s' if len(self.problems) != 1 else ''}):\n  " + "\n  ".join(self.problems))


# ----------------------------------------------------------------------------------------------
# Typed structure
# ----------------------------------------------------------------------------------------------


@dataclass
class Spectrum:
    """A tabulated spectrum (nm → value), linear between points."""

    wavelength_nm: np.ndarray
    value: np.ndarray

    def at(self, wavelength_nm):
        return np.interp(np.asarray(wavelength_nm, float), self.wavelength_nm, self.value)


@dataclass
class Clearcoat:
    thickness_um: float
    ior: float
    roughness: float = 0.0
    absorption_per_um: float | Spectrum | None = None
    path: str = "layers[0].clearcoat"


@dataclass
class CatalogParticle:
    """A catalogue species with a volume fraction; ``entry`` is the resolved catalogue entry."""

    species: str
    entry: dict
    volume_fraction: float
    orientation_alpha: float | None = None
    diameter_um: float | None = None
    opaque: bool = False
    median_diameter_um: float | None = None
    gsd: float | None = None
    path: str = ""
    #: the recipe's ``orientation_distribution`` override (None: the catalogue's, else Beckmann)
    orientation_distribution: str | None = None
    #: flakes: geometric standard deviation of the log-normal diameter distribution (texture only)
    diameter_gsd: float | None = None

    @property
    def kind(self):
        return self.entry["kind"]

    @property
    def is_flake(self):
        return self.kind in ("interference_flake", "mirror_flake")


@dataclass
class FlakeTable:
    """R or T of a custom flake over the flake cosine c (constant: c = [0, 1], equal values)."""

    c: np.ndarray
    value: np.ndarray


@dataclass
class CustomFlake:
    R: FlakeTable
    T: FlakeTable
    orientation_alpha: float
    optical_depth: float
    name: str = "custom-flake"
    path: str = ""
    #: the flake normals' distribution (flakedb.rt.microflake.FLAKE_DISTRIBUTIONS)
    orientation_distribution: str = "beckmann"


@dataclass
class CustomMedium:
    """``albedo``: a float or a :class:`Spectrum` (per band); ``phase``: ``"isotropic"``, ``("hg", g)``,
    ``("vmf", kappa)`` (a recipe's mean cosine g converted to κ, :func:`flakedb.rt.media.vmf_kappa_from_mean_cosine`)
    or ``("table", cos_theta, value)``."""

    albedo: float | Spectrum
    phase: object
    optical_depth: float
    name: str = "custom-medium"
    path: str = ""


@dataclass
class Basecoat:
    thickness_um: float
    ior: float
    particles: list = field(default_factory=list)
    path: str = ""
    #: Beckmann α of the inner interface at this basecoat's top (0: smooth; only where the ior changes)
    interface_roughness: float = 0.0


@dataclass
class Primer:
    """Lambertian primer: ``albedo`` is a float or a :class:`Spectrum`; ``label`` says where it came from."""

    albedo: float | Spectrum
    label: str
    path: str = ""


@dataclass
class MetalBase:
    """A metal base in place of the primer (docs/model.md §4): a Beckmann microfacet conductor of
    roughness ``roughness``.  ``material``: a catalogue material name (complex index n + ik per
    wavelength, :func:`flakedb.paint.materials.refractive_index`) or a wavelength-independent complex
    index n + ik (relative to vacuum).  ``energy_compensation``: Kulla & Conty's lobe (default)."""

    material: str | complex
    roughness: float
    energy_compensation: bool = True
    label: str = ""
    path: str = ""


@dataclass
class Recipe:
    """A validated recipe.  ``wavelength_nm`` is the band grid (spectral mode) or the integration
    grid of the RGB conversion (rgb mode); None in mono mode.  ``n`` is None for ``auto``."""

    name: str
    mode: str
    wavelength_nm: np.ndarray | None
    n: int | None
    clearcoat: Clearcoat | None
    basecoats: list
    primer: Primer | None
    description: str = ""
    text: str = ""
    source: str = "<recipe>"
    warnings: list = field(default_factory=list)
    doc: dict = field(default_factory=dict)
    #: accuracy targets of ``resolution: auto`` ({albedo_error, lobe_error}; empty: the defaults of
    #: :data:`flakedb.paint.mapping.AUTO_TARGETS`)
    targets: dict = field(default_factory=dict)
    #: a metal base in place of the primer (None: the primer, or nothing)
    metal: MetalBase | None = None

    @property
    def binder_ior(self) -> float:
        """The single binder index below the top interface (1.0 when there is no layer with one)."""
        if self.clearcoat is not None:
            return self.clearcoat.ior
        if self.basecoats:
            return self.basecoats[0].ior
        return 1.0

    def particles(self):
        """(basecoat, particle) pairs, top to bottom."""
        return [(b, p) for b in self.basecoats for p in b.particles]


# ----------------------------------------------------------------------------------------------
# Schema validation with messages that say what to do
# ----------------------------------------------------------------------------------------------


def repo_root() -> Path:
    """The package folder (holds ``catalog/`` and ``schemas/``, see :mod:`flakedb.resources`)."""
    return PACKAGE_DIR


def schema_path() -> Path:
    return SCHEMAS_DIR / "recipe.schema.json"


_SCHEMA = None


def _schema():
    global _SCHEMA
    if _SCHEMA is None:
        with open(schema_path(), encoding="utf-8") as f:
            _SCHEMA = json.load(f)
    return _SCHEMA


def fmt_path(parts) -> str:
    """``['layers', 1, 'basecoat', 'particles', 0]`` → ``layers[1].basecoat.particles[0]``."""
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


def _range_text(schema) -> str | None:
    lo = hi = None
    if "minimum" in schema:
        lo = f"{schema['minimum']:g} ≤ value"
    if "exclusiveMinimum" in schema:
        lo = f"{schema['exclusiveMinimum']:g} < value"
    if "maximum" in schema:
        hi = f"value ≤ {schema['maximum']:g}"
    if "exclusiveMaximum" in schema:
        hi = f"value < {schema['exclusiveMaximum']:g}"
    if lo and hi:
        return lo + hi[len("value"):]
    return lo or hi


def _json_short(v) -> str:
    s = json.dumps(v, default=str)
    return s if len(s) <= 60 else s[:57] + "..."


def _looks_numeric(text) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _describe_error(err) -> str:
    path = fmt_path(err.absolute_path)
    v = err.validator
    hint = err.schema.get("description") if isinstance(err.schema, dict) else None
    if v in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        msg = f"value {err.instance!r} is outside the allowed range {_range_text(err.schema)}"
    elif v == "additionalProperties":
        allowed = sorted((err.schema.get("properties") or {}).keys())
        extra = sorted(set(err.instance) - set(allowed)) if isinstance(err.instance, dict) else []
        parts = []
        for k in extra:
            close = difflib.get_close_matches(str(k), allowed, n=1)
            parts.append(f"unknown key {k!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        msg = "; ".join(parts) + f"; allowed keys: {', '.join(allowed)}"
    elif v == "required":
        msg = err.message.replace("is a required property", "is missing (required)")
    elif v == "enum":
        msg = f"value {_json_short(err.instance)} is not one of {', '.join(map(str, err.validator_value))}"
    elif v == "const":
        if path == "flakedb" and str(err.instance).strip() == str(FORMAT_VERSION):
            msg = (f"recipe format version {_json_short(err.instance)} is a {type(err.instance).__name__}, not "
                   f"the number {FORMAT_VERSION} (write `flakedb: {FORMAT_VERSION}` without quotes)")
        elif path == "flakedb":
            msg = (f"recipe format version {_json_short(err.instance)} is not supported; this flakedb reads "
                   f"version {FORMAT_VERSION} (write `flakedb: {FORMAT_VERSION}` as the first line)")
        else:
            msg = f"value {_json_short(err.instance)} must be {_json_short(err.validator_value)}"
    elif v == "type":
        msg = f"value {_json_short(err.instance)} has the wrong type; expected {err.validator_value}"
        if isinstance(err.instance, str) and _looks_numeric(err.instance):
            msg += " (YAML reads a number without a '.' before its exponent, like 1e-3, as text: write 1.0e-3)"
    elif v == "multipleOf":
        msg = f"value {err.instance!r} must be a multiple of {err.validator_value:g}"
    elif v in ("minProperties", "maxProperties"):
        allowed = sorted((err.schema.get("properties") or {}).keys())
        msg = f"{_json_short(err.instance)} must have exactly one of the keys {', '.join(allowed)}"
    elif v == "pattern":
        msg = f"value {_json_short(err.instance)} does not match the pattern {err.validator_value}"
    elif v in ("minItems", "maxItems"):
        n = len(err.instance) if isinstance(err.instance, (list, dict, str)) else "?"
        bound = "at least" if v == "minItems" else "at most"
        msg = f"{n} entries; the allowed range is {bound} {err.validator_value} entries"
    elif v in ("minLength", "maxLength"):
        n = len(err.instance) if isinstance(err.instance, str) else "?"
        bound = "at least" if v == "minLength" else "at most"
        msg = f"value {_json_short(err.instance)} has {n} characters; the allowed length is {bound} {err.validator_value}"
    else:
        text = err.message if len(err.message) <= 200 else err.message[:197] + "..."
        msg = f"{_json_short(err.instance)}: {text}"
    return f"{path}: {msg}" + (f" (hint: {hint})" if hint else "")


def schema_problems(doc) -> list[str]:
    """Every schema violation of a parsed recipe document as ``path: message (hint: …)``."""
    schema = _schema()
    validator = jsonschema.Draft202012Validator(schema)

    out = []
    errors = sorted(validator.iter_errors(doc), key=lambda e: [str(p) for p in e.absolute_path])
    for err in errors:
        if err.validator in ("oneOf", "anyOf") and err.context:
            # the branch that got furthest (deepest path), else a summary naming the alternatives
            best = max(err.context, key=lambda e: (len(e.absolute_path), e.validator != "type"))
            if len(best.absolute_path) > len(err.absolute_path):
                out.append(_describe_error(best))
                continue
            hint = err.schema.get("description") if isinstance(err.schema, dict) else None
            what = "is not valid"
            if isinstance(err.instance, str) and _looks_numeric(err.instance):  # a number or a spectrum, given text
                what = ("has the wrong type; expected a number (YAML reads a number without a '.' before its "
                        "exponent, like 1e-3, as text: write 1.0e-3)")
            out.append(f"{fmt_path(err.absolute_path)}: value {_json_short(err.instance)} {what}"
                       + (f" (hint: {hint})" if hint else ""))
            continue
        out.append(_describe_error(err))
    # one error per path and message
    seen, uniq = set(), []
    for p in out:
        if p not in seen:
            seen.add(p)
            uniq.append(p)
    return uniq


# ----------------------------------------------------------------------------------------------
# Semantic checks
# ----------------------------------------------------------------------------------------------


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
    """(mode, grid or None, problems) of a schema-valid document's ``spectral`` block."""
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
    return problems, CustomFlake(R, T, float(C["orientation_alpha"]), tau, C.get("name", "custom-flake"), pp,
                                 C.get("orientation_distribution", "beckmann"))


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
                            f"included), got {_json_short(ct.tolist())}")
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
                        + " (hint: `flakedb species list` shows the catalogue; or describe it inline "
                          "with `custom:` and an optical_depth)")
        return problems, warnings, None
    entry = allsp[name]
    is_flake = entry["kind"] != "pigment"
    flake_only = ("orientation_alpha", "orientation_distribution", "diameter_um", "opaque", "diameter_gsd")
    pig_only = ("median_diameter_um", "gsd")
    for key in (pig_only if is_flake else flake_only):
        if key in P:
            problems.append(f"{pp}.{key}: {name!r} is a {entry['kind']}; {key} applies to "
                            f"{'pigments' if key in pig_only else 'flakes'} only (hint: remove it)")
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
        if P.get("opaque") and entry["kind"] == "mirror_flake":
            warnings.append(f"{pp}.opaque: a mirror flake is opaque already (T = 0)")
    else:
        dm = float(P.get("median_diameter_um", entry["median_diameter_um"]["value"]))
        if dm > d:
            problems.append(f"{pp}: median particle diameter {dm:g} µm exceeds {base}.thickness_um = {d:g} µm "
                            f"(hint: a layer must be thicker than its pigment particles)")
        elif mode != "mono":
            cost = _pigment_cost_problem(pp, name, P, entry, grid, ior)
            if cost:
                problems.append(cost)
    particle = CatalogParticle(
        name, entry, vf, P.get("orientation_alpha"), P.get("diameter_um"), bool(P.get("opaque", False)),
        P.get("median_diameter_um"), P.get("gsd"), pp, P.get("orientation_distribution"), P.get("diameter_gsd"))
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


def _basecoat_checks(base, L, mode, grid, allsp):
    """(problems, warnings, Basecoat): every particle checked, then the packing of the layer."""
    problems, warnings = [], []
    bc = Basecoat(float(L["thickness_um"]), float(L["ior"]), [], base, float(L.get("interface_roughness", 0.0)))
    problem = roughness_problem(bc.interface_roughness)
    if problem:
        problems.append(f"{base}.interface_roughness: {problem}")
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
            p, w, particle = _catalog_particle_checks(pp, base, P, bc.thickness_um, mode, grid, allsp, bc.ior)
            problems += p
            warnings += w
            if particle is None:
                continue
            catalogued.append(particle)
        bc.particles.append(particle)
    p, w = _packing_checks(base, catalogued)
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
            problems.append(f"{base}.material: unknown material {_json_short(m)}"
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
            p, w, bc = _basecoat_checks(base, L, mode, grid, allsp)
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


# ----------------------------------------------------------------------------------------------
# Entry points
# ----------------------------------------------------------------------------------------------


def validate_recipe(doc, catalog=None) -> list[str]:
    """Every problem of a parsed recipe document (empty: valid).  Schema first; semantics only when
    the schema passes (the checks rely on its shapes)."""
    if not isinstance(doc, dict):
        return [f"(top level): a recipe is a YAML mapping (flakedb: 1, name: …, layers: …), got {type(doc).__name__}"]
    problems = value_problems(doc) or schema_problems(doc)
    if problems:
        return problems
    return semantic_problems(doc, catalog)[0]


def parse_recipe(text: str, source="<recipe>", catalog=None) -> Recipe:
    """Parse, validate and check recipe YAML ``text``; returns a :class:`Recipe` or raises
    :class:`RecipeError` listing every problem."""
    try:
        doc = parse_yaml_text(text, source)
    except YamlFileError as exc:
        raise RecipeError(source, [exc.problem]) from None
    return recipe_from_document(doc, text, source, catalog)


def recipe_from_document(doc, text, source="<recipe>", catalog=None) -> Recipe:
    """The :class:`Recipe` of a document read by the strict loader (:func:`parse_recipe`)."""
    if not isinstance(doc, dict):
        raise RecipeError(source, validate_recipe(doc, catalog))
    problems = value_problems(doc) or schema_problems(doc)
    if problems:
        raise RecipeError(source, problems)
    problems, warnings, parts = semantic_problems(doc, catalog)
    if problems:
        raise RecipeError(source, problems)
    res = doc.get("resolution", "auto")
    return Recipe(
        name=doc["name"], mode=parts["mode"], wavelength_nm=parts["grid"],
        n=None if res == "auto" or isinstance(res, dict) else int(res), clearcoat=parts["clearcoat"], basecoats=parts["basecoats"],
        primer=parts["primer"], description=doc.get("description", ""), text=text, source=str(source),
        warnings=warnings, doc=doc, targets=dict(res) if isinstance(res, dict) else {}, metal=parts["metal"],
    )


def read_recipe_file(path):
    """``(text, document)`` of the recipe file at ``path``, read by the one strict loader
    (:func:`flakedb.paint.checks.load_yaml_file`: a regular file, at most 1 MB, no duplicate keys or
    alias bombs); :class:`RecipeError` otherwise.  Also how ``flakedb match`` reads its base."""
    try:
        return load_yaml_file(path, "recipe")
    except YamlFileError as exc:
        raise RecipeError(path, [exc.problem]) from None


def load_recipe(path, catalog=None) -> Recipe:
    """Read and check the recipe file at ``path`` (see :func:`parse_recipe`)."""
    path = Path(path)
    text, doc = read_recipe_file(path)
    return recipe_from_document(doc, text, source=path, catalog=catalog)
