"""A flake's beam in the texture model (flakedb.texture.model.beam_collected, docs/texture.md §3.2): the Airy
pattern of a circular flake at its own wavelengths, the refracted source and aperture as the ellipses they are.
Guards against the uniform diffraction disc of the same peak (half maximum at 0.637 λ'/D instead of Airy's
0.514: glints 1.5× too many), 555 nm whatever the flake's colour, and circular cones of equal area."""

import numpy as np
import pytest
from scipy.special import j0, j1

from flakedb.texture import model as tm

#: x = π D θ/λ at the half maximum of [2 J1(x)/x]² (Born & Wolf §8.5.2: 1.6163), and its first zero (3.8317).
X_HALF, X_ZERO = 1.616339948, 3.831705970


def _geometry(light_deg, view_deg=0.0, source_deg=1.0, aperture_rad=np.radians(0.5), eta=1.5):
    return tm.directional_geometry(eta, light_deg, view_deg, source_deg, aperture_rad)


def test_airy_pattern_closed_forms():
    """Unit integral over solid angle (encircled energy 1 − J0² − J1², Rayleigh), peak A/λ², half maximum at
    0.514 λ/D, zero at 1.22 λ/D, and the transfer function is its Fourier transform (Hankel transform)."""
    D, lam = 20.0, 0.37
    assert tm.airy_pattern(0.0, D, lam) == pytest.approx(np.pi * D * D / 4 / lam**2, rel=1e-12)
    assert tm.airy_pattern(X_HALF * lam / (np.pi * D), D, lam) == pytest.approx(0.5 * tm.airy_pattern(0.0, D, lam), rel=1e-8)
    assert X_HALF / np.pi == pytest.approx(0.5145, abs=1e-4)
    assert tm.airy_pattern(X_ZERO * lam / (np.pi * D), D, lam) < 1e-12 * tm.airy_pattern(0.0, D, lam)
    x_out = 40.0
    th = np.linspace(0.0, x_out * lam / (np.pi * D), 200001)
    enc = np.trapezoid(tm.airy_pattern(th, D, lam) * 2 * np.pi * th, th)
    assert enc == pytest.approx(1.0 - j0(x_out) ** 2 - j1(x_out) ** 2, rel=1e-6)
    for nu in (0.2, 0.5, 0.8):  # OTF(ν λ/D) = ∫ PSF(θ) J0(2π ν θ) 2π θ dθ (cycles per rad, ν in D/λ units)
        th = np.linspace(0.0, 400.0 * lam / (np.pi * D), 400001)
        ft = np.trapezoid(tm.airy_pattern(th, D, lam) * j0(2 * np.pi * nu * D / lam * th) * 2 * np.pi * th, th)
        assert ft == pytest.approx(float(tm.airy_otf(nu)), abs=2e-3)


def _profile(g, D, lam):
    x, f = tm.beam_collected(g, D, [lam], [1.0])
    order = np.argsort(x)
    return x[order], f[order][:, 0] / f[0, 0], f[0][order] / f[0, 0]  # along ∥ and ⊥ (δ_other = 0)


def test_small_cones_see_the_airy_pattern():
    """Source and aperture much smaller than λ'/D: the collected fraction against the offset is the Airy
    pattern itself, half maximum at 0.514 λ'/D across the plane of incidence and 0.514 λ'/(D c) in it (the
    flake's projection is D c × D)."""
    g = _geometry(15.0, source_deg=0.002, aperture_rad=3e-5)
    D, lam = 20.0, 0.55 / 1.5
    x, par, perp = _profile(g, D, lam)
    half_perp = np.interp(-0.5, -perp[x >= 0], x[x >= 0])
    half_par = np.interp(-0.5, -par[x >= 0], x[x >= 0])
    assert half_perp == pytest.approx(X_HALF / np.pi * lam / D, rel=0.01)
    assert half_par == pytest.approx(X_HALF / np.pi * lam / (D * g.c), rel=0.01)
    inside = (x > 0) & (x < 0.9 * X_ZERO / np.pi * lam / D)
    want = tm.airy_pattern(x[inside], D, lam) / tm.airy_pattern(0.0, D, lam)
    assert np.max(np.abs(perp[inside] - want)) < 5e-3


