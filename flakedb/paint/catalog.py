"""The particle catalogue (``catalog/particles.yaml``): reading, validation and sweeps.

Catalogue files are YAML validated against ``schemas/catalog.schema.json`` (JSON Schema 2020-12,
no unknown keys), then checked for what a schema cannot say (known materials, a flake's total
thickness equal to its film stack, sweep bases and parameters that exist).  Errors name the entry
and the field (``particles.metallic.coating[0].thickness_nm``) and say what to do.  A *species* is
one entry of the catalogue, or one member of a sweep (:func:`expand_sweeps`).
"""

from __future__ import annotations

import copy
import json
import os
import re
from collections.abc import Mapping
from pathlib import Path

import jsonschema
import numpy as np

from flakedb.optics.mie import default_n_quad
from flakedb.paint.checks import YamlFileError, load_yaml_file, value_problems
from flakedb.rt.scattering.microflake import DEFAULT_DISTRIBUTION, STUDENT_T_SHAPE_RANGE, flake_distribution
from flakedb.paint.materials import material_names
from flakedb.resources import CATALOG_DIR, PACKAGE_DIR, SCHEMAS_DIR


#: Largest catalogue file [bytes] (the shipped one is 7 kB).
MAX_CATALOG_BYTES = 5_000_000


class CatalogError(ValueError):
    """The catalogue file is invalid; the message lists every problem with its path."""


def repo_root() -> Path:
    """The package folder (holds ``catalog/`` and ``schemas/``, see :mod:`flakedb.resources`)."""
    return PACKAGE_DIR


def default_catalog_path() -> Path:
    """``$FLAKEDB_CATALOG`` if set, else ``catalog/particles.yaml`` of this checkout."""
    env = os.environ.get("FLAKEDB_CATALOG")
    return Path(env) if env else CATALOG_DIR / "particles.yaml"


def schema_path() -> Path:
    return SCHEMAS_DIR / "catalog.schema.json"


def _fmt_path(parts) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


def validate_catalog(doc) -> list[str]:
    """All problems of a parsed catalogue as 'path: message' strings (empty list: valid)."""
    with open(schema_path(), encoding="utf-8") as f:
        schema = json.load(f)
    validator = jsonschema.Draft202012Validator(schema)
    problems = []
    for err in sorted(validator.iter_errors(doc), key=lambda e: [str(p) for p in e.absolute_path]):
        errs = [err]
        if err.validator in ("oneOf", "anyOf") and err.context:
            # report the branch that got furthest instead of "is not valid under any of the given schemas"
            errs = [max(err.context, key=lambda e: len(e.absolute_path))]
        for e in errs:
            why = e.schema.get("description") if isinstance(e.schema, dict) else None
            problems.append(f"{_fmt_path(e.absolute_path)}: {e.message}" + (f" (allowed: {why})" if why else ""))
    if problems:
        return problems
    problems += _semantic_problems(doc)
    return problems


#: Kinds whose optics the precomputed store holds (flakedb build projects them).  A ``tinter`` (optics per
#: unit volume fraction, no Mie, no thin film: docs/calibration.md) is always computed directly.
STORED_KINDS = ("interference_flake", "mirror_flake", "pigment")
def is_stored(entry: dict) -> bool:
    """Whether a store holds this catalogue entry's optics: a kind of :data:`STORED_KINDS` without a ``grating``
    (a grating flake's kernel depends on each band's wavelength and is computed directly by compose: the store's
    flake factors are the specular kernel's, docs/model.md §3)."""
    return entry["kind"] in STORED_KINDS and "grating" not in entry


#: The coefficient tables of a tinter entry (σ_a/φ, σ_s/φ in 1/µm; schemas/catalog.schema.json).
TINTER_TABLES = ("specific_absorption_per_um", "specific_scattering_per_um")


#: Largest memory the Mie size average of one pigment may ask for [bytes] (8 GiB), checked before any work.
MAX_PIGMENT_BYTES = 8 * 1024 ** 3
#: Bytes per (band, size node, phase angle) of that average: the amplitudes S1, S2 (complex) and their
#: temporaries.  Measured (cadmium yellow, 81 bands, 361 angles): d_med 0.3 µm / gsd 1.5 (1133 nodes)
#: peaks at 1.99 GB RSS, estimate 1.97 GiB; 0.6 µm (2265 nodes) 3.76 GB, estimate 3.95 GiB.
PIGMENT_BYTES_PER_POINT = 64
#: Phase angles of a pigment's table (flakedb.paint.components.phase_cos_grid: 0.5° steps).
PIGMENT_PHASE_ANGLES = 361
#: The grid a catalogue pigment is checked on (the default build grid, 380-780 nm in 5 nm steps).
DEFAULT_GRID_NM = np.arange(380.0, 781.0, 5.0)


