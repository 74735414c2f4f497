"""Thickness-distributed thin films (flakedb.optics.thinfilm.thin_film_thickness_average) against closed
forms, an independently written characteristic-matrix product, energy conservation and brute-force
averages over many thicknesses (a dense trapezoid in z, and an independent Monte Carlo sampler)."""

import numpy as np
import pytest

from flakedb.optics.thinfilm import (
    THICKNESS_NODES_MAX,
    lognormal_thickness_nodes,
    thickness_nodes_needed,
    thin_film_thickness_average,
    thin_film_transfer_matrix,
)

WL = np.linspace(380.0, 780.0, 21)
AL = 0.958 + 6.69j  # Rakić 1995 Al near 550 nm, a constant index for these tests


def _char_matrix_R(n_films, d_nm, wl, cos_a, n_a, n_e, pol):
    """Born & Wolf §1.6 written out directly (unscaled cos/sin, one wavelength and angle): R for 's' or 'p'."""
    sin_a = np.sqrt(1 - cos_a ** 2)
    beta = n_a * sin_a
    def adm(N):
        q = np.sqrt(N * N - beta * beta + 0j)
        q = q if q.imag >= 0 else -q
        return (q if pol == "s" else q / (N * N)), q
    M = np.eye(2, dtype=complex)
    for N, d in zip(n_films, d_nm):
        p, q = adm(N)
        delta = 2 * np.pi / wl * d * q
        M = M @ np.array([[np.cos(delta), -1j * np.sin(delta) / p], [-1j * p * np.sin(delta), np.cos(delta)]])
    pa, _ = adm(n_a)
    pe, _ = adm(n_e)
    B, C = M @ np.array([1.0, pe])
    r = (B * pa - C) / (B * pa + C)
    return abs(r) ** 2


def _brute_1d(n_films, d_nm, rel_sd, group_mask, wl, cos, n_a, m=3001):
    """E[R] over one log-normal factor scaling the films in group_mask: dense trapezoid in z on [-8, 8]."""
    s2 = np.log1p(rel_sd ** 2)
    z = np.linspace(-8, 8, m)
    pdf = np.exp(-z * z / 2)
    pdf /= np.trapezoid(pdf, z)
    R = np.stack([thin_film_transfer_matrix(n_films, np.where(group_mask, np.asarray(d_nm) * np.exp(np.sqrt(s2) * zi - s2 / 2),
                                                                  d_nm), wl, cos, n_a).R for zi in z])
    return np.trapezoid(R * pdf[:, None, None], z, axis=0)


class TestClosedForms:
    def test_no_spread_is_the_transfer_matrix(self):
        n, d, c = [2.6, 1.46, 2.6], [60.0, 106.0, 60.0], np.array([0.3, 0.8, 1.0])
        a = thin_film_thickness_average(n, d, [0.0, 0.0, 0.0], WL, c, 1.5)
        b = thin_film_transfer_matrix(n, d, WL, c, 1.5)
        assert np.array_equal(a.R, b.R) and np.array_equal(a.T, b.T)

    def test_quarter_wave_film_reflectance(self):
        # normal incidence, quarter wave at 550 nm: R = ((n_a n_s - n1²)/(n_a n_s + n1²))² (Born & Wolf §1.6.4)
        n_a, n1, n_s = 1.5, 2.6, 1.6
        rt = thin_film_thickness_average([n1, n_s], [550 / (4 * n1), 1e9], [0.0, 0.0], [550.0], [1.0], n_a, n_s)
        assert rt.R[0, 0] == pytest.approx(((n_a * n_s - n1 ** 2) / (n_a * n_s + n1 ** 2)) ** 2, abs=1e-12)

    @pytest.mark.parametrize("cos_a", [1.0, 0.6, 0.2])
    def test_multilayer_against_direct_characteristic_matrix(self, cos_a):
        n = [2.6, 1.46, 2.6, 1.6, 2.6, 1.46, 2.6]
        d = [60.0, 106.0, 60.0, 400.0, 60.0, 106.0, 60.0]
        rt = thin_film_transfer_matrix(n, d, [450.0, 620.0], [cos_a], 1.5)
        for i, wl in enumerate([450.0, 620.0]):
            assert rt.R_s[i, 0] == pytest.approx(_char_matrix_R(n, d, wl, cos_a, 1.5, 1.5, "s"), abs=1e-12)
            assert rt.R_p[i, 0] == pytest.approx(_char_matrix_R(n, d, wl, cos_a, 1.5, 1.5, "p"), abs=1e-12)


