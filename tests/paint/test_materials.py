"""Optical constants (flakedb.paint.materials, catalog/materials/).

Guards against: a mistyped or mis-copied table or dispersion coefficient (published check values,
formula vs. shipped table); interpolation that does not pass through the table points or that
interpolates a metal in the wrong variable; silent extrapolation outside a table (must raise,
naming the material, the wavelength and the range); an extrapolation rule that bends the wrong
way (PMMA checked against an independent measurement); k < 0 slipping through (CdS's fit noise);
a wrong powder average for birefringent rutile; shape handling.
"""

import numpy as np
import pytest
import yaml

from flakedb.paint import materials
from flakedb.paint.materials import (
    HC_EV_NM,
    dispersion_formula_n,
    material_info,
    material_names,
    material_table,
    materials_dir,
    read_table,
    refractive_index,
)

TABULATED = [m for m in material_names() if "file" in material_info(m)]
FORMULA = [m for m in material_names() if "formula" in material_info(m)]


class TestPublishedValues:
    """Check values quoted in the optical-constants README (sources named)."""

    @pytest.mark.parametrize(
        "material, wl, n_ref, tol",
        [
            ("SiO2", 587.56, 1.45846, 5e-6),  # Malitson 1965, n_d of fused silica
            ("TiO2-rutile-o", 589.0, 2.6131, 5e-5),  # Devore 1951, ordinary ray
            ("TiO2-rutile-e", 589.0, 2.9089, 5e-5),  # Devore 1951, extraordinary ray
            ("MgF2", 589.0, 1.3777, 5e-5),  # Dodge 1984, ordinary ray
            ("PMMA", 589.0, 1.4906, 5e-5),  # Sultanova et al. 2009
        ],
    )
    def test_check_value(self, material, wl, n_ref, tol):
        N = refractive_index(material, wl)
        assert abs(N.real - n_ref) < tol
        assert N.imag == 0.0

    # Querry 1985 magnetite as the refractiveindex.info database stores it (database/data/main/Fe3O4/
    # nk/Querry.yml, rows "λ/µm n k"): the 430-440 nm minimum of k, the 630 nm maximum and two more
    # rows.  A µm/nm slip, swapped n/k columns or a shifted row would change these; they are also the
    # numbers catalog/pigment-colours.md gives as the cause of the navy iron black.
    @pytest.mark.parametrize(
        "wl_um, n_ref, k_ref",
        [(0.38, 2.459, 0.096), (0.43, 2.423, 0.026), (0.44, 2.404, 0.026), (0.55, 2.343, 0.105),
         (0.63, 2.358, 0.148), (0.78, 2.294, 0.123)],
    )
    def test_magnetite_reproduces_querry_rows(self, wl_um, n_ref, k_ref):
        N = refractive_index("Fe3O4", wl_um * 1000.0)
        assert abs(N.real - n_ref) < 1e-12 and abs(N.imag - k_ref) < 1e-12

    def test_rutile_powder_average(self):
        # eps = (2 eps_o + eps_e) / 3 for randomly oriented crystallites (optical-constants README)
        n = np.sqrt((2 * 2.6131**2 + 2.9089**2) / 3)
        assert abs(refractive_index("TiO2-rutile-powder", 589.0).real - n) < 5e-5