def test_without_diffraction_the_cones_overlap_as_discs():
    """A flake far larger than λ'/D (no diffraction to speak of), light and view along the normal (both cones
    circles in the binder, radius r/η): f(d) = lens(d; r_s', r_a')/(π r_s'²), the overlap of two discs."""
    g = _geometry(0.0, source_deg=1.0, aperture_rad=np.radians(0.5))
    assert g.s_par == pytest.approx(g.s_perp) and g.a_par == pytest.approx(g.a_perp)
    x, f = tm.beam_collected(g, 2e5, [0.37], [1.0])
    d = np.abs(x)
    want = tm.lens_area(d, g.s_perp, g.a_perp) / (np.pi * g.s_perp**2)
    assert np.max(np.abs(f[:, 0] - want)) < 0.02 * want.max()
    assert f[0, 0] == pytest.approx((g.a_perp / g.s_perp) ** 2, rel=2e-3)


def test_the_refracted_source_is_an_ellipse():
    """Light at 75° (η 1.5): the source's cone in the binder is r μ_l/(η μ_l') in the plane of incidence and r/η
    across it (Snell, small cones), 0.34× as wide; with a tiny aperture and no diffraction the collected
    fraction is the source's indicator: above half inside the ellipse, below half outside, on both axes."""
    g = _geometry(75.0, source_deg=2.0, aperture_rad=1e-5)
    mu_l, mu_lb = np.cos(np.radians(75.0)), np.sqrt(1 - (np.sin(np.radians(75.0)) / 1.5) ** 2)
    r = np.radians(2.0)
    assert g.s_par == pytest.approx(r * mu_l / (1.5 * mu_lb), rel=1e-12)
    assert g.s_perp == pytest.approx(r / 1.5, rel=1e-12)
    assert g.s_par / g.s_perp == pytest.approx(0.338, abs=1e-3)
    x, f = tm.beam_collected(g, 2e5, [0.37], [1.0])
    phi = f / f[0, 0]
    for axis, semi in ((0, g.s_par), (1, g.s_perp)):
        line = phi[:, 0] if axis == 0 else phi[0, :]
        assert np.all(line[(np.abs(x) < 0.85 * semi)] > 0.5)
        assert np.all(line[(np.abs(x) > 1.15 * semi)] < 0.5)


def test_a_flake_diffracts_at_its_own_colours():
    """The wavelengths of a flake's pattern are its luminance-weighted reflectance's: a flake that reflects the
    red half of the spectrum gets a pattern (λ'/D) wider than one that reflects the blue half."""
    stack = tm.TextureStack(1.5, np.full(16, 1 / 16), (), (), np.linspace(400.0, 700.0, 16))
    blue = np.where(stack.wavelength_nm < 550, 1.0, 0.0)
    lam_b, w_b = tm._diffraction_bands(stack, blue)
    lam_r, w_r = tm._diffraction_bands(stack, 1.0 - blue)
    assert w_b.sum() == pytest.approx(1.0) and w_r.sum() == pytest.approx(1.0)
    mean_b, mean_r = lam_b @ w_b * 1.5e3, lam_r @ w_r * 1.5e3  # back to nm in air
    assert mean_b == pytest.approx(stack.wavelength_nm[:8].mean(), rel=1e-12)
    assert mean_r == pytest.approx(stack.wavelength_nm[8:].mean(), rel=1e-12)
    g = _geometry(15.0, source_deg=0.002, aperture_rad=3e-5)
    widths = []
    for lam, w in ((lam_b, w_b), (lam_r, w_r)):
        x, f = tm.beam_collected(g, 20.0, lam, w)
        prof = f[0] / f[0, 0]
        order = np.argsort(x)
        xs, ps = x[order], prof[order]
        widths.append(np.interp(-0.5, -ps[xs >= 0], xs[xs >= 0]))
    assert widths[1] / widths[0] == pytest.approx(mean_r / mean_b, rel=0.03)


# ----------------------------------------------------------------------------------------------
# Glints a person and an instrument share (issue #36 item 2)
# ----------------------------------------------------------------------------------------------


