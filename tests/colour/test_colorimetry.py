"""Colour (flakedb.colour.colorimetry): spectra → XYZ → linear sRGB / CIELAB, CIEDE2000, RGB mode.

The default path (2°/10° observers, D65/A/FL11, grids whose ≤ 1 nm fine nodes are integer nm, sRGB)
runs on flakedb's own tables, Sprague matrix, sRGB matrix, CIELAB and CIEDE2000 without importing
colour-science; ``TestNativeEqualsColourScience`` holds it to colour-science's results to 1e-12.

Guards against: a wrong normalisation (the perfect white must give Y = 1 and D65's chromaticity,
Lab (100, 0, 0)); mis-aligned or mis-interpolated CIE tables (1 nm results must equal
colour-science's own integration to rounding; coarse grids must stay close to it on the 24
ColorChecker spectra, with the agreement stated); a wrong sRGB matrix (IEC 61966-2-1 primaries);
a CIEDE2000 implementation that fails Sharma et al.'s published test pairs; broken broadcasting
over leading axes; an RGB mode that does not conserve energy (R + T = 1 must map to 1 per channel);
accepting grids it cannot integrate.
"""

import colour
import numpy as np
import pytest

from flakedb.colour import cie_tables
from tests.tolerances import assert_within, assert_within_sum_bound, sum_tol
from flakedb.colour.colorimetry import (
    CMFS_NAME,
    SRGB_PRIMARIES_XY,
    SRGB_WHITE_XY,
    XYZ_to_Lab,
    XYZ_to_linear_sRGB,
    delta_E_2000,
    normalised_primary_matrix,
    reflectance_to_XYZ,
    spectra_to_rgb_matrix,
    spectra_to_rgb_mode,
    spectral_grid,
    srgb_matrices,
    tristimulus_weights,
    tristimulus_weights_colour_science,
    white_XYZ,
)

CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
D65 = colour.SDS_ILLUMINANTS["D65"]


def _colorchecker(step):
    """The 24 'ColorChecker N Ohta' spectra (native 380-780 nm, 5 nm) shipped with colour-science,
    on a grid of `step` nm (colour's Sprague interpolation / sampling)."""
    shape = colour.SpectralShape(380, 780, step)
    sds = list(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values())
    assert len(sds) == 24
    return sds, np.array([sd.copy().align(shape).values for sd in sds])


@pytest.fixture(scope="module")
def reference_1nm():
    """colour-science's own 1 nm integration (CIE 15 weighted sum) of the ColorChecker, Y = 1 scale."""
    sh = colour.SpectralShape(380, 780, 1)
    cmfs = CMFS.copy().trim(sh)
    ill = D65.copy().align(sh)
    sds, _ = _colorchecker(1)
    return np.array([colour.sd_to_XYZ(sd.copy().align(sh), cmfs, ill, method="Integration") for sd in sds]) / 100


class TestGrid:
    def test_default_grid(self):
        wl = spectral_grid()
        assert wl[0] == 380 and wl[-1] == 780 and wl.size == 41

    def test_step_must_divide_range(self):
        with pytest.raises(ValueError, match="does not divide"):
            spectral_grid((380, 780), 7)

    @pytest.mark.parametrize(
        "wl, match",
        [
            (np.array([380.0, 390.0, 405.0, 420.0]), "uniform"),
            (np.arange(380.0, 781.0, 25.0), "1-20 nm"),
            (np.arange(380.0, 800.1, 10.0), "common domain"),
            (np.arange(340.0, 781.0, 10.0), "common domain"),
        ],
    )
    def test_rejects_grids_it_cannot_integrate(self, wl, match):
        with pytest.raises(ValueError, match=match):
            reflectance_to_XYZ(np.ones(wl.size), wl)


