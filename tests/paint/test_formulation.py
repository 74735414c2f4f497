"""Formulation units (flakedb.paint.formulation and the recipe's weight_fraction).

Guards against: a weight → volume conversion that leaves the hand computation (the film's mass
balance) or is not the inverse of volume → weight; a weight-fraction recipe that composes to another
colour than its volume-fraction equivalent; a CPVC estimate off Asbeck & Van Loo's formula, or a PVC
above it accepted; a weight fraction accepted where a density is missing (species, binder) or where a
custom particle has no volume; both or neither loading given; and store versions renamed by
formulation data that do not change the optics.
"""

import numpy as np
import pytest
import yaml

from flakedb.colour.tolerance import delta_E_2000
from flakedb.match.fit import predict
from flakedb.paint.catalog import FORMULATION_FIELDS, STORED_KINDS, expand_sweeps, load_catalog
from flakedb.paint.formulation import cpvc_oil_absorption, volume_fractions, weight_fractions
from flakedb.paint.recipe import RecipeError, parse_recipe
from flakedb.store.plan import BuildRequest, content_hash
from tests.match.test_fit import _text


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(None)


def test_conversion_against_hand_computation():
    # 10 % by weight of cadmium yellow (4.82 g/cm³) beside 4 % by volume of metallic flakes (2.957: the film stack's
    # (2 · 0.2 · 3.15 + 0.3 · 2.70) / 0.7 = 2.9571 rounded to the 4 digits of this hand computation) in the
    # binder (1.18): film density M = (1.18 · 0.96 + 2.957 · 0.04) / (1 − 0.1 · (1 − 1.18 / 4.82))
    #                                = (1.1328 + 0.11828) / (1 − 0.0755187) = 1.25108 / 0.9244813 = 1.353278,
    # φ = 0.1 · 1.353278 / 4.82 = 0.0280763 (hand, 7 digits)
    phi = volume_fractions([0.04, np.nan], [np.nan, 0.1], [2.957, 4.82], 1.18)
    assert phi[0] == 0.04
    assert phi[1] == pytest.approx(0.0280763, abs=5e-8)
    # and back: the flakes' weight fraction is 2.957 · 0.04 / 1.353278 = 0.0874026
    w = weight_fractions(phi, [2.957, 4.82], 1.18)
    assert w == pytest.approx([0.0874026, 0.1], abs=5e-8)


def test_round_trip_and_all_by_weight():
    rng = np.random.default_rng(3)
    for _ in range(50):
        k = rng.integers(1, 5)
        rho = rng.uniform(1.5, 8.0, k)
        w = rng.dirichlet(np.ones(k + 1))[:k] * rng.uniform(0.1, 0.9)
        phi = volume_fractions(np.full(k, np.nan), w, rho, 1.2)
        np.testing.assert_allclose(weight_fractions(phi, rho, 1.2), w, rtol=1e-12)
        # all by weight: φ_i = (w_i/ρ_i) / (w_b/ρ_b + Σ w_k/ρ_k)
        np.testing.assert_allclose(phi, (w / rho) / ((1 - w.sum()) / 1.2 + np.sum(w / rho)), rtol=1e-12)
    with pytest.raises(ValueError, match="add up to 1.1"):
        volume_fractions([np.nan, np.nan], [0.6, 0.5], [4.0, 4.0], 1.2)


def test_cpvc_oil_absorption():
    # one pigment: 1 / (1 + ρ OA / 93.5); titanium white (4.23, OA 20): 1 / (1 + 84.6 / 93.5) = 1 / 1.904813 = 0.524986
    assert cpvc_oil_absorption([0.2], [4.23], [20.0]) == pytest.approx(1 / (1 + 84.6 / 93.5), rel=1e-14)
    assert cpvc_oil_absorption([0.2], [4.23], [20.0]) == pytest.approx(0.524986, abs=1e-6)
    # a blend: the oil volumes per pigment volume averaged with the volume fractions
    c = cpvc_oil_absorption([0.1, 0.3], [4.0, 2.0], [20.0, 60.0])
    assert c == pytest.approx(1 / (1 + (0.1 * 80 / 93.5 + 0.3 * 120 / 93.5) / 0.4), rel=1e-14)


