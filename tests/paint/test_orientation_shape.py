"""The recipe's orientation shape fields (issue #35 item 3): ``orientation_distribution: student_t`` with
``orientation_shape`` γ, and ``orientation_mixture`` (a second population: weight, orientation_alpha,
orientation_distribution, orientation_shape), on catalogue and custom flakes.

Guards against: fields that are dropped between the recipe and the solver (a Student-t or mixture paint
computed as Beckmann), a name that is not the registry's canonical one (the store would miss its
factors), a custom flake's optical-depth loading computed with another distribution's σ_t, values outside
the physical bounds accepted or refused without the field path, the value and the range, and a recipe
with the new fields that does not compose to the very stack tests/reference/test_shape_vs_montecarlo.py
validates against the Monte Carlo reference.
"""

import numpy as np
import pytest

from flakedb.paint.mapping import build_paint, solve_paint
from flakedb.paint.components import recipe_distribution
from flakedb.paint.recipe import RecipeError, parse_recipe
from flakedb.rt.scattering.microflake import FlakeOptics, extinction_Ergun
from flakedb.rt.adding.stack import SolverSettings, solve_stack
from tests.paint.test_orientation_distribution import CUSTOM, _recipe
from tests.reference.test_shape_vs_montecarlo import MIX, shape_case

MET = "{species: metallic, volume_fraction: 0.05%s}"


def _dist(extra, particle=MET):
    rec = parse_recipe(_recipe(particle % extra))
    return recipe_distribution(rec.basecoats[0].particles[0]), rec


def test_catalogue_flake_fields_reach_the_solver():
    d, rec = _dist(", orientation_distribution: student_t, orientation_shape: 2.50, orientation_alpha: 0.2")
    assert d == "student_t(2.5)"
    paint = build_paint(rec)
    med = paint.slabs[0].medium
    assert med.distribution == "student_t(2.5)" and paint.components[0]["orientation_distribution"] == "student_t(2.5)"
    x = np.array([1.0, 0.3])
    sig = {k: build_paint(parse_recipe(_recipe(MET % f", orientation_alpha: 0.2{e}"))).slabs[0].medium.sigma_t(x)
           for k, e in (("b", ""), ("g", ", orientation_distribution: ggx"),
                        ("t2", ", orientation_distribution: student_t, orientation_shape: 2"))}
    assert not np.allclose(med.sigma_t(x), sig["b"], rtol=1e-3) and not np.allclose(med.sigma_t(x), sig["g"], rtol=1e-3)
    np.testing.assert_allclose(sig["t2"], sig["g"], rtol=1e-11)  # γ = 2 is GGX through the whole recipe path


def test_mixture_fields_reach_the_solver():
    extra = (", orientation_alpha: 0.1, orientation_mixture: {weight: 0.25, orientation_alpha: 0.5, "
             "orientation_distribution: student_t, orientation_shape: 1.8}")
    d, rec = _dist(extra)
    assert d == "mix(beckmann,0.25,student_t(1.8),0.5)"
    med = build_paint(rec).slabs[0].medium
    x = np.array([1.0, 0.6, 0.2])
    one = lambda e: build_paint(parse_recipe(_recipe(MET % e))).slabs[0].medium.sigma_t(x)  # noqa: E731
    ref = 0.75 * one(", orientation_alpha: 0.1") + 0.25 * one(
        ", orientation_alpha: 0.5, orientation_distribution: student_t, orientation_shape: 1.8")
    np.testing.assert_allclose(med.sigma_t(x), ref, rtol=1e-13)
    # the second population defaults to Beckmann; the first is the particle's own distribution
    d, _ = _dist(", orientation_distribution: ggx, orientation_mixture: {weight: 0.5, orientation_alpha: 0.05}")
    assert d == "mix(ggx,0.5,beckmann,0.05)"


def test_custom_flake_loading_uses_its_distribution():
    for extra, dist in ((", orientation_distribution: student_t, orientation_shape: 4", "student_t(4.0)"),
                        (", orientation_mixture: {weight: 0.4, orientation_alpha: 0.9, orientation_distribution: ggx}",
                         "mix(beckmann,0.4,ggx,0.9)")):
        paint = build_paint(parse_recipe(_recipe(CUSTOM % extra)))
        med = paint.slabs[0].medium
        assert med.distribution == dist and paint.components[0]["orientation_distribution"] == dist
        st = extinction_Ergun(np.array([1.0]), 0.3, med.optics, med.a_rho_per_um, distribution=dist)[0, 0]
        assert st * 15.0 == pytest.approx(1.5, rel=1e-12)


