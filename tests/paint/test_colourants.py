"""The formulator's colourants in the catalogue (issue #35 item 1): carbon black (PBk7), red iron oxide
(PR101), a PW6 grade; their optical constants, densities and Colour Index names.

Guards against: a mis-copied soot or hematite table, or a wrong powder average; an extrapolation rule
that leaks beyond its range or changes the table inside it; a flake density that is not the stack's
mass per volume (and a sweep member that keeps its base's); `species list --json` losing a species or
a field; a carbon-black masstone that is not black and neutral (the issue's done-when: L* ≤ 5,
|a*|, |b*| ≤ 2 at 45as45, 45as75, 45as110 for 2 % by volume in 20 µm over a black primer under a
smooth 40 µm clear coat), and the physics that makes it so (Rayleigh absorption of primary particles,
checked against the closed form of Bohren & Huffman eq. 5.7) silently changing.
"""

import copy
import json

import numpy as np
import pytest
from click.testing import CliRunner

import flakedb.paint.species as species_module
from flakedb.cli.main import cli
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.paint.catalog import CatalogError, expand_sweeps, load_catalog, validate_catalog
from flakedb.paint.materials import material_density_g_cm3, refractive_index
from flakedb.paint.species import binder_index, pigment_optics, species_density_g_cm3

#: the seven families of issue #35 that this catalogue has, by Colour Index name
COLOURANTS = {"carbon-black": "PBk7", "iron-oxide-red": "PR101", "iron-oxide-red-transparent": "PR101",
              "titanium-white-r706": "PW6"}
#: 45° illumination, aspecular 45°, 75°, 110° (the done-when geometries)
DONE_WHEN = [(45.0, 45.0), (45.0, 75.0), (45.0, 110.0)]


def masstone_doc(species, vf, basecoat_um, primer="black", step_nm=10, n=16):
    return {"flakedb": 1, "name": "masstone", "spectral": {"mode": "spectral", "range_nm": [380, 780], "step_nm": step_nm},
            "resolution": n,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": basecoat_um, "ior": 1.5,
                                     "particles": [{"species": species, "volume_fraction": vf}]}},
                       {"primer": {"color": primer}}]}


def lab(doc, catalog, geometry=DONE_WHEN):
    return predict(recipe_from_doc(doc, catalog=catalog), geometry, catalog=catalog).lab("10", "D65")


class TestOpticalConstants:
    # rows of the refractiveindex.info files as the database stores them (λ/µm n k):
    # other/soots/acetylene soot/nk/Dalzell.yml and main/Fe2O3/nk/Querry-o.yml, Querry-e.yml
    @pytest.mark.parametrize("material, wl_nm, n_ref, k_ref", [
        ("C-soot", 435.8, 1.56, 0.46), ("C-soot", 550.0, 1.56, 0.46), ("C-soot", 806.5, 1.57, 0.46),
        ("Fe2O3-hematite-o", 550.0, 3.318, 0.498), ("Fe2O3-hematite-o", 650.0, 3.074, 0.057),
        ("Fe2O3-hematite-e", 550.0, 2.927, 0.460), ("Fe2O3-hematite-e", 450.0, 2.809, 0.873),
        ("C-amorphous", 516.6, 2.30, 0.87),
    ])
    def test_table_rows(self, material, wl_nm, n_ref, k_ref):
        N = refractive_index(material, wl_nm)
        assert abs(N.real - n_ref) < 1e-12 and abs(N.imag - k_ref) < 1e-12

    def test_hematite_powder_is_the_orientation_average(self):
        wl = np.arange(380.0, 781.0, 10.0)
        eps = (2 * refractive_index("Fe2O3-hematite-o", wl) ** 2 + refractive_index("Fe2O3-hematite-e", wl) ** 2) / 3
        N = refractive_index("Fe2O3-hematite-powder", wl)
        np.testing.assert_allclose(N ** 2, eps, rtol=1e-13)
        assert np.all(N.imag > 0)

    def test_soot_holds_its_first_value_below_the_table_only(self):
        wl = np.array([380.0, 400.0, 435.7])
        np.testing.assert_array_equal(refractive_index("C-soot", wl), 1.56 + 0.46j)
        # inside the table the interpolation is untouched (ε linear in energy between 435.8 and 450 nm)
        N = refractive_index("C-soot", 440.0)
        assert 0.46 < N.imag < 0.48
        with pytest.raises(ValueError, match=r"379.*outside.*extrapolation range \[380, 435.8\]"):
            refractive_index("C-soot", 379.0)
        with pytest.raises(ValueError, match="807"):
            refractive_index("C-soot", 807.0)