def _lab(rec, catalog):
    return predict(rec, [(45.0, g) for g in (15.0, 45.0, 110.0)], catalog=catalog).lab()


def test_weight_fraction_recipe_composes_to_its_volume_equivalent(catalog):
    by_w = parse_recipe(_text(VF_METALLIC=0.04, VF_YELLOW=0.02).replace("volume_fraction: 0.02", "weight_fraction: 0.1"),
                        catalog=catalog)
    p = by_w.basecoats[0].particles
    # the catalogue's metallic density is the film stack's 2.957143 (not the 2.957 of the hand check above):
    # M = (1.18 · 0.96 + 2.957143 · 0.04) / 0.9244813 = 1.353284, φ = 0.1 · 1.353284 / 4.82 = 0.0280764
    assert (p[1].weight_fraction, p[1].volume_fraction) == (0.1, pytest.approx(0.0280764, abs=5e-8))
    exact = parse_recipe(_text(VF_METALLIC=0.04, VF_YELLOW=repr(p[1].volume_fraction)), catalog=catalog)
    hand = parse_recipe(_text(VF_METALLIC=0.04, VF_YELLOW=0.02807), catalog=catalog)   # the hand value, 4 digits
    lab_w = _lab(by_w, catalog)
    assert np.max(delta_E_2000(_lab(exact, catalog), lab_w)) == 0.0
    de = np.max(delta_E_2000(_lab(hand, catalog), lab_w))
    assert 0 < de <= 0.01, de
    f = by_w.basecoats[0].formulation
    assert f["pvc"] == pytest.approx(0.04 + 0.0280764, abs=5e-8)
    assert [x["given"] for x in f["particles"]] == ["volume_fraction", "weight_fraction"]
    assert f["particles"][0]["weight_fraction"] == pytest.approx(2.957143 * 0.04 / 1.353284, abs=5e-8)
    assert f["cpvc_estimate"] is None and "cadmium-yellow" in f["cpvc_basis"]


def _white(w):
    return (_text(VF_METALLIC=0.04, VF_YELLOW=0.02)
            .replace("{species: metallic, volume_fraction: 0.04, orientation_alpha: 0.3}", f"{{species: titanium-white, weight_fraction: {w}}}")
            .replace("        - {species: cadmium-yellow, volume_fraction: 0.02}\n", ""))


def test_pvc_above_the_cpvc_estimate_is_refused(catalog):
    # 75 wt% rutile: φ = (0.75/4.23) / (0.75/4.23 + 0.25/1.18) = 0.4556 < CPVC 0.524986: accepted
    ok = parse_recipe(_white(0.75), catalog=catalog).basecoats[0]
    assert ok.particles[0].volume_fraction == pytest.approx((0.75 / 4.23) / (0.75 / 4.23 + 0.25 / 1.18), rel=1e-12)
    assert ok.formulation["cpvc_estimate"] == pytest.approx(0.524986, abs=1e-6)
    # 80 wt%: φ = 0.189125 / (0.189125 + 0.169492) = 0.5274 > 0.524986: refused, naming the PVC, the estimate and why
    with pytest.raises(RecipeError) as e:
        parse_recipe(_white(0.8), catalog=catalog)
    msg = str(e.value)
    assert "PVC = 0.5274" in msg and "estimated 0.525" in msg and "Asbeck & Van Loo" in msg and "not enough binder" in msg


@pytest.mark.parametrize("old,new,expect", [
    ("{species: metallic, volume_fraction: 0.04,", "{species: metallic, volume_fraction: 0.04, weight_fraction: 0.1,",
     "exactly one (got volume_fraction and weight_fraction)"),
    ("{species: metallic, volume_fraction: 0.04,", "{species: metallic,", "exactly one (got neither)"),
    ("{species: metallic, volume_fraction: 0.04,", "{species: gray-mirror, volume_fraction: 0.04,",
     "species 'gray-mirror' has no density_g_cm3"),
    ("{species: metallic, volume_fraction: 0.04, orientation_alpha: 0.3}",
     "{custom: {kind: medium, albedo: 0.5, phase: isotropic}, optical_depth: 1}", "a custom particle (optical_depth) has none"),
])
def test_weight_fraction_refusals(catalog, old, new, expect):
    text = _text(VF_METALLIC=0.04, VF_YELLOW=0.02).replace("volume_fraction: 0.02", "weight_fraction: 0.1")
    assert old in text
    with pytest.raises(RecipeError, match=expect.replace("(", r"\(").replace(")", r"\)")):
        parse_recipe(text.replace(old, new), catalog=catalog)