def pigment_memory_bytes(median_diameter_um, gsd, wavelength_nm, n_binder) -> float:
    """Estimated peak memory [bytes] of a pigment's Mie size average (flakedb.optics.mie.lognormal_pigment
    with the phase table): bands × size nodes (:func:`flakedb.optics.mie.default_n_quad`) × phase angles ×
    :data:`PIGMENT_BYTES_PER_POINT` (measured, see there)."""
    wl = np.atleast_1d(np.asarray(wavelength_nm, float))
    q = default_n_quad(float(np.pi * n_binder / (wl.min() * 1e-3)), float(median_diameter_um), float(gsd))
    return float(wl.size) * q * PIGMENT_PHASE_ANGLES * PIGMENT_BYTES_PER_POINT


#: A species name (the schema's ``$defs/name``): it also names files, so no separators.
_NAME_RE = re.compile(r"[a-z0-9][a-z0-9-]*")

#: Longest species name [characters] (a name also names store files).
MAX_SPECIES_NAME = 64


def species_name_problem(name) -> str | None:
    """None for a valid species name (the schema's ``$defs/name``, at most :data:`MAX_SPECIES_NAME` characters),
    else why not, with the name cut to 40 characters:

    >>> species_name_problem("cadmium-yellow-lab") is None, species_name_problem("Cadmium Yellow (lab)")
    (True, "'Cadmium Yellow (lab)' is not a species name: lower-case letters, digits and '-', starting with a letter or digit (e.g. 'cadmium-yellow-lab')")
    """
    s = name if isinstance(name, str) else str(name)
    shown = repr(s) if len(s) <= 40 else repr(s[:37]) + "... (" + f"{len(s):,} characters)"
    if len(s) > MAX_SPECIES_NAME:
        return f"{shown} is not a species name: at most {MAX_SPECIES_NAME} characters"
    if not isinstance(name, str) or not _NAME_RE.fullmatch(s):
        return (f"{shown} is not a species name: lower-case letters, digits and '-', starting with a letter or "
                f"digit (e.g. 'cadmium-yellow-lab')")
    return None


#: Catalogue fields that are formulation data (weight ↔ volume fractions, the CPVC estimate), not optics:
#: a store is built from, and named by, the entry without them (:func:`optical_entry`).
FORMULATION_FIELDS = ("density_g_cm3", "oil_absorption_g_100g")


def optical_entry(entry: dict) -> dict:
    """``entry`` (a species or the binder) without :data:`FORMULATION_FIELDS`: what its optics depend on."""
    return {k: v for k, v in entry.items() if k not in FORMULATION_FIELDS}


#: Most members one sweep may generate (each is a species a build projects: the shipped sweep has 8).
MAX_SWEEP_MEMBERS = 1000


def catalog_distribution(entry) -> str:
    """The flake-normal distribution of a catalogue flake ``entry``, as the canonical name of
    :data:`flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS`: its ``orientation_distribution`` (default Beckmann,
    every entry written before the field), ``student_t`` with its ``orientation_shape`` value γ as
    ``student_t(γ)``.  The one place a catalogue entry's orientation fields become a name (recipes, the
    store's plan and the build request read it)."""
    fam = entry.get("orientation_distribution", DEFAULT_DISTRIBUTION)
    if fam == "student_t":
        return flake_distribution(f"student_t({float(entry['orientation_shape']['value'])!r})").name
    return str(fam)