class TestEnergy:
    def test_lossless_stack_with_spread_conserves(self):
        rt = thin_film_thickness_average([2.6, 1.6, 2.6], [52.0, 400.0, 52.0], [0.1, 0.05, 0.1], WL,
                                         np.linspace(0, 1, 7), 1.5, groups=[0, 1, 0])
        np.testing.assert_allclose(rt.R + rt.T, 1.0, rtol=0, atol=1e-12)

    def test_absorbing_stack_R_T_A(self):
        rt = thin_film_thickness_average([1.68, AL, 1.68], [50.0, 20.0, 50.0], [0.2, 0.1, 0.2], WL,
                                         np.linspace(0, 1, 7), 1.5, groups=[0, 1, 0])
        np.testing.assert_allclose(rt.R + rt.T + rt.A, 1.0, rtol=0, atol=1e-12)
        assert np.all(rt.A > 0) and np.all(rt.R >= 0) and np.all(rt.T >= 0)


class TestQuadrature:
    def test_nodes_reproduce_the_lognormal_moments(self):
        for sd in (0.05, 0.2, 0.5):
            f, w = lognormal_thickness_nodes(sd, thickness_nodes_needed(2.6, 120.0, sd, 380.0))
            s2 = np.log1p(sd ** 2)
            assert w @ f == pytest.approx(1.0, abs=1e-12)
            assert w @ f ** 2 == pytest.approx(np.exp(s2), rel=1e-9)  # E f² = e^{σ²} = 1 + rel_sd² (trapezoid: 2e-11 at 0.5)

    @pytest.mark.parametrize("n1, d1, sd", [(2.6, 120.0, 0.1), (2.6, 250.0, 0.2), (2.6, 120.0, 0.3), (1.6, 400.0, 0.2)])
    def test_single_film_against_dense_average(self, n1, d1, sd):
        c = np.array([0.5, 1.0])
        ref = _brute_1d([n1], [d1], sd, np.array([True]), WL, c, 1.5)
        rt = thin_film_thickness_average([n1], [d1], [sd], WL, c, 1.5)
        assert np.abs(rt.R - ref).max() < 1e-5

    def test_symmetric_flake_coatings_move_together(self):
        # TiO2 | Al | TiO2 with the two coatings in one group: a 1-D average, checked densely
        n, d, c = [2.6, AL, 2.6], [60.0, 300.0, 60.0], np.array([0.5, 1.0])
        ref = _brute_1d(n, d, 0.15, np.array([True, False, True]), WL, c, 1.5)
        rt = thin_film_thickness_average(n, d, [0.15, 0.0, 0.15], WL, c, 1.5, groups=[0, 1, 0])
        assert np.abs(rt.R - ref).max() < 1e-6

    def test_two_variables_against_monte_carlo(self):
        # coating and substrate independent; an independent sampler (numpy lognormal), 4000 flakes, 4 standard errors
        rng = np.random.default_rng(35)
        n, d = [2.6, 1.6, 2.6], np.array([60.0, 300.0, 60.0])
        sd_c, sd_s, wl, c = 0.15, 0.1, np.array([450.0, 550.0, 650.0]), np.array([1.0])
        N = 4000
        def draw(sd):
            s = np.sqrt(np.log1p(sd ** 2))
            return rng.lognormal(-s * s / 2, s, N)
        fc, fs = draw(sd_c), draw(sd_s)
        samples = np.stack([thin_film_transfer_matrix(n, d * [a, b, a], wl, c, 1.5).R[:, 0] for a, b in zip(fc, fs)])
        mc, se = samples.mean(axis=0), samples.std(axis=0) / np.sqrt(N)
        rt = thin_film_thickness_average(n, d, [sd_c, sd_s, sd_c], wl, c, 1.5, groups=[0, 1, 0])
        assert np.all(np.abs(rt.R[:, 0] - mc) < 4 * se + 1e-12)

    def test_node_rule_is_bounded(self):
        assert thickness_nodes_needed(2.6, 120.0, 0.0, 380.0) == 1
        assert thickness_nodes_needed(1.52, 1e5, 0.5, 380.0) == THICKNESS_NODES_MAX

    def test_bad_inputs(self):
        with pytest.raises(ValueError, match="rel_sd"):
            thin_film_thickness_average([2.6], [100.0], [-0.1], WL, [1.0], 1.5)
        with pytest.raises(ValueError, match="groups"):
            thin_film_thickness_average([2.6], [100.0], [0.1], WL, [1.0], 1.5, groups=[0.5])