def test_sweep_member_has_its_own_stack_density(catalog):
    """A sweep member's density is its own film stack's (2 · 70 nm rutile 4.23 + 300 nm silica 2.20) / 440 nm
    = 2.846, not its base's (120 nm: 3.102): the conversion of a weight fraction uses it."""
    text = _text(VF_METALLIC=0.04, VF_YELLOW=0.02).replace("volume_fraction: 0.02", "weight_fraction: 0.1")
    rec = parse_recipe(text.replace("{species: metallic,", "{species: pearlescent-tio2-070nm,"), catalog=catalog)
    f = rec.basecoats[0].formulation["particles"]
    assert f[0]["density_g_cm3"] == pytest.approx((2 * 70 * 4.23 + 300 * 2.20) / 440, rel=1e-12)
    base = parse_recipe(text.replace("{species: metallic,", "{species: pearlescent,"), catalog=catalog)
    assert base.basecoats[0].formulation["particles"][0]["density_g_cm3"] == pytest.approx(
        (2 * 120 * 4.23 + 300 * 2.20) / 540, rel=1e-12)


def test_binder_without_density_refused(catalog):
    cat = dict(catalog, binder={k: v for k, v in catalog["binder"].items() if k != "density_g_cm3"})
    text = _text(VF_METALLIC=0.04, VF_YELLOW=0.02).replace("volume_fraction: 0.02", "weight_fraction: 0.1")
    with pytest.raises(RecipeError, match="the catalogue's binder has no density_g_cm3"):
        parse_recipe(text, catalog=cat)
    assert parse_recipe(_text(VF_METALLIC=0.04, VF_YELLOW=0.02), catalog=cat).basecoats[0].formulation[
        "particles"][1]["weight_fraction"] is None      # by volume: still fine, no weight shown


def test_formulation_data_do_not_rename_store_versions(catalog):
    # the stored kinds only: a store never holds a tinter (make_request refuses one; docs/calibration.md)
    sp = {k: e for k, e in expand_sweeps(catalog).items() if e["kind"] in STORED_KINDS}
    stripped = {k: {f: v for f, v in e.items() if f not in FORMULATION_FIELDS} for k, e in sp.items()}
    assert any("density_g_cm3" in e for e in sp.values())
    binder = {k: v for k, v in catalog["binder"].items() if k != "density_g_cm3"}
    a = BuildRequest(sp, catalog["binder"], {}, (32,), (400.0, 700.0))
    b = BuildRequest(stripped, binder, {}, (32,), (400.0, 700.0))
    assert content_hash(a.inputs()) == content_hash(b.inputs())


def test_compose_reports_both_fractions_and_pvc(catalog, tmp_path):
    from flakedb.compose.orchestrate import compose
    from flakedb.appearance.report import format_report

    rec = parse_recipe(_text(VF_METALLIC=0.04, VF_YELLOW=0.02).replace("volume_fraction: 0.02", "weight_fraction: 0.1"),
                       catalog=catalog)
    rep = compose(rec, tmp_path, catalog=catalog).report
    (f,) = rep["formulation"]
    assert f["layer"] == "layers[1].basecoat" and f["pvc"] == pytest.approx(0.0680764, abs=5e-8)
    assert [(p["species"], round(p["volume_fraction"], 7), round(p["weight_fraction"], 7)) for p in f["particles"]] == [
        ("metallic", 0.04, 0.0874064), ("cadmium-yellow", 0.0280764, 0.1)]
    text = format_report(rep)
    assert "formulation layers[1].basecoat: PVC 0.0681" in text
    assert "cadmium-yellow           volume 0.0281  weight 0.1000" in text
    saved = yaml.safe_load((tmp_path / "two-species.json").read_text())
    assert saved["formulation"][0]["particles"][1]["given"] == "weight_fraction"