def _semantic_problems(doc) -> list[str]:
    known = set(material_names())
    out = []

    def check_material(path, name):
        if name not in known:
            out.append(f"{path}: unknown material {name!r}; known: {', '.join(sorted(known))}")

    check_material("binder.material", doc["binder"]["material"])
    for name, e in doc["particles"].items():
        base = f"particles.{name}"
        if e["kind"] == "interference_flake":
            check_material(f"{base}.substrate.material", e["substrate"]["material"])
            for i, film in enumerate(e["coating"]):
                check_material(f"{base}.coating[{i}].material", film["material"])
            total_um = _stack_total_um(e)
            if not np.isclose(e["thickness_um"]["value"], total_um, rtol=1e-6, atol=1e-9):
                out.append(
                    f"{base}.thickness_um: value {e['thickness_um']['value']} µm differs from the film "
                    f"stack's total {total_um:.6g} µm (2 × coating + substrate); make them agree"
                )
        if e["kind"] != "pigment":
            fam, shape = e.get("orientation_distribution", DEFAULT_DISTRIBUTION), e.get("orientation_shape")
            if fam == "student_t" and shape is None:
                out.append(f"{base}.orientation_shape: missing; orientation_distribution student_t needs its tail "
                           f"shape gamma, {STUDENT_T_SHAPE_RANGE[0]:g} ≤ gamma ≤ {STUDENT_T_SHAPE_RANGE[1]:g} "
                           f"(hint: orientation_shape: {{value: 2.5, source: ...}}; 2 is GGX)")
            elif fam != "student_t" and shape is not None:
                out.append(f"{base}.orientation_shape: value {shape['value']:g} applies to orientation_distribution "
                           f"student_t only, not {fam!r} (hint: set orientation_distribution: student_t or remove it)")
        if e["kind"] == "pigment":
            check_material(f"{base}.material", e["material"])
            af = e.get("absorption_factor")
            if af is not None and len(af["wavelength_nm"]) != len(af["value"]):
                out.append(f"{base}.absorption_factor: wavelength_nm has {len(af['wavelength_nm'])} entries, "
                           f"value {len(af['value'])}")
            elif af is not None and np.any(np.diff(af["wavelength_nm"]) <= 0):
                out.append(f"{base}.absorption_factor.wavelength_nm: must be strictly increasing")
            need = pigment_memory_bytes(e["median_diameter_um"]["value"], e["gsd"]["value"], DEFAULT_GRID_NM, 1.5)
            if need > MAX_PIGMENT_BYTES:
                out.append(f"{base}.median_diameter_um = {e['median_diameter_um']['value']:g} µm with {base}.gsd = "
                           f"{e['gsd']['value']:g}: its Mie size average needs about {need / 2**30:,.0f} GiB over "
                           f"380-780 nm; the limit is {MAX_PIGMENT_BYTES / 2**30:.0f} GiB (hint: a smaller median "
                           f"diameter or gsd: pigments are 0.05-5 µm with gsd 1.2-2)")
        elif e["kind"] == "tinter":
            for key in TINTER_TABLES:
                wl, val = e[key]["wavelength_nm"], e[key]["value"]
                if len(wl) != len(val):
                    out.append(f"{base}.{key}: wavelength_nm has {len(wl)} entries, value {len(val)} (make them equal)")
                elif np.any(np.diff(wl) <= 0):
                    out.append(f"{base}.{key}.wavelength_nm: must be strictly increasing")
        elif e["kind"] == "mirror_flake" and "wavelength_nm" in e["albedo"]:
            wl, val = e["albedo"]["wavelength_nm"], e["albedo"]["value"]
            if len(wl) != len(val):
                out.append(f"{base}.albedo: wavelength_nm has {len(wl)} entries, value {len(val)}")
            elif np.any(np.diff(wl) <= 0):
                out.append(f"{base}.albedo.wavelength_nm: must be strictly increasing")
    names = set(doc["particles"])
    for sname, s in (doc.get("sweeps") or {}).items():
        base = f"sweeps.{sname}"
        entry = doc["particles"].get(s["base"])
        if entry is None:
            out.append(f"{base}.base: no particle {s['base']!r}; particles: {', '.join(sorted(names))}")
            continue
        if entry["kind"] != "interference_flake":
            out.append(f"{base}.base: {s['base']!r} is a {entry['kind']}; sweeps step film thicknesses of interference flakes")
            continue
        m = re.fullmatch(r"coating\[(\d+)\]\.thickness_nm", s["parameter"])
        if m and int(m.group(1)) >= len(entry["coating"]):
            out.append(f"{base}.parameter: {s['parameter']} but {s['base']!r} has {len(entry['coating'])} coating film(s)")
        v = s["values_nm"]
        if v["stop"] < v["start"]:
            out.append(f"{base}.values_nm: stop {v['stop']} < start {v['start']}")
            continue
        count = (v["stop"] - v["start"]) // v["step"] + 1
        if count > MAX_SWEEP_MEMBERS:
            out.append(f"{base}.values_nm: start {v['start']}, stop {v['stop']}, step {v['step']} make {count:,} "
                       f"members; the limit is {MAX_SWEEP_MEMBERS} (each member is a species every build projects; "
                       f"hint: a larger step)")
            continue
        try:
            generated = [s["name_format"].format(value=x) for x in _sweep_values(v)]
        except (ValueError, KeyError, IndexError) as exc:
            out.append(f"{base}.name_format: {s['name_format']!r} does not format an integer value ({exc})")
            continue
        for g in generated:
            if not _NAME_RE.fullmatch(g):
                out.append(f"{base}.name_format: generates the name {g!r}; a species name is lower-case letters, "
                           f"digits and '-' (it names files, e.g. NAME-optics.png)")
                break
            if g in names:
                out.append(f"{base}: generated name {g!r} is already used")
            names.add(g)
    return out