class TestTables:
    @pytest.mark.parametrize("material", TABULATED)
    def test_interpolation_reproduces_table_points(self, material):
        wl, n, k = material_table(material)
        N = refractive_index(material, wl)
        np.testing.assert_allclose(N.real, n, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(N.imag, k, rtol=1e-12, atol=1e-14)

    @pytest.mark.parametrize("material", FORMULA)
    def test_index_formula_reproduces_shipped_table(self, material):
        # the coefficients in materials.yaml drive the extrapolation: they must be the source's
        wl, n, _ = material_table(material)
        f = material_info(material)["formula"]
        assert np.max(np.abs(dispersion_formula_n(f["type"], f["coefficients"], wl) - n)) < 6e-7

    @pytest.mark.parametrize("material", TABULATED)
    def test_headers_carry_citations(self, material):
        text = (materials_dir() / material_info(material)["file"]).read_text(encoding="utf-8")
        assert "# reference" in text and "CC0" in text

    def test_metal_interpolates_dielectric_function_in_energy(self):
        wl, n, k = material_table("Al")
        i = int(np.argmin(np.abs(wl - 550)))
        e1, e2 = HC_EV_NM / wl[i], HC_EV_NM / wl[i + 1]
        eps1, eps2 = (n[i] + 1j * k[i]) ** 2, (n[i + 1] + 1j * k[i + 1]) ** 2
        e_mid = 0.5 * (e1 + e2)
        expected = np.sqrt(0.5 * (eps1 + eps2))  # linear in energy: the midpoint in E averages eps
        got = refractive_index("Al", HC_EV_NM / e_mid)
        assert abs(got - expected) < 1e-12
        nk_linear = np.interp(HC_EV_NM / e_mid, wl, n) + 1j * np.interp(HC_EV_NM / e_mid, wl, k)
        assert abs(got - nk_linear) > 1e-3  # the two rules differ here: the test sees which one ran

    def test_cds_negative_k_noise_clipped(self):
        _, _, k_raw = read_table(materials_dir() / material_info("CdS")["file"])
        assert np.any(k_raw < 0)  # the source has them (README caveat)
        assert np.all(material_table("CdS")[2] >= 0)

    @pytest.mark.parametrize("material", material_names())
    def test_k_nonnegative_and_finite_on_product_range(self, material):
        lo, hi = 380.0, 780.0
        if material == "PMMA-Zhang2020":
            lo = 400.0  # no extrapolation rule: covered by the error test below
        N = refractive_index(material, np.linspace(lo, hi, 401))
        assert np.all(np.isfinite(N)) and np.all(N.imag >= 0) and np.all(N.real > 0)

    def test_shape_preserved(self):
        wl = np.array([[450.0, 500.0], [550.0, 600.0]])
        assert refractive_index("Al", wl).shape == (2, 2)
        assert refractive_index("SiO2", 550.0).shape == ()


class TestRangeAndExtrapolation:
    def test_outside_table_without_rule_raises_with_details(self):
        with pytest.raises(ValueError) as e:
            refractive_index("Al", [500.0, 200.0])
        msg = str(e.value)
        assert "'Al'" in msg and "200 nm" in msg and "247.97" in msg and "1033.2" in msg

    def test_beyond_extrapolation_range_raises(self):
        with pytest.raises(ValueError, match=r"'PMMA'.*370 nm.*437.*1000.*380.*437"):
            refractive_index("PMMA", 370.0)
        with pytest.raises(ValueError, match=r"TiO2-rutile-o.*1200 nm"):
            refractive_index("TiO2-rutile-o", 1200.0)

    def test_unknown_material_lists_names(self):
        with pytest.raises(ValueError, match=r"unknown material 'unobtainium'.*SiO2"):
            refractive_index("unobtainium", 550.0)

    def test_derived_material_checks_range_of_its_parts(self):
        with pytest.raises(ValueError, match="TiO2-rutile-o"):
            refractive_index("TiO2-rutile-powder", 350.0)

    @pytest.mark.parametrize("material, edge", [("TiO2-rutile-o", 430.0), ("TiO2-rutile-e", 430.0), ("PMMA", 437.0)])
    def test_extrapolation_is_continuous_and_normally_dispersive(self, material, edge):
        just_in = refractive_index(material, edge).real
        just_out = refractive_index(material, edge - 1e-9).real
        assert abs(just_in - just_out) < 1e-6
        wl = np.linspace(380.0, edge, 50)
        n = refractive_index(material, wl).real
        assert np.all(np.diff(n) < 0)  # n rises toward the UV (normal dispersion)

    def test_pmma_extrapolation_against_zhang2020_measurement(self):
        # Sultanova's fit (valid from 436.8 nm) extrapolated to 400 nm versus Zhang et al. 2020's
        # measured PMMA (a different sample: offset ~0.006).  The offset may not change by more than
        # 0.0015 between 450 nm (both valid) and 400 nm; holding n constant below 437 nm would change it
        # by 0.0044.
        def offset(w):
            return refractive_index("PMMA", w).real - refractive_index("PMMA-Zhang2020", w).real

        assert abs(offset(400.0) - offset(450.0)) < 0.0015


def test_the_fast_yaml_loader_reads_the_index_as_the_python_one():
    """materials.yaml through libyaml's loader (when present) gives exactly PyYAML's SafeLoader document."""
    path = materials.materials_dir() / "materials.yaml"
    text = path.read_text(encoding="utf-8")
    assert yaml.load(text, Loader=materials.YAML_LOADER) == yaml.load(text, Loader=yaml.SafeLoader)
    assert materials.YAML_LOADER is getattr(yaml, "CSafeLoader", yaml.SafeLoader)
