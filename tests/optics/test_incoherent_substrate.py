"""The incoherent-substrate flake (flakedb.optics.thinfilm.incoherent_substrate_flake) against the coherent
transfer-matrix code averaged by brute force over the substrate's thickness, a closed form and energy."""

import numpy as np
import pytest

from flakedb.optics.thinfilm import (_power, _prepare, _lognormal_factor, _z_nodes, incoherent_substrate_flake,
                                     thin_film_transfer_matrix)
from tests.tolerances import U

N_TIO2, N_FE2O3 = 2.6 + 0.0j, 3.0 + 0.4j  # a lossless and an absorbing coating film (representative values)
N_MICA, N_BINDER = 1.6, 1.5
COAT_N, COAT_D = [N_FE2O3, N_TIO2], [8.0, 52.0]  # outside -> in, as mica-tio2-fe2o3-gold
D0 = 400.0


def _coherent_average(wl, cos, periods=20, per_period=256):
    """Brute force: the coherent flake's R_s, R_p, T_s, T_p averaged over substrate thicknesses uniform on
    [D0, D0 + periods · λ / (2 q_s)] (q_s = n cos θ in the mica), ``per_period`` equally spaced nodes per
    period (the periodic trapezoid rule on a whole number of periods of R(d))."""
    q_s = np.sqrt(N_MICA**2 - N_BINDER**2 * (1 - cos**2))
    K = periods * per_period
    d_sub = D0 + (wl / (2 * q_s)) * np.arange(K) / per_period
    n_films = COAT_N + [N_MICA] + COAT_N[::-1]
    d = np.empty((5, K))
    d[[0, 1, 3, 4]] = np.array(COAT_D + COAT_D[::-1])[:, None]
    d[2] = d_sub
    n, _, wl_, cos_, n_a, n_e = _prepare(n_films, np.zeros(5), [wl], [cos], N_BINDER, None)
    rt = _power(n, d, wl_, cos_, n_a, n_e)  # each (1, K, 1)
    return [x[0, :, 0].mean() for x in (rt.R_s, rt.R_p, rt.T_s, rt.T_p)], K


@pytest.mark.parametrize("wl", [420.0, 550.0, 690.0])
@pytest.mark.parametrize("cos", [1.0, 0.6, 0.15])
def test_equals_brute_force_average_of_the_coherent_flake(wl, cos):
    inc = incoherent_substrate_flake(COAT_N, COAT_D, N_MICA, D0, [wl], [cos], N_BINDER)
    ref, K = _coherent_average(wl, cos)
    # Error budget: the 256-node periodic trapezoid rule aliases the Fourier coefficients of R(phase) beyond
    # order 256, which decay like |r'|^n (|r'| < 0.8 here at cos 0.15, s: 0.8^256 = 1e-25; at 64 nodes the
    # measured error was 9e-9); rounding: each coherent member carries ~ 100 u of a 10^2-rad phase.
    tol = K * 100 * U  # 5.7e-11
    got = [inc.R_s[0, 0], inc.R_p[0, 0], inc.T_s[0, 0], inc.T_p[0, 0]]
    np.testing.assert_allclose(got, ref, rtol=0, atol=tol)
    # and the coherent member at D0 alone is far from it: the test sees the fringes
    one = thin_film_transfer_matrix(COAT_N + [N_MICA] + COAT_N[::-1], COAT_D + [D0] + COAT_D[::-1], [wl], [cos],
                                    N_BINDER)
    assert max(abs(one.R_s[0, 0] - ref[0]), abs(one.R_p[0, 0] - ref[1])) > 1e3 * tol


def _fresnel(n1, n2, cos1):
    cos2 = np.sqrt(1 - (n1 / n2) ** 2 * (1 - cos1**2) + 0j)
    rs = (n1 * cos1 - n2 * cos2) / (n1 * cos1 + n2 * cos2)
    rp = (n2 * cos1 - n1 * cos2) / (n2 * cos1 + n1 * cos2)
    return abs(rs) ** 2, abs(rp) ** 2, cos2


