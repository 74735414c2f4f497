"""The recipe's ``orientation_distribution`` (issue #21; docs/model.md §3 "Flake orientation distributions").

Guards against: a schema whose allowed names drift from the solver's registry; the field accepted on a
pigment or with an unknown name without a clear error; a catalogue or custom flake whose distribution
is dropped on the way to the solver (so GGX is computed as Beckmann), or whose optical-depth loading is
computed with the other distribution's σ_t.
"""

import copy
import json
import re

import numpy as np
import pytest

from flakedb.paint import catalog as cat
from flakedb.paint.mapping import build_paint
from flakedb.paint.components import recipe_distribution
from flakedb.paint.recipe import RecipeError, parse_recipe
from flakedb.resources import SCHEMAS_DIR
from flakedb.rt.scattering.media import FlakeMedium
from flakedb.rt.scattering.microflake import FLAKE_DISTRIBUTION_FAMILIES, FLAKE_DISTRIBUTIONS, extinction_Ergun, flake_distribution


def _recipe(particle):
    return f"""flakedb: 1
name: d
spectral: {{mode: spectral, range_nm: [500, 600], step_nm: 20}}
resolution: 16
layers:
  - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}
  - basecoat:
      thickness_um: 15
      ior: 1.5
      particles:
        - {particle}
  - primer: {{color: gray}}
"""


CUSTOM = "{custom: {kind: flake, R: 0.6, T: 0.2, orientation_alpha: 0.3%s}, optical_depth: 1.5}"


def _enums(node, out):
    if isinstance(node, dict):
        for k, v in node.items():
            if k in ("orientation_distribution", "distribution_alphas"):
                out.append(v)
            _enums(v, out)
    elif isinstance(node, list):
        for v in node:
            _enums(v, out)
    return out


def test_schemas_name_the_registry():
    # the recipe and the catalogue name the registry's fixed entries and its shape family (student_t, with
    # orientation_shape; the mix family is the recipe's orientation_mixture object)
    for name, extra in (("recipe", ["student_t"]), ("catalog", ["student_t"])):
        found = _enums(json.loads((SCHEMAS_DIR / f"{name}.schema.json").read_text()), [])
        assert found and all(sorted(f["enum"]) == sorted([*FLAKE_DISTRIBUTIONS, *extra]) for f in found), name
    assert set(FLAKE_DISTRIBUTION_FAMILIES) == {"student_t", "mix"}
    store = _enums(json.loads((SCHEMAS_DIR / "store.schema.json").read_text()), [])
    names = store[0]["additionalProperties"]["propertyNames"]["anyOf"]
    assert sorted(names[0]["enum"]) == sorted(set(FLAKE_DISTRIBUTIONS) - {"beckmann"})
    # every canonical parametrised name is a valid store key, and a misspelt one is not
    for d in ("student_t(2.5)", "student_t(1000)", "mix(ggx,0.25,student_t(1.5),0.05)", "mix(beckmann,0.5,ggx,2)"):
        assert any(re.search(a["pattern"], flake_distribution(d).name) for a in names[1:]), d
    assert not any(re.search(a["pattern"], "student_t(2.5") for a in names[1:])


def test_bad_values_are_refused_with_the_field_named():
    with pytest.raises(RecipeError, match="orientation_distribution") as e:
        parse_recipe(_recipe("{species: metallic, volume_fraction: 0.05, orientation_distribution: phong}"))
    assert "ggx" in str(e.value)
    with pytest.raises(RecipeError, match="orientation_distribution: 'cadmium-yellow' is a pigment"):
        parse_recipe(_recipe("{species: cadmium-yellow, volume_fraction: 0.05, orientation_distribution: ggx}"))


def test_catalogue_flake_reaches_the_solver():
    beck = build_paint(parse_recipe(_recipe("{species: metallic, volume_fraction: 0.05}")))
    ggx = build_paint(parse_recipe(_recipe("{species: metallic, volume_fraction: 0.05, orientation_distribution: ggx}")))
    mb, mg = beck.slabs[0].medium, ggx.slabs[0].medium
    assert isinstance(mb, FlakeMedium) and mb.distribution == "beckmann"
    assert mg.distribution == "ggx" and mg.alpha == mb.alpha and mg.a_rho_per_um == mb.a_rho_per_um
    assert ggx.components[0]["orientation_distribution"] == "ggx"
    assert beck.components[0]["orientation_distribution"] == "beckmann"
    x = np.array([1.0, 0.3])
    assert not np.allclose(mg.sigma_t(x), mb.sigma_t(x), rtol=1e-3)


def test_custom_flake_loading_uses_its_distribution():
    for dist, extra in (("beckmann", ""), ("ggx", ", orientation_distribution: ggx")):
        paint = build_paint(parse_recipe(_recipe(CUSTOM % extra)))
        med = paint.slabs[0].medium
        assert med.distribution == dist and paint.components[0]["orientation_distribution"] == dist
        # aρ chosen so that σ_t(μ = 1) · d = τ with the flake's own distribution
        st = extinction_Ergun(np.array([1.0]), 0.3, med.optics, med.a_rho_per_um, distribution=dist)[0, 0]
        assert st * 15.0 == pytest.approx(1.5, rel=1e-12)


def test_catalogue_can_state_the_distribution():
    doc = copy.deepcopy(cat.load_catalog())
    doc["particles"]["metallic"]["orientation_distribution"] = "ggx"
    assert cat.validate_catalog(doc) == []
    bad = copy.deepcopy(doc)
    bad["particles"]["metallic"]["orientation_distribution"] = "cauchy"
    assert any("orientation_distribution" in p for p in cat.validate_catalog(bad))
    rec = parse_recipe(_recipe("{species: metallic, volume_fraction: 0.05}"), catalog=doc)
    p = rec.basecoats[0].particles[0]
    assert recipe_distribution(p) == "ggx"
    over = parse_recipe(_recipe("{species: metallic, volume_fraction: 0.05, orientation_distribution: beckmann}"),
                        catalog=doc)
    assert recipe_distribution(over.basecoats[0].particles[0]) == "beckmann"
    assert build_paint(rec, catalog=doc).slabs[0].medium.distribution == "ggx"
