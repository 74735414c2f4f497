"""Every catalogue species and every recipe field family through the store (issue #35): the build plan names what
the recipe will ask for, and a tiny store built for the recipe (`flakedb build --recipe`) composes the same paint
as the direct solve, within the store's stated accuracy (docs/store.md, "Accuracy": max |Δf| ≤ 1e-3 of max f,
ΔE00 ≤ 0.05 at the report's angles; measured here ≤ 3.2e-5 and ≤ 3e-4).

Guards against: a species the store cannot hold or holds under another name than the one compose asks for; a
tinter that reaches the store (it is always computed directly, and a store compose must still give its optics);
a recipe field that the store silently ignores (serving the catalogue's optics for a recipe that changed them), or
refuses although a build for the recipe could hold it (before this test: every film override, coating or substrate
thickness and spread, and a pigment's size distribution were refused, "compose without --store", while the
refusal told the user to run the `flakedb build --recipe` that could not add them).
"""

from __future__ import annotations

import numpy as np
import pytest

from flakedb.colour.colorimetry import delta_E_2000
from flakedb.paint.components import store_key
from flakedb.paint.mapping import catalog_species
from flakedb.pipelines.build import build, request_for_recipe
from flakedb.solve.pipeline import solve_recipe, solve_reported
from flakedb.paint.texture_inputs import texture_stack
from flakedb.solve.store_context import StoreContext, store_problems
from flakedb.store import versions as st
from tests.every.cases import (CARRIER, N, document, field_params, field_recipe, is_flake, particle, recipe_of,
                               species_params, stored, tiny)

#: The store's acceptance against the direct compose (docs/store.md, "Accuracy").
F_REL, DE00 = 1e-3, 0.05
PHI = np.linspace(0.0, np.pi, 9)


def _lab(reported):
    return np.array([[g["L"], g["a"], g["b"]] for g in reported.report["geometries"]])


def _through_the_store(rec, tmp_path):
    """Plan, build and compose ``rec`` from a tiny store made for it; returns (direct, stored) reported solves."""
    req = request_for_recipe(rec)
    keys = {store_key(p) for p in catalog_species(rec)}
    assert set(req.species) == keys                      # the request holds exactly what compose will ask for
    plan = st.plan_build(req)
    named = {t.species for t in plan.tasks}
    assert keys <= named, f"plan {sorted(named)} lacks {sorted(keys - named)}"
    for p in catalog_species(rec):
        if p.is_flake:                                   # the flake's task is at the recipe's (distribution, α)
            prefix = [t.prefix for t in plan.tasks if t.species == store_key(p)]
            assert any(t.endswith(f"a{float(p.orientation_alpha or p.entry['orientation_alpha']['value']):.6g}")
                       for t in prefix), prefix
    url = str(tmp_path / "store")
    assert build(req, url, scheduler="sync")["status"] == "built"
    version = st.open_version(url)
    assert store_problems(version, rec, N) == []
    direct = solve_reported(rec, N, verify=False)
    from_store = solve_reported(rec, N, store=url, verify=False)
    # the texture model takes a pigment's cross-sections from the same store entry the solve reads
    ctx = StoreContext.open_for_recipe(url, rec, N)
    (own, _), (via, _) = texture_stack(rec), texture_stack(rec, stored=ctx)
    for a, b in zip(own.absorbers, via.absorbers):
        np.testing.assert_allclose(b.sigma_per_um, a.sigma_per_um, rtol=1e-3)
    assert "store" in from_store.solved.paint.info and "store" not in direct.solved.paint.info
    return direct, from_store


def _agree(direct, from_store):
    fd = direct.solved.stack.eval_nodes(PHI)
    fs = from_store.solved.stack.eval_nodes(PHI)
    assert np.all(np.isfinite(fs))
    rel = float(np.abs(fs - fd).max() / np.abs(fd).max())
    de = float(delta_E_2000(_lab(from_store), _lab(direct)).max())
    assert rel <= F_REL and de <= DE00, (rel, de)
    return rel, de


@pytest.mark.parametrize("species", species_params())
def test_every_species_composes_from_a_store_as_directly(species, tmp_path):
    rec = tiny(species)
    if not stored(species):   # a tinter or a grating flake: not in any store, computed directly on both paths beside
        if is_flake(species):  # a stored carrier (a flake-less species has it already)
            rec = recipe_of(document([particle(species), particle(CARRIER)], name=f"every-{species}-carried"))
        assert species not in request_for_recipe(rec).species
    direct, from_store = _through_the_store(rec, tmp_path)
    _agree(direct, from_store)


@pytest.mark.parametrize("species,fields", field_params())
def test_every_field_composes_from_a_store_as_directly(species, fields, tmp_path):
    rec = field_recipe(species, fields)
    direct, from_store = _through_the_store(rec, tmp_path)
    _agree(direct, from_store)
    # and the field reached the optics: the same recipe without it is another paint (diameters: texture only)
    base = solve_reported(tiny(species), N, verify=False)
    moved = float(delta_E_2000(_lab(base), _lab(direct)).max())
    if set(fields) <= {"diameter_um", "diameter_gsd"}:
        assert moved < 1e-9
    else:
        assert moved > 1e-3, f"{fields} does not change the paint (max ΔE00 {moved:.2g})"


def test_a_film_override_is_its_own_species_in_the_store(tmp_path):
    """The catalogue species and the same species with the recipe's films are two species of a version, each served
    to the recipe that asks for it; a store built for one refuses the other with the build command that adds it."""
    films = [{"coating_thickness_nm": [12.0]}, {"coating_thickness_nm": [13.0]}]
    recs = [field_recipe("metallic", f) for f in films]
    keys = [store_key(next(p for p in catalog_species(r) if p.species == "metallic")) for r in recs]
    assert len(set(keys)) == 2 and all(k.startswith("metallic~") for k in keys)
    assert keys[0] == store_key(next(p for p in catalog_species(field_recipe("metallic", films[0]))
                                     if p.species == "metallic"))   # deterministic: the same films, the same key
    url = str(tmp_path / "s")
    assert build(request_for_recipe(recs[0]), url, scheduler="sync")["status"] == "built"
    v = st.open_version(url)
    assert store_problems(v, recs[0], N) == []
    probs = store_problems(v, recs[1], N)
    assert len(probs) == 1 and "with the recipe's coating_thickness_nm" in probs[0] and keys[1] in probs[0]
    # the plain catalogue species is not in this store either (only what the recipe needs was built)
    assert any("'metallic'" in p and "not in the store" in p for p in store_problems(v, tiny("metallic"), N))