class TestDensity:
    def test_flake_density_is_the_stack_mass_per_volume(self):
        cat = load_catalog(None)
        allsp = expand_sweeps(cat)
        rho_al, rho_mgf2 = material_density_g_cm3("Al"), material_density_g_cm3("MgF2")
        rho, src = species_density_g_cm3(allsp["metallic"])
        assert rho == pytest.approx((0.3 * rho_al + 2 * 0.2 * rho_mgf2) / 0.7, rel=1e-14)
        assert "Al" in src and "MgF2" in src
        # a sweep member has its own stack, so its own density (TiO2 70 nm vs 140 nm on 300 nm SiO2)
        r70 = species_density_g_cm3(allsp["pearlescent-tio2-070nm"])[0]
        r140 = species_density_g_cm3(allsp["pearlescent-tio2-140nm"])[0]
        rho_ti, rho_si = material_density_g_cm3("TiO2-rutile-o"), material_density_g_cm3("SiO2")
        assert r70 == pytest.approx((140 * rho_ti + 300 * rho_si) / 440, rel=1e-14)
        assert r140 == pytest.approx((280 * rho_ti + 300 * rho_si) / 580, rel=1e-14)

    def test_pigments_state_a_cited_density_and_colour_index(self):
        cat = load_catalog(None)
        for name, e in cat["particles"].items():
            if e["kind"] == "pigment":
                rho, src = species_density_g_cm3(e)
                assert 1.0 < rho < 6.0 and len(src) > 20, name
                assert e.get("colour_index"), name
        for name, ci in COLOURANTS.items():
            assert cat["particles"][name]["colour_index"] == ci

    def test_bad_colour_index_and_density_are_named(self):
        cat = copy.deepcopy(load_catalog(None))
        cat["particles"]["carbon-black"]["colour_index"] = "Pigment Black 7"
        cat["particles"]["iron-oxide-red"]["density_g_cm3"]["value"] = 0.1
        problems = validate_catalog(cat)
        assert any(p.startswith("particles.carbon-black.colour_index") for p in problems), problems
        assert any(p.startswith("particles.iron-oxide-red.density_g_cm3.value") and "0.5-25" in p for p in problems)


def test_species_list_json_lists_every_species_with_its_fields():
    out = CliRunner().invoke(cli, ["species", "list", "--json"])
    assert out.exit_code == 0, out.output
    rows = json.loads(out.output)
    cat = load_catalog(None)
    assert [r["name"] for r in rows] == list(expand_sweeps(cat))
    for r in rows:
        assert {"name", "kind", "colour_index", "density_g_cm3", "source"} <= set(r)
        assert r["source"], r["name"]
    by = {r["name"]: r for r in rows}
    for name, ci in COLOURANTS.items():
        assert by[name]["colour_index"] == ci and by[name]["density_g_cm3"] > 1
    assert by["titanium-white-r706"]["grade"]["surface_treatment"].startswith("alumina")
    assert by["metallic"]["colour_index"] == "PM1"
    assert by["gray-mirror"]["density_g_cm3"] is None          # an idealised flake: no material


#: Colour-Index species for which no citable density was reached (docs/colourants.md, "Densities":
#: what was searched).  A new Colour-Index species without a density, or a density added to one of
#: these without updating the list, fails the test below.
DENSITY_NOT_FOUND = {"phthalo-green-yellow-shade", "quinacridone-magenta", "pyrrole-red", "hansa-yellow-opaque"}