def _surface_layer(R, D=16.0, gsd=1.0, rho=1e-7):
    """A thin layer of identical flakes at the surface (no attenuation to speak of), grey R."""
    c = np.linspace(0.0, 1.0, 5)
    f = tm.FlakeLayer("f", 0.0, 1.0, rho, D, gsd, 0.3, 0.2, c, np.full((1, 5), R), np.zeros((1, 5)))
    return tm.TextureStack(1.5, np.array([1.0]), (f,))


def test_the_reference_flake_meets_the_fixed_threshold_at_half_its_peak():
    """Flakes that are the threshold's own reference (R = 1, 16 µm, 555 nm, unattenuated): the fixed-luminance
    count is the half-peak count, and the threshold is half their peak."""
    from tests.texture.cases import TEST_OBSERVER

    r = tm.sparkle_indices(_surface_layer(1.0), TEST_OBSERVER, 15.0)
    assert r["glint_threshold_luminance_factor"] == pytest.approx(0.5 * r["peak_luminance_factor"], rel=1e-12)
    assert r["glints_per_mm2_above_threshold"] == pytest.approx(r["glints_per_mm2"], rel=5e-3)


def test_the_fixed_threshold_sees_brightness_the_half_peak_count_does_not():
    """Halving every flake's reflectance leaves the half-peak count as it is (each flake against its own
    peak) but lowers the count above the fixed luminance; bigger flakes, brighter peaks: the fixed count of
    20 µm flakes exceeds the half-peak one, of 8 µm flakes falls below it."""
    from tests.texture.cases import TEST_OBSERVER

    a, b = (tm.sparkle_indices(_surface_layer(R), TEST_OBSERVER, 15.0) for R in (1.0, 0.5))
    assert b["glints_per_mm2"] == pytest.approx(a["glints_per_mm2"], rel=1e-9)
    assert b["glints_per_mm2_above_threshold"] < 0.8 * a["glints_per_mm2_above_threshold"]
    big, small = (tm.sparkle_indices(_surface_layer(1.0, D=D), TEST_OBSERVER, 15.0) for D in (20.0, 8.0))
    assert big["glints_per_mm2_above_threshold"] > big["glints_per_mm2"]
    assert small["glints_per_mm2_above_threshold"] < small["glints_per_mm2"]


@pytest.mark.parametrize("ratio", [0.3, 1.0, 3.0])
def test_spot_fill_against_random_placements(ratio):
    """spot_fill (the brightest spot's share of a glint) against random disc positions rasterised on a fine
    sub-grid, independently: limits A/p² (small flakes, less where they straddle a border) and 1."""
    p = 15.0
    D = ratio * p
    rng = np.random.default_rng(1)
    sub = 120  # sub-cells per spot side
    u = (np.arange(-2 * sub, 3 * sub) + 0.5) / sub * p  # sample points over 5 × 5 spots
    X, Y = np.meshgrid(u, u, indexing="ij")
    fills = []
    for _ in range(200):
        cx, cy = rng.random(2) * p + 0.0
        inside = (X - cx) ** 2 + (Y - cy) ** 2 <= (D / 2) ** 2
        cells = np.floor(X[inside] / p).astype(int) * 100 + np.floor(Y[inside] / p).astype(int)
        fills.append(np.bincount(cells - cells.min()).max() / sub**2)
    assert tm.spot_fill(D, p) == pytest.approx(np.mean(fills), abs=3 * np.std(fills) / np.sqrt(200) + 0.01)
    assert tm.spot_fill(D, p) <= min(1.0, np.pi * D * D / 4 / p**2) + 1e-12


def test_spot_fill_of_flakes_much_larger_than_the_spot():
    """A disc of diameter ≥ 2√2 p holds the whole spot its centre lies in (that spot is within √2 p of the
    centre): spot_fill is exactly 1, which the binned estimate already gives from 2.5 p; a schema-valid flake of
    1000 µm with diameter_gsd 3 (diameters to ~75 mm) under the 15 µm BYK-like spot asked the binning for
    40 GiB (`flakedb texture`: out of memory); 75 mm here (205 GB before) is immediate."""
    p = 15.0
    tm._spot_fill_one.cache_clear()
    assert [tm.spot_fill(r * p, p) for r in (2.5, 2.7, 2.82)] == [1.0, 1.0, 1.0]   # binned, below the bound
    assert tm.spot_fill(np.array([2.83, 10.0, 5000.0]) * p, p).tolist() == [1.0, 1.0, 1.0]