class TestWhite:
    @pytest.mark.parametrize("step", [1, 2, 4, 5, 10, 20])
    def test_perfect_white_is_Y1_and_D65(self, step):
        wl = spectral_grid((380, 780), step)
        XYZ = reflectance_to_XYZ(np.ones(wl.size), wl)
        assert abs(XYZ[1] - 1.0) <= sum_tol(wl.size, 1.0, extra_ops=1)  # Σ of n weights normalised to 1 (a sum and a division)
        xy = XYZ[:2] / XYZ.sum()
        # CIE 15:2004 D65, 2° observer: (0.31272, 0.32903); colour-science tabulates (0.3127, 0.3290)
        np.testing.assert_allclose(xy, [0.3127, 0.3290], atol=1e-4)
        # same white on every grid with the same end points (integration on the 1 nm tables)
        np.testing.assert_allclose(XYZ, white_XYZ(spectral_grid((380, 780), 1)), atol=1e-12)

    def test_lab_of_white(self):
        wl = spectral_grid()
        white = white_XYZ(wl)
        np.testing.assert_allclose(XYZ_to_Lab(white, white=white), [100.0, 0.0, 0.0], atol=1e-10)
        lab = XYZ_to_Lab(white)  # against CIE's tabulated D65 white point
        assert abs(lab[0] - 100.0) < 1e-10 and np.all(np.abs(lab[1:]) < 0.05)

    def test_half_gray(self):
        wl = spectral_grid()
        XYZ = reflectance_to_XYZ(np.full(wl.size, 0.5), wl)
        assert_within_sum_bound(XYZ, 0.5 * white_XYZ(wl), wl.size, 0.5 * np.abs(tristimulus_weights(wl)).sum(0))  # BLAS vs np.sum
        # CIE 1976: L* = 116 (0.5)^(1/3) - 16 = 76.0693
        assert abs(XYZ_to_Lab(XYZ, white=white_XYZ(wl))[0] - 76.06926) < 1e-4


class TestColorChecker:
    """Agreement with colour.sd_to_XYZ on the 24 ColorChecker spectra (measured values in the
    colorimetry module docstring: ΔE00 max 0.084 at 10 nm, 0.106 at 20 nm)."""

    @pytest.mark.parametrize("step", [1, 5])
    def test_exact_where_colour_integrates_the_same_data(self, step, reference_1nm):
        _, R = _colorchecker(step)
        np.testing.assert_allclose(reflectance_to_XYZ(R, spectral_grid((380, 780), step)), reference_1nm, atol=1e-12)

    @pytest.mark.parametrize("step, max_dE", [(10, 0.12), (20, 0.15)])
    def test_coarse_grids_close_to_1nm(self, step, max_dE, reference_1nm):
        _, R = _colorchecker(step)
        XYZ = reflectance_to_XYZ(R, spectral_grid((380, 780), step))
        dE = delta_E_2000(XYZ_to_Lab(XYZ), XYZ_to_Lab(reference_1nm))
        assert dE.max() < max_dE

    def test_broadcasting_over_leading_axes(self):
        _, R = _colorchecker(10)
        wl = spectral_grid()
        stacked = R.reshape(4, 6, -1)
        out = reflectance_to_XYZ(stacked, wl)
        assert out.shape == (4, 6, 3)
        assert_within_sum_bound(out.reshape(24, 3), reflectance_to_XYZ(R, wl), wl.size, np.abs(R) @ np.abs(tristimulus_weights(wl)))
        assert spectra_to_rgb_mode(stacked, wl).shape == (4, 6, 3)

    def test_nan_stays_in_its_row(self):
        _, R = _colorchecker(10)
        R = R.copy()
        R[3, 7] = np.nan
        XYZ = reflectance_to_XYZ(R, spectral_grid())
        assert np.all(np.isnan(XYZ[3])) and np.all(np.isfinite(np.delete(XYZ, 3, axis=0)))


class TestSRGB:
    def test_primaries_and_white(self):
        # IEC 61966-2-1: XYZ of the linear sRGB red primary = first column of the RGB→XYZ matrix
        # (0.4124, 0.2126, 0.0193); the D65 white (0.3127, 0.3290, Y = 1) maps to (1, 1, 1) up to the
        # rounding of the standard's 4-decimal XYZ→RGB matrix, which colour-science uses (1.6e-4).
        np.testing.assert_allclose(XYZ_to_linear_sRGB([0.4124, 0.2126, 0.0193]), [1.0, 0.0, 0.0], atol=2e-3)
        white = colour.xy_to_XYZ([0.3127, 0.3290])
        np.testing.assert_allclose(XYZ_to_linear_sRGB(white), [1.0, 1.0, 1.0], atol=3e-4)