def test_every_colour_index_species_has_a_cited_density_but_the_named_gaps():
    rows = json.loads(CliRunner().invoke(cli, ["species", "list", "--json"]).output)
    missing = {r["name"] for r in rows if r["colour_index"] and r["density_g_cm3"] is None}
    assert missing == DENSITY_NOT_FOUND
    for r in rows:
        if r["colour_index"] and r["density_g_cm3"] is not None:
            # a pigment's true density: organics ~1.2-2.2, oxides and sulfides 3.5-5.5 g/cm³; a cited source
            assert 1.0 < r["density_g_cm3"] < 6.0 and len(r["density_source"]) > 20, r["name"]
    by = {r["name"]: r for r in rows}
    assert by["phthalo-green"]["density_g_cm3"] == 2.1 and "Heliogen Green" in by["phthalo-green"]["density_source"]
    assert by["quinacridone-red"]["density_g_cm3"] == 1.46 and "Chinacridon" in by["quinacridone-red"]["density_source"]


class TestCarbonBlack:
    def test_primary_particles_absorb_as_rayleigh_spheres(self):
        # 15 nm soot spheres in the binder: absorption per particle volume is the small-sphere limit
        # (6π n_b/λ) Im[(m²−1)/(m²+2)] (Bohren & Huffman eq. 5.11) up to its first size correction
        # (eq. 5.7: a relative x²/15 Re-ish term; bounded here by |x²/15 · F · (m⁴+27m²+38)/(2m²+3)|
        # at the volume-weighted size, doubled), and scattering is negligible (albedo < 0.01): why the
        # masstone is black whatever the size below ~50 nm (docs/colourants.md).
        cat = load_catalog(None)
        e = cat["particles"]["carbon-black"]
        wl = np.arange(380.0, 781.0, 40.0)
        nb = binder_index(cat, wl)
        p = pigment_optics(e, wl, nb)
        m = refractive_index("C-soot", wl) / nb
        F = (m ** 2 - 1) / (m ** 2 + 2)
        per_volume = (p.c_ext_um2 - p.c_sca_um2) / p.mean_volume_um3
        rayleigh = 6 * np.pi * nb / (wl * 1e-3) * F.imag
        sigma = np.log(e["gsd"]["value"])
        x2 = (np.pi * e["median_diameter_um"]["value"] * nb / (wl * 1e-3)) ** 2 * np.exp(8 * sigma ** 2)
        bound = 2 * np.abs(x2 / 15 * F * (m ** 4 + 27 * m ** 2 + 38) / (2 * m ** 2 + 3))
        rel = np.abs(per_volume / rayleigh - 1)
        assert np.all(rel <= bound), (rel, bound)
        # scattering: Rayleigh, C_sca/C_abs = (2/3) x³ |F|²/Im F at the <d⁶>/<d³> size (measured ≤ 0.004)
        x3 = (np.pi * e["median_diameter_um"]["value"] * nb / (wl * 1e-3)) ** 3 * np.exp(13.5 * sigma ** 2)
        albedo = p.c_sca_um2 / p.c_ext_um2
        assert np.all(albedo < 0.01)
        np.testing.assert_allclose(albedo, 2 / 3 * x3 * np.abs(F) ** 2 / F.imag, rtol=0.3)

    def test_masstone_is_black_and_neutral(self):
        # issue #35 done-when: 2 % by volume in 20 µm over a black primer, smooth 40 µm clear coat.
        # Measured: L* 0.09-0.10, a* 0.00, b* −0.11…−0.13 (the limits are the issue's, not fitted).
        cat = load_catalog(None)
        L, a, b = lab(masstone_doc("carbon-black", 0.02, 20), cat).T
        assert np.all(L <= 5) and np.all(np.abs(a) <= 2) and np.all(np.abs(b) <= 2), (L, a, b)

    def test_masstone_does_not_depend_on_the_extrapolated_violet(self, monkeypatch):
        # materials.yaml's reason for holding soot's 435.8 nm value below it: a ±10 % change of k
        # there moves the masstone by < 0.1 in L*, a*, b*.
        cat = load_catalog(None)
        ref = lab(masstone_doc("carbon-black", 0.02, 20), cat)
        orig = species_module.refractive_index

        for scale in (0.9, 1.1):
            def changed(mat, wl, scale=scale):
                N = orig(mat, wl)
                if mat != "C-soot":
                    return N
                w = np.asarray(wl, float)
                return np.where(w < 435.8, N.real + 1j * N.imag * scale, N)
            monkeypatch.setattr(species_module, "refractive_index", changed)
            got = lab(masstone_doc("carbon-black", 0.02, 20), cat)
            assert np.max(np.abs(got - ref)) < 0.1, (scale, got - ref)


