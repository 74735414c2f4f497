"""Every catalogue species' loading given by weight (issue #35: "each species carries ... its density"; the recipe
field family ``weight_fraction``, docs/formulation.md): a species with a material has a density (its own, or a flake's
film-stack mean over materials.yaml), so a recipe may give its loading as a weight fraction, and the volume fraction
the recipe resolves is the exact conversion (flakedb.paint.formulation: φ = w M / ρ, M the film's density) by a
hand-written formula here.

Guards against: a film or substrate material without a density (before: Al2O3, sapphire, borosilicate glass,
muscovite, fluorphlogopite and powder hematite had none, so aluminium-cornflake, -silver-dollar, -vmp, the mica,
alumina and glass-flake pigments, 9 species, could not be given by weight and listed no density).
"""

from __future__ import annotations

import pytest

from flakedb.paint.species import species_density_g_cm3
from tests.every.cases import CATALOG, SPECIES, kind, particle, recipe_of, document

#: Species without a material whose density could apply: the idealised mirror flake (no material, Ergun et al.'s
#: Table 1) and tinters whose source (the RIT KM palette) gives no density, named by the catalogue's own record.
NO_DENSITY = {s for s in SPECIES if kind(s) == "mirror_flake" or (kind(s) == "tinter" and "density_g_cm3" not in CATALOG[s])}


@pytest.mark.parametrize("species", [s for s in SPECIES if s not in NO_DENSITY])
def test_every_species_loading_by_weight(species):
    rho, source = species_density_g_cm3(CATALOG[species])
    assert rho is not None and 0.5 < rho < 8.0 and source
    w = 0.05
    doc = document([{"species": species, "weight_fraction": w}], name=f"every-w-{species}")
    rec = recipe_of(doc)
    b = rec.basecoats[0]
    parts = {p.species: p for p in b.particles}
    phi_other = sum(p.volume_fraction for s, p in parts.items() if s != species)   # the carrier, by volume
    rho_other = sum(species_density_g_cm3(CATALOG[s])[0] * p.volume_fraction for s, p in parts.items() if s != species)
    from flakedb.paint.catalog import load_catalog
    rho_b = float(load_catalog()["binder"]["density_g_cm3"]["value"])
    # M = (ρ_b (1 − Σφ_v) + Σρφ_v) / (1 − w (1 − ρ_b/ρ)),  φ = w M / ρ  (flakedb.paint.formulation, module docstring)
    M = (rho_b * (1 - phi_other) + rho_other) / (1 - w * (1 - rho_b / rho))
    assert parts[species].volume_fraction == pytest.approx(w * M / rho, rel=1e-12)


def test_the_species_without_a_density_are_the_expected_ones():
    assert all(kind(s) in ("mirror_flake", "tinter") for s in NO_DENSITY)
    assert all(species_density_g_cm3(CATALOG[s])[0] is None for s in NO_DENSITY)