@pytest.mark.parametrize("cos", [1.0, 0.5, 0.05])
@pytest.mark.parametrize("k", [0.0, 2e-4])
def test_bare_slab_closed_form(cos, k):
    """No coating: R = r + (1-r)² r a² / (1 - r² a²), T = (1-r)² a / (1 - r² a²) per polarisation,
    a = exp(-4π k d / λ · Im-part of q_s / k) (= exp(-4π k d / (λ cos θ_s)) to O(k²))."""
    wl, d = 550.0, 2000.0
    inc = incoherent_substrate_flake([], [], N_MICA + 1j * k, d, [wl], [cos], N_BINDER)
    Rs, Rp, cos2 = _fresnel(N_BINDER, N_MICA, cos)
    q = np.sqrt((N_MICA + 1j * k) ** 2 - N_BINDER**2 * (1 - cos**2))
    a = np.exp(-4 * np.pi * d / wl * q.imag)
    if k:
        assert a < 1 and abs(a - np.exp(-4 * np.pi * k * d / (wl * cos2.real))) < 1e-6
    for r, R, T in ((Rs, inc.R_s, inc.T_s), (Rp, inc.R_p, inc.T_p)):
        den = 1 - r * r * a * a
        np.testing.assert_allclose(R[0, 0], r + (1 - r) ** 2 * r * a * a / den, rtol=0, atol=64 * U)
        np.testing.assert_allclose(T[0, 0], (1 - r) ** 2 * a / den, rtol=0, atol=64 * U)


def test_energy():
    wl = np.linspace(400.0, 700.0, 7)
    cos = np.array([1.0, 0.8, 0.4, 0.1, 1e-3, 0.0])
    # lossless coating and substrate: R + T = 1 (R and T come from different formulas), also beyond the
    # substrate's critical angle (a lower-index substrate than the binder: nothing enters it, R = 1)
    for n_sub in (N_MICA, 1.40):
        rt = incoherent_substrate_flake([N_TIO2, 1.46], [60.0, 106.0], n_sub, D0, wl, cos, N_BINDER)
        np.testing.assert_allclose(rt.R + rt.T, 1.0, rtol=0, atol=64 * U)
        assert np.all(rt.R >= 0) and np.all(rt.T >= 0)
    # absorbing coating or substrate: 0 < A < 1, and A grows with the substrate's k
    As = []
    for k in (0.0, 1e-4, 1e-3):
        rt = incoherent_substrate_flake(COAT_N, COAT_D, N_MICA + 1j * k, D0, wl, cos[:4], N_BINDER)
        assert np.all(rt.A > 0) and np.all(rt.A < 1) and np.all(rt.R > 0) and np.all(rt.T > 0)
        As.append(rt.A)
    assert np.all(As[1] > As[0]) and np.all(As[2] > As[1])
    # an absorbing coating reflects differently from its two sides: R1' != R1 matters
    fwd = incoherent_substrate_flake(COAT_N, COAT_D, N_MICA, D0, wl, cos, N_BINDER)
    assert np.all(np.isfinite(fwd.R)) and np.all(np.abs(fwd.A[:, :4]) > 1e-3)


def test_coating_spread_is_the_power_average_over_its_nodes():
    wl, cos, sd, m = np.array([450.0, 600.0]), np.array([1.0, 0.5]), 0.1, 31
    got = incoherent_substrate_flake(COAT_N, COAT_D, N_MICA, D0, wl, cos, N_BINDER, coating_rel_sd=sd, n_nodes=m)
    z, w = _z_nodes(m)
    f = _lognormal_factor(sd, z)
    ref = sum(wi * incoherent_substrate_flake(COAT_N, np.array(COAT_D) * fi, N_MICA, D0, wl, cos, N_BINDER).R
              for fi, wi in zip(f, w))
    np.testing.assert_allclose(got.R, ref, rtol=0, atol=4 * m * U)