class TestCIEDE2000:
    # G. Sharma, W. Wu, E. N. Dalal, "The CIEDE2000 color-difference formula: implementation notes,
    # supplementary test data, and mathematical observations", Color Res. Appl. 30, 21-30 (2005),
    # Table 1, pairs 1, 2, 3, 7, 17, 18, 19, 20, 21, 25, 31, 33, 34.
    PAIRS = [
        ((50.0000, 2.6772, -79.7751), (50.0000, 0.0000, -82.7485), 2.0425),
        ((50.0000, 3.1571, -77.2803), (50.0000, 0.0000, -82.7485), 2.8615),
        ((50.0000, 2.8361, -74.0200), (50.0000, 0.0000, -82.7485), 3.4412),
        ((50.0000, 0.0000, 0.0000), (50.0000, -1.0000, 2.0000), 2.3669),
        ((50.0000, 2.5000, 0.0000), (73.0000, 25.0000, -18.0000), 27.1492),
        ((50.0000, 2.5000, 0.0000), (61.0000, -5.0000, 29.0000), 22.8977),
        ((50.0000, 2.5000, 0.0000), (56.0000, -27.0000, -3.0000), 31.9030),
        ((50.0000, 2.5000, 0.0000), (58.0000, 24.0000, 15.0000), 19.4535),
        ((50.0000, 2.5000, 0.0000), (50.0000, 3.1736, 0.5854), 1.0000),
        ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
        ((90.8027, -2.0831, 1.4410), (91.1528, -1.6435, 0.0447), 1.4441),
        ((6.7747, -0.2908, -2.4247), (5.8714, -0.0985, -2.2286), 0.6377),
        ((2.0776, 0.0795, -1.1350), (0.9033, -0.0636, -0.5514), 0.9082),
    ]

    def test_sharma_2005_pairs(self):
        lab1 = np.array([p[0] for p in self.PAIRS])
        lab2 = np.array([p[1] for p in self.PAIRS])
        ref = np.array([p[2] for p in self.PAIRS])
        np.testing.assert_allclose(delta_E_2000(lab1, lab2), ref, atol=1e-4)
        np.testing.assert_allclose(delta_E_2000(lab2, lab1), ref, atol=1e-4)  # symmetric

    def test_zero_for_identical(self):
        assert delta_E_2000([50.0, 10.0, -10.0], [50.0, 10.0, -10.0]) == 0.0


class TestRGBMode:
    def test_flat_spectrum_maps_to_gray(self):
        wl = spectral_grid()
        for c in (0.0, 0.3, 1.0):
            assert_within(spectra_to_rgb_mode(np.full(wl.size, c), wl), [c, c, c], sum_tol(wl.size + 4, c * (np.abs(tristimulus_weights(wl)) @ np.abs(XYZ_to_linear_sRGB(np.eye(3))) / np.abs(XYZ_to_linear_sRGB(white_XYZ(wl)))).sum(0)))  # Σ_i M_ij = 1: W A, Σ W, A, ÷

    def test_flat_spectrum_maps_to_exactly_equal_channels(self):
        # the docstring's "exactly": c Σ_b M_bk is 1 only to rounding (0.5 gave 0.5000000000000001, 0.49999999999999994,
        # 0.49999999999999967), and a grey RGB paint's channels then differ and are solved three times instead of once
        wl = spectral_grid()
        for c in (0.0, 0.3, 0.5, 0.95, 1.0):
            assert spectra_to_rgb_mode(np.full(wl.size, c), wl).tolist() == [c, c, c]
        two = spectra_to_rgb_mode(np.stack([np.full(wl.size, 0.5), np.linspace(0.2, 0.8, wl.size)]), wl)
        assert two[0].tolist() == [0.5] * 3  # a flat row in a batch too; a sloped one is the matrix product
        np.testing.assert_allclose(two[1], np.linspace(0.2, 0.8, wl.size) @ spectra_to_rgb_matrix(wl), rtol=1e-14)

    def test_R_plus_T_equal_one_is_conserved(self):
        wl = spectral_grid()
        rng = np.random.default_rng(1)
        R = rng.uniform(0.0, 1.0, (5, wl.size))
        rgb = spectra_to_rgb_mode(R, wl) + spectra_to_rgb_mode(1.0 - R, wl)
        assert_within(rgb, 1.0, sum_tol(wl.size + 6, (np.abs(R) + np.abs(1.0 - R)) @ (np.abs(tristimulus_weights(wl)) @ np.abs(XYZ_to_linear_sRGB(np.eye(3))) / np.abs(XYZ_to_linear_sRGB(white_XYZ(wl)))), evaluations=3))  # 2 sums, Σ_i M_ij − 1, 1 − R, +

    def test_linear_and_equal_to_xyz_path(self):
        wl = spectral_grid()
        _, R = _colorchecker(10)
        rgb = spectra_to_rgb_mode(R, wl)
        white = XYZ_to_linear_sRGB(white_XYZ(wl))
        direct = XYZ_to_linear_sRGB(reflectance_to_XYZ(R, wl)) / white
        # R @ (W A) against (R @ W) @ A: both round a sum of W·3 products; the bound is relative to the sum of
        # their absolute values (the result cancels: A has negative entries), plus the division
        A = np.abs(XYZ_to_linear_sRGB(np.eye(3)))
        abs_terms = (np.abs(R) @ np.abs(tristimulus_weights(wl))) @ A / np.abs(white)
        assert_within_sum_bound(rgb, direct, wl.size * 3, abs_terms, extra_ops=1)
        assert_within(spectra_to_rgb_mode(R[:2].sum(0), wl), rgb[:2].sum(0), sum_tol(wl.size + 1, np.abs(R[:2]).sum(0) @ (np.abs(tristimulus_weights(wl)) @ np.abs(XYZ_to_linear_sRGB(np.eye(3))) / np.abs(XYZ_to_linear_sRGB(white_XYZ(wl))))))

    def test_weights_are_cached_and_read_only(self):
        W = tristimulus_weights(spectral_grid())
        assert not W.flags.writeable and abs(W[:, 1].sum() - 1.0) <= sum_tol(W.shape[0], np.abs(W[:, 1]).sum(), extra_ops=1)


