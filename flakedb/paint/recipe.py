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

from pathlib import Path

from flakedb.paint.checks import YamlFileError, load_yaml_file, parse_yaml_text, value_problems
from flakedb.paint.recipe_checks import METAL_K_WARNING, semantic_problems, spectral_grid_of  # noqa: F401  (re-exported)
from flakedb.paint.recipe_model import (  # noqa: F401  (re-exported)
    DEFAULT_SPECTRAL,
    DILUTE_WARNING,
    FORMAT_VERSION,
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
    Recipe,
    RecipeError,
    Spectrum,
)
from flakedb.paint.recipe_schema import fmt_path, json_short, repo_root, schema_path, schema_problems  # noqa: F401  (re-exported)


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
    :class:`RecipeError` listing every problem.

    >>> text = "flakedb: 1\\nname: grey\\nresolution: 32\\nlayers:\\n  - primer: {color: gray}\\n"
    >>> r = parse_recipe(text)
    >>> r.name, r.n, r.mode, r.primer.albedo
    ('grey', 32, 'spectral', 0.18)
    >>> try:
    ...     parse_recipe(text.replace("32", "33"))
    ... except RecipeError as e:
    ...     print(e.problems[0][:30])
    resolution: value 33 is not va
    """
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