def test_substrate_spread_averages_the_absorption_only():
    """A lossless substrate's spread changes nothing; an absorbing one's is the bare-slab closed form averaged
    over the log-normal thickness (here by a 2001-node trapezoid rule in z, independent of the code's nodes)."""
    wl, cos = np.array([500.0]), np.array([1.0])
    a0 = incoherent_substrate_flake(COAT_N, COAT_D, N_MICA, D0, wl, cos, N_BINDER)
    a1 = incoherent_substrate_flake(COAT_N, COAT_D, N_MICA, D0, wl, cos, N_BINDER, substrate_rel_sd=0.3)
    np.testing.assert_array_equal(a1.R, a0.R)
    k, d, sd = 5e-3, 3000.0, 0.3
    got = incoherent_substrate_flake([], [], N_MICA + 1j * k, d, wl, cos, N_BINDER, substrate_rel_sd=sd)
    r = ((N_MICA - N_BINDER) / (N_MICA + N_BINDER)) ** 2
    z = np.linspace(-7.5, 7.5, 2001)
    w = np.exp(-z * z / 2)
    w /= w.sum()
    a = np.exp(-4 * np.pi * k * d * _lognormal_factor(sd, z) / wl[0])
    R_ref = w @ (r + (1 - r) ** 2 * r * a * a / (1 - r * r * a * a))
    T_ref = w @ ((1 - r) ** 2 * a / (1 - r * r * a * a))
    assert abs(got.T[0, 0] - T_ref) < 1e-9 and abs(got.R[0, 0] - R_ref) < 1e-9
    one = incoherent_substrate_flake([], [], N_MICA + 1j * k, d, wl, cos, N_BINDER)
    assert abs(one.T[0, 0] - T_ref) > 1e-3  # the spread matters here


def test_catalogue_field_dispatches_and_defaults_to_coherent():
    """substrate.coherence: absent or 'coherent' gives the coherent flake bit for bit; 'incoherent' gives
    incoherent_substrate_flake on the entry's films; an unknown value is refused by the schema, by path."""
    import copy

    from flakedb.paint.catalog import get_species, load_catalog, validate_catalog
    from flakedb.paint.species import binder_index, film_spreads, film_stack, flake_reflectance_transmittance
    from flakedb.paint.materials import refractive_index

    doc = load_catalog()
    wl, cos = np.array([450.0, 550.0, 650.0]), np.array([1.0, 0.5])
    nb = binder_index(doc, wl)
    e = get_species("mica-tio2-pearl", doc)
    assert e["substrate"]["coherence"]["value"] == "incoherent"
    coh = copy.deepcopy(e)
    coh["substrate"].pop("coherence")
    explicit = copy.deepcopy(e)
    explicit["substrate"]["coherence"]["value"] = "coherent"
    R0, T0 = flake_reflectance_transmittance(coh, wl, cos, nb)
    R1, T1 = flake_reflectance_transmittance(explicit, wl, cos, nb)
    np.testing.assert_array_equal(R0, R1)
    np.testing.assert_array_equal(T0, T1)
    R, T = flake_reflectance_transmittance(e, wl, cos, nb)
    mats, d = film_stack(e)
    n = np.stack([refractive_index(m, wl) for m in mats], axis=1)
    _, sd = film_spreads(e)
    ref = incoherent_substrate_flake(n[:, :1], d[:1], n[:, 1], d[1], wl, cos, nb, coating_rel_sd=sd[:1])
    np.testing.assert_array_equal(R, ref.R)
    assert np.abs(R - R0).max() > 0.05  # the mica's fringes: the two treatments differ visibly
    bad = copy.deepcopy(doc)
    bad["particles"]["mica-tio2-pearl"]["substrate"]["coherence"]["value"] = "partial"
    probs = validate_catalog(bad)
    assert any("particles.mica-tio2-pearl.substrate.coherence" in p for p in probs), probs