OBSERVERS = ("CIE 1931 2 Degree Standard Observer", "CIE 1964 10 Degree Standard Observer")


class TestNativeEqualsColourScience:
    """The native default path against colour-science's own functions (docs/colorimetry.md)."""

    @pytest.mark.parametrize("observer", OBSERVERS)
    @pytest.mark.parametrize("illuminant", ["D65", "A", "FL11"])
    @pytest.mark.parametrize("step", [1, 5, 10, 20])
    def test_tristimulus_weights(self, observer, illuminant, step):
        wl = spectral_grid((380, 780), step)
        got = tristimulus_weights(wl, illuminant, observer)
        ref = tristimulus_weights_colour_science(wl, illuminant, observer)
        # measured: max |Δ| 7e-16 of the largest weight; 1e-13 relative on every weight above 1e-6 of it
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
        big = np.abs(ref) > 1e-6 * np.abs(ref).max()
        np.testing.assert_allclose(got[big], ref[big], rtol=1e-12)

    @pytest.mark.parametrize("observer", OBSERVERS)
    def test_tristimulus_weights_from_360_nm(self, observer):
        wl = spectral_grid((360, 780), 10)
        np.testing.assert_allclose(tristimulus_weights(wl, "D65", observer),
                                   tristimulus_weights_colour_science(wl, "D65", observer), rtol=0, atol=1e-15)

    @pytest.mark.parametrize("wl, illuminant", [(spectral_grid((380, 780), 2.5), "D65"),   # 0.83 nm fine nodes
                                                (spectral_grid((380.5, 770.5), 10), "D65"),  # half-nm nodes
                                                (spectral_grid((380, 780), 10), "D50")])      # not tabulated
    def test_other_cases_fall_back_to_colour_science(self, wl, illuminant):
        assert np.array_equal(tristimulus_weights(wl, illuminant), tristimulus_weights_colour_science(wl, illuminant))

    def test_same_domain_errors_as_colour_science(self):
        wl = spectral_grid((370, 780), 10)
        for f in (tristimulus_weights, tristimulus_weights_colour_science):
            with pytest.raises(ValueError, match="common domain 380-780 nm"):
                f(wl, "FL11")

    def test_srgb_matrices_are_the_standards(self):
        cs = colour.RGB_COLOURSPACES["sRGB"]
        N = normalised_primary_matrix(SRGB_PRIMARIES_XY, SRGB_WHITE_XY)
        np.testing.assert_allclose(N, colour.normalised_primary_matrix(cs.primaries, cs.whitepoint), rtol=1e-12)
        np.testing.assert_allclose(N @ [1.0, 1.0, 1.0], colour.xy_to_XYZ(SRGB_WHITE_XY), rtol=1e-14)
        to_xyz, to_rgb = srgb_matrices()
        # IEC 61966-2-1 prints these (and colour-science uses them): equal to the last bit
        assert np.array_equal(to_xyz, cs.matrix_RGB_to_XYZ) and np.array_equal(to_rgb, cs.matrix_XYZ_to_RGB)
        assert to_rgb[0].tolist() == [3.2406, -1.5372, -0.4986]

    def test_xyz_to_linear_srgb(self):
        cs = colour.RGB_COLOURSPACES["sRGB"]
        XYZ = np.random.default_rng(3).uniform(-0.1, 1.1, (50, 3))
        ref = colour.XYZ_to_RGB(XYZ, cs, illuminant=cs.whitepoint, chromatic_adaptation_transform=None,
                                apply_cctf_encoding=False)
        np.testing.assert_allclose(XYZ_to_linear_sRGB(XYZ), ref, rtol=1e-12, atol=1e-15)
        assert np.array_equal(XYZ_to_linear_sRGB(np.eye(3)), colour.XYZ_to_RGB(
            np.eye(3), cs, illuminant=cs.whitepoint, chromatic_adaptation_transform=None, apply_cctf_encoding=False))

    def test_xyz_to_lab(self):
        rng = np.random.default_rng(4)
        XYZ = np.concatenate([rng.uniform(0.0, 1.0, (40, 3)), rng.uniform(0.0, 0.01, (20, 3)),  # both branches
                              rng.uniform(-0.01, 0.0, (5, 3))])
        d65 = colour.CCS_ILLUMINANTS[OBSERVERS[0]]["D65"]
        np.testing.assert_allclose(XYZ_to_Lab(XYZ), colour.XYZ_to_Lab(XYZ, d65), rtol=1e-12, atol=1e-12)
        white = white_XYZ(spectral_grid()) * 0.97
        ref = colour.XYZ_to_Lab(XYZ / white[1], colour.XYZ_to_xy(white))
        np.testing.assert_allclose(XYZ_to_Lab(XYZ, white=white), ref, rtol=1e-12, atol=1e-12)
        # another tabulated white goes through colour-science
        np.testing.assert_allclose(XYZ_to_Lab(XYZ, white="D50"),
                                   colour.XYZ_to_Lab(XYZ, colour.CCS_ILLUMINANTS[OBSERVERS[0]]["D50"]), rtol=1e-15)

    def test_delta_e_2000(self):
        rng = np.random.default_rng(5)
        lab1 = np.column_stack([rng.uniform(0, 100, 200), rng.uniform(-80, 80, 200), rng.uniform(-80, 80, 200)])
        lab2 = lab1 + rng.normal(0, 5, lab1.shape)
        lab2[:20, 1:] = 0.0                                   # achromatic samples (h' = 0 branch)
        lab2[20:40] = lab1[20:40] * [1, -1, -1]               # opposite hues (|Δh'| > 180° branches)
        ref = colour.delta_E(lab1, lab2, method="CIE 2000")
        np.testing.assert_allclose(delta_E_2000(lab1, lab2), ref, rtol=1e-12, atol=1e-13)

    @pytest.mark.parametrize("step", [5, 10, 20])
    def test_rgb_matrix(self, step):
        wl = spectral_grid((380, 780), step)
        cs = colour.RGB_COLOURSPACES["sRGB"]
        W = tristimulus_weights_colour_science(wl)
        A = colour.XYZ_to_RGB(np.eye(3), cs, illuminant=cs.whitepoint, chromatic_adaptation_transform=None,
                              apply_cctf_encoding=False)
        ref = (W @ A) / (W.sum(axis=0) @ A)[None, :]
        np.testing.assert_allclose(spectra_to_rgb_matrix(wl), ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_grids_of_three_to_five_bands_are_carried_linearly():
    """A 5-band grid (too short for Sprague's 6-point scheme) gets weights from linear interpolation:
    a linear ramp's XYZ equals the 1 nm CIE sum of the ramp itself (it crashed before)."""
    wl = np.arange(400.0, 481.0, 20.0)
    W = tristimulus_weights(wl)
    assert W.shape == (5, 3) and np.isclose(W[:, 1].sum(), 1.0)
    fine = np.arange(400, 481)
    S = cie_tables.ILLUMINANTS_1NM["D65"][fine - cie_tables.ILLUMINANT_START_NM["D65"]]
    cmfs = cie_tables.CMFS_1NM[CMFS_NAME][fine - cie_tables.CMFS_START_NM[CMFS_NAME]]
    ramp = lambda w: 0.2 + 0.001 * (w - 400.0)  # noqa: E731
    expect = (ramp(fine) * S) @ cmfs / (S @ cmfs[:, 1])
    np.testing.assert_allclose(ramp(wl) @ W, expect, rtol=1e-13)
