"""The species and recipe fields every product path must handle (issue #35, "the store, texture model, exports and
match handle every new species and field"), enumerated from the catalogue, so a new species joins every test
without editing one.

A species is tried in a tiny recipe (n = 16, six 20 nm bands, 500-600 nm): a 10 µm basecoat with 2 % of it under
a 30 µm smooth coat over a grey primer.  A species without flakes (a pigment or a tinter) carries a metallic
flake beside it, so that the texture model and the sparkle export have something to see through it.
"""

from __future__ import annotations

import pytest
import yaml

from flakedb.paint.catalog import expand_sweeps, is_stored, load_catalog
from flakedb.paint.recipe import parse_recipe

N = 16
RANGE_NM, STEP_NM = (500, 600), 20
#: The flake a flake-less species is seen with (texture, sparkle): the paper's aluminium flake.
CARRIER = "metallic"
CATALOG = expand_sweeps(load_catalog())
SPECIES = list(CATALOG)
#: Species a catalogue sweep makes from a base species by stepping one thickness (e.g. ``pearlescent-tio2-070nm``):
#: the base's film structure at another value.
SWEEP_MEMBERS = frozenset(SPECIES) - frozenset(load_catalog()["particles"])
FLAKE_KINDS = ("interference_flake", "mirror_flake")

#: Species whose tiny solve alone takes several seconds (a coating-thickness distribution averaged over
#: 1100-1900 flake cosines: glass-flake-tio2 2.6 s, synthetic-mica-tio2-interference 4.2 s at these six bands,
#: 23-31 s at the default 81): their store / match sweeps run in the slow tier only (measured on the shared
#: 2-core machine, 2026-12-07).
SLOW_SPECIES = {
    "synthetic-mica-tio2-interference": "a three-film stack with a thickness spread: 4.2 s per tiny solve",
    "glass-flake-tio2": "a 1 µm glass substrate with a coating spread: 1900 flake cosines, 2.6 s per tiny solve",
}


def kind(species):
    return CATALOG[species]["kind"]


def is_flake(species):
    return kind(species) in FLAKE_KINDS


def stored(species):
    """Whether a store holds the species' optics (:func:`flakedb.paint.catalog.is_stored`; a tinter or a grating
    flake never)."""
    return is_stored(CATALOG[species])


def coatings(species) -> list:
    """The catalogue coating films (outside in) of an interference flake; [] for anything else."""
    return list(CATALOG[species].get("coating") or []) if kind(species) == "interference_flake" else []


def species_params(slow_ok=False):
    """pytest params of every catalogue species; those of :data:`SLOW_SPECIES` marked slow, with their reason."""
    return [pytest.param(s, id=s, marks=[pytest.mark.slow] if s in SLOW_SPECIES and not slow_ok else [])
            for s in SPECIES]


def kind_representatives(per_kind=2) -> list:
    """The first ``per_kind`` catalogue species of each kind (catalogue order): the end-to-end export sweep, whose
    code path depends on the kind and not on the species (the fast tier takes every species through the glint
    layer, the part that reads the species), at ~5 s of fitting each instead of ~200 s for all."""
    reps: dict = {}
    for s in SPECIES:
        reps.setdefault(kind(s), [])
        if len(reps[kind(s)]) < per_kind:
            reps[kind(s)].append(s)
    return [s for group in reps.values() for s in group]


def particle(species, volume_fraction=0.02, **fields) -> dict:
    return {"species": species, "volume_fraction": volume_fraction, **fields}


def document(particles, name="every", thickness_um=10.0) -> dict:
    """The tiny recipe's document with ``particles`` (dicts) in its basecoat; a species without flakes gets
    the :data:`CARRIER` flake beside it."""
    parts = list(particles)
    if not any(is_flake(p["species"]) for p in parts):
        parts.append(particle(CARRIER))
    return {"flakedb": 1, "name": name,
            "spectral": {"mode": "spectral", "range_nm": list(RANGE_NM), "step_nm": STEP_NM},
            "resolution": N,
            "layers": [{"clearcoat": {"thickness_um": 30, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": thickness_um, "ior": 1.5, "particles": parts}},
                       {"primer": {"color": "gray"}}]}


def recipe_of(doc):
    return parse_recipe(yaml.safe_dump(doc, sort_keys=False), source=f"<{doc['name']}>")


def tiny(species, **fields):
    """The tiny recipe of one species (with the carrier flake where it has none), ``fields`` on its particle."""
    return recipe_of(document([particle(species, **fields)], name=f"every-{species}"))


def field_cases() -> list:
    """Every recipe field family of a catalogue particle that changes the optics or the flakes' statistics,
    each on the first catalogue species that has it (so a field's case follows the catalogue):
    (id, species, fields).  Films: one value per coating film (1.3 × the catalogue's), the substrate 0.8 ×."""
    first = lambda pred: next(s for s in SPECIES if pred(s))
    metal = first(lambda s: kind(s) == "interference_flake" and CATALOG[s]["substrate"]["material"] == "Al"
                  and coatings(s) and s not in SLOW_SPECIES)
    multi = first(lambda s: len(coatings(s)) >= 2 and s not in SLOW_SPECIES)
    dielectric = first(lambda s: kind(s) == "interference_flake" and CATALOG[s]["substrate"]["material"] != "Al"
                       and coatings(s) and s not in SLOW_SPECIES)
    pigment = first(lambda s: kind(s) == "pigment")
    tinter = first(lambda s: kind(s) == "tinter")
    films = lambda s, f: [round(f * float(c["thickness_nm"]["value"]), 3) for c in coatings(s)]
    sub = lambda s, f: round(f * float(CATALOG[s]["substrate"]["thickness_nm"]["value"]), 3)
    return [
        ("orientation_alpha", metal, {"orientation_alpha": 0.3}),
        ("ggx", metal, {"orientation_distribution": "ggx", "orientation_alpha": 0.2}),
        ("student_t", metal, {"orientation_distribution": "student_t", "orientation_shape": 3.0,
                              "orientation_alpha": 0.2}),
        ("mixture", metal, {"orientation_alpha": 0.2, "orientation_mixture": {
            "weight": 0.3, "orientation_alpha": 0.5, "orientation_distribution": "student_t", "orientation_shape": 3.0}}),
        ("opaque", dielectric, {"opaque": True}),
        ("coating_thickness_nm-metal", metal, {"coating_thickness_nm": films(metal, 1.3)}),
        ("coating_thickness_nm-multilayer", multi, {"coating_thickness_nm": films(multi, 1.3)}),
        ("coating_thickness_rel_sd", dielectric, {"coating_thickness_rel_sd": 0.2}),
        ("substrate_thickness_nm", dielectric, {"substrate_thickness_nm": sub(dielectric, 0.8)}),
        ("substrate_thickness_rel_sd", dielectric, {"substrate_thickness_rel_sd": 0.1}),
        ("diameter", metal, {"diameter_um": 30.0, "diameter_gsd": 1.2}),
        ("pigment_size", pigment, {"median_diameter_um": 0.3, "gsd": 1.3}),
        ("weight_fraction-pigment", pigment, {"volume_fraction": None, "weight_fraction": 0.05}),
        ("weight_fraction-tinter", tinter, {"volume_fraction": None, "weight_fraction": 0.05}),
    ]


def field_recipe(species, fields):
    p = particle(species, **fields)
    if p.get("volume_fraction") is None:
        p.pop("volume_fraction")
    return recipe_of(document([p], name=f"every-field-{species}"))


def field_params():
    return [pytest.param(s, f, id=i) for i, s, f in field_cases()]