@pytest.mark.parametrize("particle, extra, expect", [
    (MET, ", orientation_distribution: student_t",
     r"particles\[0\]\.orientation_shape: missing; .*student_t needs its tail shape gamma, 1\.5 ≤ gamma ≤ 1000"),
    (MET, ", orientation_distribution: student_t, orientation_shape: 1.2",
     r"particles\[0\]\.orientation_shape: value 1\.2 is outside the allowed range 1\.5 ≤ value ≤ 1000"),
    (MET, ", orientation_distribution: student_t, orientation_shape: 5000",
     r"particles\[0\]\.orientation_shape: value 5000 is outside the allowed range 1\.5 ≤ value ≤ 1000"),
    (MET, ", orientation_distribution: ggx, orientation_shape: 3",
     r"particles\[0\]\.orientation_shape: value 3 applies to the student_t distribution only, but "
     r".*orientation_distribution is 'ggx'"),
    (MET, ", orientation_mixture: {weight: 0, orientation_alpha: 0.3}",
     r"particles\[0\]\.orientation_mixture\.weight: value 0 is outside the allowed range 0 < value < 1"),
    (MET, ", orientation_mixture: {weight: 0.5, orientation_alpha: 3}",
     r"particles\[0\]\.orientation_mixture\.orientation_alpha: value 3 is outside the allowed range 0\.001 ≤ value ≤ 2"),
    (MET, ", orientation_mixture: {weight: 0.5}", r"particles\[0\]\.orientation_mixture.*orientation_alpha"),
    (MET, ", orientation_mixture: {weight: 0.5, orientation_alpha: 0.3, orientation_distribution: student_t}",
     r"particles\[0\]\.orientation_mixture\.orientation_shape: missing"),
    (MET, ", orientation_mixture: {weight: 0.5, orientation_alpha: 0.3, orientation_distribution: cauchy}",
     r"orientation_mixture\.orientation_distribution: value \"cauchy\" is not one of beckmann, ggx, student_t"),
    ("{species: cadmium-yellow, volume_fraction: 0.05%s}", ", orientation_shape: 3",
     r"orientation_shape: 'cadmium-yellow' is a pigment; orientation_shape applies to flakes only"),
    ("{species: cadmium-yellow, volume_fraction: 0.05%s}", ", orientation_mixture: {weight: 0.5, orientation_alpha: 0.3}",
     r"orientation_mixture: 'cadmium-yellow' is a pigment"),
    (CUSTOM, ", orientation_shape: 3",
     r"particles\[0\]\.custom\.orientation_shape: value 3 applies to the student_t distribution only"),
])
def test_bad_values_are_refused_with_field_value_and_range(particle, extra, expect):
    with pytest.raises(RecipeError, match=expect):
        parse_recipe(_recipe(particle % extra))


def test_recipe_composes_to_the_monte_carlo_validated_stack():
    """The mixture-paint case of tests/reference/test_shape_vs_montecarlo.py (solver within 1.1 σ of the
    Monte Carlo) written as a recipe: the same stack to 1e-6."""
    top, slabs, bottom, _, _ = shape_case("mixture-paint", MIX)
    tau = 2.0 * extinction_Ergun(np.array([1.0]), 0.15, FlakeOptics.constant(0.7, 0.1), 0.8, distribution=MIX)[0, 0]
    text = f"""flakedb: 1
name: validation-mixture-paint
spectral: {{mode: mono}}
resolution: 32
layers:
  - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}
  - basecoat:
      thickness_um: 2.0
      ior: 1.5
      particles:
        - custom: {{kind: flake, name: f, R: 0.7, T: 0.1, orientation_alpha: 0.15,
                    orientation_mixture: {{weight: 0.35, orientation_alpha: 0.6, orientation_distribution: student_t,
                                          orientation_shape: 3}}}}
          optical_depth: {float(tau)!r}
        - custom: {{kind: medium, name: hg, albedo: 0.85, phase: {{hg: 0.6}}}}
          optical_depth: 3.0
  - primer: {{albedo: 0.3}}
"""
    n = 24
    direct = solve_stack(top, slabs, bottom, SolverSettings(n=n))
    paint = build_paint(parse_recipe(text))
    assert paint.slabs[0].medium.components[0].distribution == MIX
    viarecipe = solve_paint(paint, n)
    np.testing.assert_allclose(viarecipe.albedo(), direct.albedo(), rtol=1e-6, atol=1e-9)
    L = min(direct.n_orders, viarecipe.n_orders)
    assert np.abs(viarecipe.Rt[:L] - direct.Rt[:L]).max() < 1e-6 * np.abs(direct.Rt).max()