def test_transparent_iron_oxide_hardly_scatters():
    # the transparent grade's reason to exist (its catalogue source): same hematite, 20 nm instead of
    # 0.2 µm, so single-scattering albedo 0.05 instead of 0.53 at 550 nm (measured), absorbing more per
    # volume in the blue (small-particle absorption) and less in the red
    cat = load_catalog(None)
    wl = np.array([450.0, 550.0, 650.0])
    nb = binder_index(cat, wl)
    t = pigment_optics(cat["particles"]["iron-oxide-red-transparent"], wl, nb)
    o = pigment_optics(cat["particles"]["iron-oxide-red"], wl, nb)
    albedo_t, albedo_o = t.c_sca_um2 / t.c_ext_um2, o.c_sca_um2 / o.c_ext_um2
    assert albedo_t[1] < 0.1 < 0.4 < albedo_o[1]
    abs_t = (t.c_ext_um2 - t.c_sca_um2) / t.mean_volume_um3
    assert abs_t[0] > abs_t[1] > abs_t[2]


class TestGoldMetallic:
    """catalog/recipes/gold-metallic.yaml: aluminium + transparent iron oxide + yellow (issue #35 item 5).
    Bounds: L*15 ≥ 60, the "light metallic colour" of Axalta's US 2013/0084403 A1 (L* at 45°/as15° of at
    least 60); b* ≥ +40 near the specular (issue #35's measured MERL gold reads +55); a gold hue
    60° ≤ h ≤ 90° (yellow-orange: flakedb's criterion) from -15° to 45°; a metallic's lightness flop
    (flop index ≥ 15, as silver-bright's cited range)."""

    ASP = (-15.0, 15.0, 25.0, 45.0, 110.0)

    def colours(self, drop=None):
        import yaml
        from flakedb.appearance.report import flop_index_standard
        from flakedb.colour.settings import FLOP_GEOMETRIES
        from flakedb.resources import RECIPES_DIR
        cat = load_catalog(None)
        doc = yaml.safe_load((RECIPES_DIR / "gold-metallic.yaml").read_text(encoding="utf-8"))
        if drop:
            ps = doc["layers"][1]["basecoat"]["particles"]
            doc["layers"][1]["basecoat"]["particles"] = [p for p in ps if p["species"] != drop]
        g = [(45.0, a) for a in self.ASP]
        lab = predict(recipe_from_doc(doc, catalog=cat), g + list(FLOP_GEOMETRIES), n=16,
                      catalog=cat).lab("10", "D65")
        return lab[:len(g)], flop_index_standard(*lab[len(g):, 0])

    def test_is_a_gold_metallic(self):
        lab, fi = self.colours()
        L, a, b = lab.T
        h = np.degrees(np.arctan2(b, a)) % 360
        assert L[1] >= 60 and b[0] >= 40 and b[1] >= 35, (L, b)
        assert np.all((60 <= h[:4]) & (h[:4] <= 90)), h
        assert np.all(np.diff(L) < 0) and fi >= 15, (L, fi)      # bright at the specular, dark at the flop
        # the yellow tinter scatters: without it the flop is much darker (what the recipe's description says)
        lab0, _ = self.colours(drop="hansa-yellow-opaque")
        assert lab0[-1, 0] < 0.5 * L[-1] and lab0[0, 2] < b[0], (lab0[:, 0], L)
