"""The Fabry-Perot colour-shift flake (`colour-shift-cr-mgf2-al`, ChromaFlair type: Cr | MgF2 | Al | MgF2 | Cr):
its reflectance is the nested Airy recursion of its five films (independent of the transfer-matrix code), its
thickness spread is the brute-force average over flakes, its colour moves to shorter wavelengths as it tilts
(the Fabry-Perot phase 2 n d cos θ), and a recipe sets and fits the absorber and the spacer."""

import numpy as np
import pytest

from flakedb.optics.fresnel import fresnel_amplitudes
from flakedb.paint.catalog import get_species, load_catalog
from flakedb.paint.materials import refractive_index
from flakedb.paint.recipe_checks import flake_entry_with_films
from flakedb.paint.species import binder_index, film_spreads, film_stack, flake_reflectance_transmittance
from tests.tolerances import U

NAME = "colour-shift-cr-mgf2-al"
WL = np.arange(400.0, 701.0, 10.0)
COS = np.array([1.0, 0.9, 0.7, 0.5, 0.2])


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


def airy_stack_R(n_films, d_nm, wl, cos_a, n_a):
    """Unpolarised R (W, A) of films (W, F) between two half-spaces of real index n_a (W,): the Airy formula
    applied from the exit up, r ← (r_{j-1,j} + r e^{2iβ_j}) / (1 + r_{j-1,j} r e^{2iβ_j}) (Born & Wolf §1.6.4,
    the same recursion Abelès' matrices multiply out), Fresnel amplitudes from flakedb.optics.fresnel."""
    W, F = n_films.shape
    N = np.concatenate([n_a[:, None], n_films, n_a[:, None]], axis=1).astype(complex)      # (W, F+2)
    cos = [np.broadcast_to(np.asarray(cos_a, float)[None, :], (W, cos_a.size)).astype(complex)]
    amps = []
    for j in range(F + 1):                                                                 # interface j | j+1
        f = fresnel_amplitudes(cos[j], N[:, j:j + 1], N[:, j + 1:j + 2])
        amps.append(f)
        cos.append(f.cos_theta_t)
    R = 0.0
    for pol in ("s", "p"):
        r = getattr(amps[F], "r_" + pol)
        for j in range(F, 0, -1):
            beta = 2 * np.pi / wl[:, None] * d_nm[j - 1] * N[:, j:j + 1] * cos[j]
            ph = np.exp(2j * beta)
            r12 = getattr(amps[j - 1], "r_" + pol)
            r = (r12 + r * ph) / (1 + r12 * r * ph)
        R = R + 0.5 * np.abs(r) ** 2
    return R


def _films(entry, wl):
    mats, d = film_stack(entry)
    return np.stack([refractive_index(m, wl) for m in mats], axis=1), np.asarray(d, float)


def test_flake_is_the_airy_recursion_of_its_films(catalog):
    # every flake alike (spreads 0): the species' R is the Airy recursion of Cr | MgF2 | Al | MgF2 | Cr in the
    # binder, for the catalogue stack and for thin absorbers / other spacers a recipe may set; T is ~0 (80 nm Al)
    nb = binder_index(catalog, WL)
    base = get_species(NAME, catalog)
    assert film_stack(base)[0] == ["Cr", "MgF2", "Al", "MgF2", "Cr"]
    for cr, mgf2 in ((5.0, 380.0), (2.0, 250.0), (12.0, 600.0)):
        e = flake_entry_with_films(base, {"coating_thickness_nm": [cr, mgf2], "coating_thickness_rel_sd": 0.0})
        R, T = flake_reflectance_transmittance(e, WL, COS, nb)
        n, d = _films(e, WL)
        # the two evaluations each sum ~ 4 products per film and interface: a few hundred roundings of O(1) terms
        np.testing.assert_allclose(R, airy_stack_R(n, d, WL, COS, nb), rtol=0, atol=1e4 * U)
        assert np.all(T < 1e-4)


def test_thickness_spread_is_the_brute_force_average(catalog):
    # the catalogue flake varies (Cr 5 % and MgF2 3 %, one shared log-normal variable for a flake's coating,
    # flakedb.paint.species.film_spreads): its R is the average of single-flake R over that distribution,
    # computed here by 200-node Gauss-Hermite quadrature of the Airy recursion (exact for this smooth integrand
    # to far below 1e-6; flakedb's own rule is a trapezoid with its own node count)
    e = get_species(NAME, catalog)
    nb = binder_index(catalog, WL)
    R, _ = flake_reflectance_transmittance(e, WL, COS, nb)
    n, d = _films(e, WL)
    groups, sd = film_spreads(e)
    assert np.all(sd[groups == 0] > 0) and sd[groups == 1] == 0
    z, w = np.polynomial.hermite_e.hermegauss(200)
    w = w / w.sum()
    s2 = np.log1p(sd ** 2)
    avg = sum(wk * airy_stack_R(n, d * np.exp(np.sqrt(s2) * zk - s2 / 2), WL, COS, nb) for zk, wk in zip(z, w))
    np.testing.assert_allclose(R, avg, rtol=0, atol=1e-6)
    # and the spread matters: the single flake differs from the average by more than that
    single = airy_stack_R(n, d, WL, COS, nb)
    assert np.abs(single - avg).max() > 0.01


def test_colour_moves_to_shorter_wavelengths_with_tilt(catalog):
    # Fabry-Perot: a reflectance minimum of order m sits where 4π n d cos θ_MgF2 / λ + φ(λ, θ) = (2m+1)π, φ the
    # reflection phases at Cr and Al; φ changes little with angle, so λ_min(θ) / λ_min(0) ≈ cos θ_MgF2 (Snell from
    # the binder).  The first-order minimum (near 700 nm at normal incidence) moves by that ratio to within 0.04 (measured: 698 -> 548 nm at cos 0.8 in the binder, ratio 0.785 against cos θ_MgF2 0.756: the rest is φ).
    e = flake_entry_with_films(get_species(NAME, catalog), {"coating_thickness_rel_sd": 0.0})
    wl = np.arange(380.0, 1001.0, 1.0)
    nb = binder_index(catalog, wl)
    R, _ = flake_reflectance_transmittance(e, wl, [1.0, 0.8], nb)
    win0 = (wl > 600) & (wl < 950)
    l0 = wl[win0][np.argmin(R[win0, 0])]
    n_mg = refractive_index("MgF2", np.array([l0])).real[0]
    cos_mg = np.sqrt(1 - (1.5 ** 2) * (1 - 0.8 ** 2) / n_mg ** 2)
    win1 = (wl > l0 * cos_mg - 40) & (wl < l0 * cos_mg + 40)
    l1 = wl[win1][np.argmin(R[win1, 1])]
    assert l1 < l0
    assert abs(l1 / l0 - cos_mg) < 0.04, (l0, l1, cos_mg)