def test_auto_resolution_follows_the_narrowest_lobe():
    """``resolution: auto`` applies the rules measured for Beckmann/GGX at α to the narrowest lobe
    (:func:`flakedb.rt.scattering.microflake.flake_lobe_alpha`): a narrow second population raises n, a Student-t with
    γ ≥ 2 keeps α's n, and γ = 1.5 (core √(2/3) × GGX's) asks for more."""
    from flakedb.solve.resolution import auto_resolution
    from flakedb.rt.scattering.microflake import flake_lobe_alpha

    def n_for(extra):
        return auto_resolution(parse_recipe(_recipe(MET % extra).replace("resolution: 16\n", "")))[0]

    base = n_for(", orientation_alpha: 0.2")  # 48 (h·α ≥ 4.8 for the default colour_error)
    assert n_for(", orientation_alpha: 0.2, orientation_distribution: ggx") == base
    assert n_for(", orientation_alpha: 0.2, orientation_distribution: student_t, orientation_shape: 4") == base
    assert n_for(", orientation_alpha: 0.2, orientation_distribution: student_t, orientation_shape: 1.5") > base
    assert n_for(", orientation_alpha: 0.3, orientation_mixture: {weight: 0.2, orientation_alpha: 0.1}") == n_for(
        ", orientation_alpha: 0.1") > base
    assert flake_lobe_alpha(0.3, "student_t(1.5)") == pytest.approx(0.3 * np.sqrt(2 / 3), rel=1e-15)
    assert flake_lobe_alpha(0.3, "mix(ggx,0.5,student_t(1.5),0.2)") == pytest.approx(0.2 * np.sqrt(2 / 3), rel=1e-15)


def test_catalogue_entries_can_state_a_shape():
    """A catalogue flake may be a Student-t (orientation_shape {value, source}); its name is formed in one
    place (:func:`flakedb.paint.catalog.catalog_distribution`) for recipes, the build request and the plan."""
    import copy
    import dataclasses

    from flakedb.paint import catalog as cat
    from flakedb.pipelines.build import make_request
    from flakedb.store import versions as st

    doc = copy.deepcopy(cat.load_catalog())
    e = doc["particles"]["metallic"]
    e["orientation_distribution"] = "student_t"
    e["orientation_shape"] = {"value": 2.5, "source": "test"}
    assert cat.validate_catalog(doc) == [] and cat.catalog_distribution(e) == "student_t(2.5)"
    bad = copy.deepcopy(doc)
    del bad["particles"]["metallic"]["orientation_shape"]
    assert any("particles.metallic.orientation_shape: missing" in p for p in cat.validate_catalog(bad))
    bad["particles"]["metallic"].update(orientation_distribution="ggx", orientation_shape={"value": 3, "source": "x"})
    assert any("applies to orientation_distribution student_t only" in p for p in cat.validate_catalog(bad))
    bad["particles"]["metallic"].update(orientation_distribution="student_t", orientation_shape={"value": 1.2, "source": "x"})
    assert any("orientation_shape.value" in p and "1.2" in p for p in cat.validate_catalog(bad))

    def name(extra):
        r = parse_recipe(_recipe(MET % extra), catalog=doc)
        return recipe_distribution(r.basecoats[0].particles[0])

    assert name("") == "student_t(2.5)"
    assert name(", orientation_shape: 4") == "student_t(4.0)"  # the recipe's γ, the catalogue's family
    assert name(", orientation_distribution: student_t") == "student_t(2.5)"  # the catalogue's γ
    assert name(", orientation_distribution: ggx") == "ggx"
    assert name(", orientation_mixture: {weight: 0.2, orientation_alpha: 0.4}") == "mix(student_t(2.5),0.2,beckmann,0.4)"
    req = make_request(species=["metallic"], n=16, wavelength_nm=(500.0, 600.0), alphas={}, distribution_alphas={})
    req = dataclasses.replace(req, species={"metallic": e}, alphas={}, distribution_alphas={})
    a = e["orientation_alpha"]["value"]
    assert [t.prefix for t in st.plan_build(req).tasks] == [f"species/metallic/n16/student_t(2.5)/a{a:g}"]


def test_auto_reasons_name_the_recipes_own_alpha():
    """Every auto rule's reason (albedo, the h ≥ 3/α rule and colour_error) names the flake's own α; a
    heavy-tailed flake adds the narrower lobe α the rules were applied at (the colour_error reason named only
    the latter: 'flakes α = 0.163' for a recipe's 0.2)."""
    from flakedb.solve.resolution import auto_resolution

    text = _recipe(MET % ", orientation_alpha: 0.2, orientation_distribution: student_t, orientation_shape: 1.5")
    n, why = auto_resolution(parse_recipe(text.replace("resolution: 16\n", "")))  # the default colour_error binds
    assert "colour_error ≤ 0.1" in why and "flakes α = 0.2 (" in why, why
    assert "flakes α = 0.163" not in why, why