def load_catalog(path=None) -> dict:
    """Read and validate a particle catalogue (default :func:`default_catalog_path`).

    Returns the parsed document (a dict with ``version``, ``binder``, ``particles`` and optionally
    ``sweeps``).  Raises :class:`CatalogError` listing every problem as ``path: message``.
    """
    path = Path(path) if path is not None else default_catalog_path()
    try:  # the recipe's strict loader: regular files only, size-limited, no duplicate keys or alias bombs
        _, doc = load_yaml_file(path, "catalogue", MAX_CATALOG_BYTES)
    except YamlFileError as exc:
        raise CatalogError(f"{path}: invalid particle catalogue: {exc.problem}") from None
    problems = value_problems(doc) or validate_catalog(doc)
    if problems:
        raise CatalogError(f"{path}: invalid particle catalogue:\n  " + "\n  ".join(problems))
    return doc


def _sweep_values(v) -> list[int]:
    return list(range(int(v["start"]), int(v["stop"]) + 1, int(v["step"])))


def _stack_total_um(entry) -> float:
    return (2 * sum(f["thickness_nm"]["value"] for f in entry["coating"]) + entry["substrate"]["thickness_nm"]["value"]) / 1000.0


def expand_sweeps(catalog: dict) -> "SpeciesView":
    """All species by name: the catalogue's particles plus one entry per sweep value.

    A sweep member is a deep copy of its base with the stepped thickness set (its ``source`` names
    the sweep) and ``thickness_um`` recomputed from the stack, named by the sweep's
    ``name_format`` (e.g. ``pearlescent-tio2-070nm``).  Insertion order: particles, then sweeps.
    Every entry is a deep copy (the caller may change it), made when it is first looked up
    (:class:`SpeciesView`): a recipe's check reads a few of the catalogue's species, not all of them.
    """
    makers = {name: (lambda e=e: copy.deepcopy(e)) for name, e in catalog["particles"].items()}
    for sname, s in (catalog.get("sweeps") or {}).items():
        for value in _sweep_values(s["values_nm"]):
            makers[s["name_format"].format(value=value)] = (
                lambda sname=sname, s=s, value=value: _sweep_member(catalog, sname, s, value))
    return SpeciesView(makers)


def _sweep_member(catalog, sname, s, value) -> dict:
    base = catalog["particles"][s["base"]]
    e = copy.deepcopy(base)
    src = f"sweep {sname}: {s['source']}"
    m = re.fullmatch(r"coating\[(\d+)\]\.thickness_nm", s["parameter"])
    film = e["coating"][int(m.group(1))] if m else e["substrate"]
    film["thickness_nm"] = {"value": value, "source": src}
    e["thickness_um"] = {"value": _stack_total_um(e), "source": "total of the film stack"}
    e.pop("density_g_cm3", None)   # the base's density is its own stack's, not this member's
    e["description"] = f"{base['description']}; {s['parameter']} = {value} nm"
    return e


class SpeciesView(Mapping):
    """name → species entry (:func:`expand_sweeps`): each entry made (a deep copy) on its first lookup and the
    same object on every later one, as a dict of copies made beforehand would give."""

    def __init__(self, makers: dict):
        self._makers = makers
        self._made: dict = {}

    def __getitem__(self, name):
        if name not in self._made:
            self._made[name] = self._makers[name]()  # KeyError for an unknown name, as a dict
        return self._made[name]

    def __iter__(self):
        return iter(self._makers)

    def __len__(self):
        return len(self._makers)

    def __contains__(self, name):
        return name in self._makers


def species_names(catalog: dict | None = None) -> list[str]:
    """Names of every species (particles and sweep members), in catalogue order."""
    return list(expand_sweeps(catalog if catalog is not None else load_catalog()))


def get_species(name: str, catalog: dict | None = None) -> dict:
    """The entry of one species; ValueError listing the known names when there is none.

    >>> entry = get_species("gray-mirror")
    >>> entry["kind"], entry["albedo"]["value"]
    ('mirror_flake', 0.5)
    >>> get_species("grey-mirror")
    Traceback (most recent call last):
    ...
    ValueError: unknown species 'grey-mirror'; known species: metallic, pearlescent, gray-mirror, ...
    """
    allsp = expand_sweeps(catalog if catalog is not None else load_catalog())
    if name not in allsp:
        raise ValueError(f"unknown species {name!r}; known species: {', '.join(allsp)} (a species of your own "
                         f"catalogue: --catalog FILE.yaml or $FLAKEDB_CATALOG)")
    return allsp[name]
