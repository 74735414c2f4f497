"""Thin-film stacks by the characteristic-matrix method (flakedb.optics.thinfilm).

Guards against: energy not conserved (R + T != 1 for lossless stacks, negative absorptance), a
missing n cos θ factor in T (wrong off-normal or with n_exit != n_ambient), wrong p-polarisation
admittance, wrong film order or phase sign, overflow / NaN for thick absorbing films (exp of a large
imaginary phase) and at grazing incidence or TIR, a wrong evanescent branch, broken broadcasting of
per-wavelength indices, and any disagreement with an independent code: S. Byrnes' ``tmm`` (0.2.0,
Fresnel-coefficient transfer matrices), compared on random stacks to 1e-10.
"""

import numpy as np
import pytest
import tmm
from hypothesis import given, settings
from hypothesis import strategies as st

from flakedb.optics.fresnel import fresnel_amplitudes
from flakedb.optics.thinfilm import (
    flake_reflectance_transmittance,
    thin_film_amplitudes,
    thin_film_transfer_matrix,
)

RAISE = dict(divide="raise", over="raise", invalid="raise")  # underflow to 0 is benign
# Al at 563.57 nm, Rakić 1995 (refractiveindex.info, shared/data/optical-constants/Al_Rakic1995.csv)
N_AL = 1.0728 + 6.7839j
# MgF2 (ordinary ray) at 550 nm, Dodge 1984 (shared/data/optical-constants/MgF2_Dodge1984.csv)
N_MGF2 = 1.378506


def _random_stack(rng, absorbing):
    F = int(rng.integers(1, 6))
    n = rng.uniform(1.0, 3.0, F) + 0j
    if absorbing:
        lossy = rng.random(F) < 0.5
        n = np.where(lossy, rng.uniform(0.1, 3.0, F) + 1j * rng.uniform(0.0, 7.0, F), n)
    d = rng.uniform(0.0, 400.0, F)
    return n, d


def _tmm(pol, n_a, n, d, n_e, cos, wl):
    return tmm.coh_tmm(pol, [n_a, *n, n_e], [np.inf, *d, np.inf], np.arccos(cos), wl)


class TestEnergy:
    def test_lossless_conserves_energy(self):
        rng = np.random.default_rng(20)
        wl = np.linspace(380, 780, 41)
        cos = np.concatenate([[0.0, 1e-12, 1e-6], np.linspace(0, 1, 50), [1.0]])
        worst = 0.0
        for _ in range(40):
            n, d = _random_stack(rng, absorbing=False)
            n_a, n_e = rng.uniform(1.0, 2.0, 2)  # n_e < n_a sin θ: TIR into the exit; films may be evanescent
            with np.errstate(**RAISE):
                rt = thin_film_transfer_matrix(n, d, wl, cos, n_a, n_e)
            for pol in ("s", "p"):
                R, T = getattr(rt, "R_" + pol), getattr(rt, "T_" + pol)
                assert np.all((R >= 0) & (R <= 1 + 1e-12) & (T >= 0) & (T <= 1 + 1e-12))
                worst = max(worst, np.abs(1 - R - T).max())
        assert worst < 1e-12

    def test_absorbing_nonnegative_absorptance(self):
        rng = np.random.default_rng(21)
        wl = np.linspace(380, 780, 41)
        cos = np.linspace(0, 1, 60)
        for _ in range(40):
            n, d = _random_stack(rng, absorbing=True)
            n_e = rng.uniform(1.0, 2.0) + 1j * rng.choice([0.0, rng.uniform(0, 5)])
            with np.errstate(**RAISE):
                rt = thin_film_transfer_matrix(n, d, wl, cos, rng.uniform(1.0, 2.0), n_e)
            for pol in ("s", "p"):
                R, T = getattr(rt, "R_" + pol), getattr(rt, "T_" + pol)
                assert np.all(1 - R - T >= -1e-12)
                assert np.all((R >= 0) & (T >= 0))
            np.testing.assert_allclose(rt.R + rt.T + rt.A, 1.0, atol=1e-15)


class TestClosedForms:
    def test_bare_interface_equals_fresnel(self):
        wl = np.array([400.0, 550.0, 700.0])
        cos = np.linspace(0, 1, 101)
        n_a, n_e = 1.5, 1.2 + 0.3j
        amp = fresnel_amplitudes(cos, n_a, n_e)
        Ts_ref = np.abs(amp.t_s) ** 2 * (n_e * amp.cos_theta_t).real / (n_a * cos + 1e-300)
        for n, d in (([], []), ([2.0 + 0.5j, 1.3], [0.0, 0.0])):  # no films / films of zero thickness
            rt = thin_film_transfer_matrix(n, d, wl, cos, n_a, n_e)
            a = thin_film_amplitudes(n, d, wl, cos, n_a, n_e)
            np.testing.assert_allclose(rt.R_s, np.broadcast_to(np.abs(amp.r_s) ** 2, (3, 101)), atol=1e-14)
            np.testing.assert_allclose(rt.R_p, np.broadcast_to(np.abs(amp.r_p) ** 2, (3, 101)), atol=1e-14)
            np.testing.assert_allclose(rt.T_s[:, 1:], np.broadcast_to(Ts_ref[1:], (3, 100)), atol=1e-14)
            for x, y in ((a.r_s, amp.r_s), (a.r_p, amp.r_p), (a.t_s, amp.t_s), (a.t_p, amp.t_p)):
                np.testing.assert_allclose(x, np.broadcast_to(y, (3, 101)), atol=1e-14)

    @pytest.mark.parametrize("n_a,n_f,n_s", [(1.0, 1.38, 1.52), (1.5, 2.4, 1.5), (1.5, 1.2, 1.0)])
    def test_quarter_wave(self, n_a, n_f, n_s):
        """Quarter-wave film (Born & Wolf §1.6.4): R = ((p_a p_s - p_f²)/(p_a p_s + p_f²))²."""
        wl = 550.0
        R0 = ((n_a * n_s - n_f**2) / (n_a * n_s + n_f**2)) ** 2
        rt = thin_film_transfer_matrix([n_f], [wl / (4 * n_f)], [wl], [1.0], n_a, n_s)
        assert rt.R_s[0, 0] == pytest.approx(R0, abs=1e-14)
        assert rt.R[0, 0] == pytest.approx(R0, abs=1e-14)
        assert rt.T[0, 0] == pytest.approx(1 - R0, abs=1e-14)
        # oblique: quarter wave in the film's own normal direction, admittances n cos θ (s), cos θ / n (p)
        cos_a = 0.8
        sin2 = n_a**2 * (1 - cos_a**2)
        cf, cs = np.sqrt(1 - sin2 / n_f**2), np.sqrt(1 - sin2 / n_s**2)
        rt = thin_film_transfer_matrix([n_f], [wl / (4 * n_f * cf)], [wl], [cos_a], n_a, n_s)
        for pol, p in (("s", lambda n, c: n * c), ("p", lambda n, c: c / n)):
            pa, pf, ps = p(n_a, cos_a), p(n_f, cf), p(n_s, cs)
            ref = ((pa * ps - pf**2) / (pa * ps + pf**2)) ** 2
            assert getattr(rt, "R_" + pol)[0, 0] == pytest.approx(ref, abs=1e-14)

    def test_half_wave_is_absent(self):
        wl = np.array([550.0])
        n_a, n_f, n_s = 1.5, 2.3, 1.1
        cos = np.array([1.0, 0.9, 0.6])
        cf = np.sqrt(1 - n_a**2 * (1 - cos**2) / n_f**2)
        for c, cfi in zip(cos, cf):
            rt = thin_film_transfer_matrix([n_f], [wl[0] / (2 * n_f * cfi)], wl, [c], n_a, n_s)
            bare = thin_film_transfer_matrix([], [], wl, [c], n_a, n_s)
            for x, y in zip(rt, bare):
                np.testing.assert_allclose(x, y, atol=1e-13)

    def test_airy_single_film(self):
        """Airy formula (Born & Wolf §1.6.4), any film, s and p.

        r = (r12 + r23 e^{2iβ}) / (1 + r12 r23 e^{2iβ}).
        """
        rng = np.random.default_rng(22)
        wl = np.linspace(400, 700, 31)
        cos = np.linspace(0.05, 1, 40)
        for _ in range(10):
            n_a, n_e = rng.uniform(1.0, 2.0, 2)
            n_f = rng.uniform(1.0, 3.0) + 1j * rng.uniform(0, 1.0)
            d = rng.uniform(10, 500)
            a = thin_film_amplitudes([n_f], [d], wl, cos, n_a, n_e)
            f12 = fresnel_amplitudes(cos, n_a, n_f)
            f23 = fresnel_amplitudes(f12.cos_theta_t, n_f, n_e)
            ph = np.exp(2j * 2 * np.pi / wl[:, None] * d * n_f * f12.cos_theta_t)
            for pol in ("s", "p"):
                r12, r23 = getattr(f12, "r_" + pol), getattr(f23, "r_" + pol)
                ref = (r12 + r23 * ph) / (1 + r12 * r23 * ph)
                np.testing.assert_allclose(getattr(a, "r_" + pol), ref, atol=1e-12)

    def test_wavelength_thickness_scaling(self):
        """Only d/λ matters (for fixed indices): scaling both by 3 changes nothing."""
        n = [2.0 + 0.1j, 1.4, 0.5 + 3j]
        d = np.array([90.0, 140.0, 12.0])
        wl = np.linspace(400, 700, 7)
        cos = np.linspace(0, 1, 9)
        a = thin_film_transfer_matrix(n, d, wl, cos, 1.5)
        b = thin_film_transfer_matrix(n, 3 * d, 3 * wl, cos, 1.5)
        for x, y in zip(a, b):
            np.testing.assert_allclose(x, y, atol=1e-13)


class TestReciprocity:
    @pytest.mark.parametrize("absorbing", [False, True])
    def test_both_ways(self, absorbing):
        """T is the same from either side (any passive stack); so is R for a lossless stack."""
        rng = np.random.default_rng(23 + absorbing)
        wl = np.linspace(400, 700, 16)
        for _ in range(20):
            n, d = _random_stack(rng, absorbing)
            n_a, n_e = rng.uniform(1.0, 2.0, 2)
            cos_a = np.linspace(0.02, 1, 25)
            sin2 = n_a**2 * (1 - cos_a**2)
            keep = sin2 < n_e**2  # no TIR into the exit, so the wave can come back
            cos_a = cos_a[keep]
            cos_e = np.sqrt(1 - sin2[keep] / n_e**2)
            fwd = thin_film_transfer_matrix(n, d, wl, cos_a, n_a, n_e)
            bwd = thin_film_transfer_matrix(n[::-1], d[::-1], wl, cos_e, n_e, n_a)
            for pol in ("s", "p"):
                np.testing.assert_allclose(getattr(fwd, "T_" + pol), getattr(bwd, "T_" + pol), atol=1e-12)
                if not absorbing:
                    np.testing.assert_allclose(getattr(fwd, "R_" + pol), getattr(bwd, "R_" + pol), atol=1e-12)


class TestGrazingAndTIR:
    def test_grazing_limit(self):
        n = [2.3, 1.38 + 0.2j, 1.6]
        d = [100.0, 50.0, 300.0]
        wl = np.linspace(380, 780, 9)
        cos = np.array([0.0, 1e-300, 1e-12, 1e-8, 1e-4])
        with np.errstate(**RAISE):
            rt = thin_film_transfer_matrix(n, d, wl, cos, 1.5)
        for x in rt:
            assert np.all(np.isfinite(x))
        np.testing.assert_allclose(rt.R[:, 0], 1.0, atol=1e-15)  # r = -C/C: exact up to complex division
        np.testing.assert_array_equal(rt.T[:, 0], 0.0)
        assert np.all(1 - rt.R[:, 3] < 1e-5)  # 1 - R = O(cos)
        assert np.all(np.diff(1 - rt.R, axis=1) >= 0)  # R -> 1 monotonically in this range

    def test_invisible_stack_at_grazing(self):
        with np.errstate(**RAISE):
            rt = thin_film_transfer_matrix([1.5, 2.0], [200.0, 0.0], [500.0], [0.0, 1e-300, 0.5], 1.5)
        np.testing.assert_array_equal(rt.R[:, :2], 0.0)  # the removable 0/0 at cos = 0 -> its limit
        np.testing.assert_array_equal(rt.T[:, :2], 1.0)
        np.testing.assert_allclose(rt.R[:, 2], 0.0, atol=1e-15)
        np.testing.assert_allclose(rt.T[:, 2], 1.0, atol=1e-15)

    def test_tir_into_exit_and_frustrated_tir(self):
        wl = np.array([500.0])
        n_a, n_e = 1.5, 1.0
        cos = np.linspace(0, np.sqrt(1 - (1 / 1.5) ** 2) - 1e-9, 50)  # beyond the critical angle
        with np.errstate(**RAISE):
            rt = thin_film_transfer_matrix([2.0, 1.2], [100.0, 80.0], wl, cos, n_a, n_e)
        np.testing.assert_array_equal(rt.T, 0.0)
        np.testing.assert_allclose(rt.R, 1.0, atol=1e-13)
        # frustrated TIR: a low-index gap between two glasses leaks more as it gets thinner,
        # T = 1 / (1 + ((q1² + κ²)² / (4 q1² κ²)) sinh²(κ k0 d)) for s
        # (Zhu et al., Am. J. Phys. 54, 601, 1986)
        cos1 = 0.5
        q1 = 1.5 * cos1
        kappa = np.sqrt(1.5**2 * (1 - cos1**2) - 1.0)
        gaps = np.array([0.0, 20.0, 100.0, 400.0, 5000.0])
        T = [thin_film_transfer_matrix([1.0], [g], wl, [cos1], 1.5).T_s[0, 0] for g in gaps]
        coupling = (q1**2 + kappa**2) ** 2 / (4 * q1**2 * kappa**2)
        ref = 1 / (1 + coupling * np.sinh(kappa * 2 * np.pi / 500 * gaps) ** 2)
        np.testing.assert_allclose(T, ref, rtol=1e-10, atol=1e-300)
        assert np.all(np.diff(T) < 0)


    def test_film_at_its_own_critical_angle(self):
        """q = 0 in a film (film index = n_ambient sin θ): the removable sin δ / q singularity."""
        n_a, c = 1.5, 0.6  # β = 1.5 · 0.8 = 1.2
        cos = np.array([c - 1e-7, c, c + 1e-7])
        with np.errstate(**RAISE):
            rt = thin_film_transfer_matrix([1.2, 2.0], [150.0, 80.0], [500.0], cos, n_a, 1.6)
        for x in rt:
            assert np.all(np.isfinite(x))
            assert abs(x[0, 1] - 0.5 * (x[0, 0] + x[0, 2])) < 1e-9  # continuous through q = 0
        # tmm 0.2.0 itself breaks down exactly at q = 0 (cos θ_film = 6e-17 from arccos; R_s = 1.08 > 1),
        # so it is compared 1e-7 either side, where it is well conditioned.
        for j in (0, 2):
            for pol in ("s", "p"):
                ref = _tmm(pol, n_a, [1.2, 2.0], [150.0, 80.0], 1.6, cos[j], 500.0)
                assert abs(getattr(rt, "R_" + pol)[0, j] - ref["R"]) < 1e-10

    @settings(max_examples=150, deadline=None)
    @given(
        st.lists(st.tuples(st.floats(1.0, 3.0), st.sampled_from([0.0, 1e-12, 0.01, 1.0, 7.0])), max_size=4),
        st.lists(st.sampled_from([0.0, 1e-9, 1.0, 55.5, 300.0, 1e4]), min_size=4, max_size=4),
        st.floats(0, 1),
        st.floats(1.0, 2.0),
        st.floats(1.0, 2.0),
    )
    def test_property_finite_and_bounded(self, films, ds, c, n_a, n_e):
        n = np.array([a + 1j * b for a, b in films], complex)
        d = np.array(ds[: len(films)])
        with np.errstate(**RAISE):
            rt = thin_film_transfer_matrix(n, d, [500.0], [c], n_a, n_e)
        for x in rt:
            assert np.all(np.isfinite(x))
        assert 0 <= rt.R[0, 0] <= 1 + 1e-12 and 0 <= rt.T[0, 0] <= 1 + 1e-12 and rt.A[0, 0] >= -1e-12
        if np.all(n.imag == 0):
            assert abs(rt.A[0, 0]) < 1e-12


class TestOpaqueMetal:
    def test_thick_aluminium_no_overflow(self):
        wl = np.array([563.57])
        cos = np.linspace(0, 1, 50)
        for d_al in (100.0, 1000.0, 1e5):
            with np.errstate(**RAISE):
                rt = thin_film_transfer_matrix([N_MGF2, N_AL, N_MGF2], [100.0, d_al, 100.0], wl, cos, 1.5)
                fl = flake_reflectance_transmittance([N_MGF2, N_AL, N_MGF2], [100.0, d_al, 100.0], wl, cos, 1.5)
            for x in rt:
                assert np.all(np.isfinite(x))
            assert np.all(rt.T < (1e-3 if d_al == 100.0 else 1e-60))
            np.testing.assert_array_equal(fl.R, rt.R)
            np.testing.assert_array_equal(fl.T, rt.T)
            if d_al >= 1000:
                # an opaque Al core reflects like a semi-infinite Al substrate under the MgF2 coat
                semi = thin_film_transfer_matrix([N_MGF2], [100.0], wl, cos, 1.5, N_AL)
                np.testing.assert_allclose(rt.R_s, semi.R_s, atol=1e-14)
                np.testing.assert_allclose(rt.R_p, semi.R_p, atol=1e-14)
        assert np.all(rt.T == 0.0)  # 100 µm: underflows cleanly to exactly 0

    def test_thin_aluminium_against_tmm(self):
        """20 nm Al (semi-transparent, Im δ < 35 so tmm's opacity clamp is not involved)."""
        cos = np.array([1.0, 0.7, 0.3, 0.05])
        rt = thin_film_transfer_matrix([N_MGF2, N_AL, N_MGF2], [90.0, 20.0, 90.0], [563.57], cos, 1.5)
        for j, c in enumerate(cos):
            for pol in ("s", "p"):
                ref = _tmm(pol, 1.5, [N_MGF2, N_AL, N_MGF2], [90.0, 20.0, 90.0], 1.5, c, 563.57)
                assert abs(getattr(rt, "R_" + pol)[0, j] - ref["R"]) < 1e-12
                assert abs(getattr(rt, "T_" + pol)[0, j] - ref["T"]) < 1e-12


class TestAgainstTmm:
    def test_random_stacks(self):
        """R, T and complex r, t for s and p against tmm.coh_tmm on random stacks (version 0.2.0)."""
        rng = np.random.default_rng(24)
        wl = np.array([380.0, 550.0, 780.0])
        worst_abs = worst_rel = 0.0
        for _ in range(60):
            n, d = _random_stack(rng, absorbing=rng.random() < 0.7)
            # keep tmm's opacity clamp (Im δ > 35 per film) out of the comparison
            d = np.minimum(d, 35 * wl.min() / (2 * np.pi * np.maximum(np.abs(n.imag), 1e-9)) * 0.9)
            n_a = rng.uniform(1.0, 2.0)
            n_e = rng.uniform(1.0, 2.0) + 1j * rng.choice([0.0, rng.uniform(0, 3)])
            cos = rng.uniform(0.01, 1.0, 4)
            rt = thin_film_transfer_matrix(n, d, wl, cos, n_a, n_e)
            amp = thin_film_amplitudes(n, d, wl, cos, n_a, n_e)
            for i, w in enumerate(wl):
                for j, c in enumerate(cos):
                    for pol in ("s", "p"):
                        ref = _tmm(pol, n_a, n, d, n_e, c, w)
                        pairs = (
                            (getattr(rt, "R_" + pol)[i, j], ref["R"]),
                            (getattr(rt, "T_" + pol)[i, j], ref["T"]),
                            (getattr(amp, "r_" + pol)[i, j], ref["r"]),
                            (getattr(amp, "t_" + pol)[i, j], ref["t"]),
                        )
                        for x, y in pairs:
                            err = abs(x - y)
                            worst_abs = max(worst_abs, err)
                            if abs(y) > 1e-6:
                                worst_rel = max(worst_rel, err / abs(y))
        assert worst_abs < 1e-10, worst_abs
        assert worst_rel < 1e-10, worst_rel

    def test_unpolarised_matches_tmm(self):
        n = np.array([2.3 + 0.0j, 1.46, 2.3])
        d = np.array([60.0, 95.0, 60.0])
        wl = np.linspace(400, 700, 4)
        cos = np.array([1.0, 0.5])
        fl = flake_reflectance_transmittance(n, d, wl, cos, 1.5)
        for i, w in enumerate(wl):
            for j, c in enumerate(cos):
                ref = tmm.unpolarized_RT([1.5, *n, 1.5], [np.inf, *d, np.inf], np.arccos(c), w)
                assert abs(fl.R[i, j] - ref["R"]) < 1e-12 and abs(fl.T[i, j] - ref["T"]) < 1e-12


class TestShapesAndValidation:
    def test_shapes_and_broadcasting(self):
        rng = np.random.default_rng(25)
        W, A, F = 5, 7, 3
        wl = np.linspace(400, 700, W)
        cos = np.linspace(0, 1, A)
        n_wf = rng.uniform(1.2, 2.5, (W, F)) + 1j * rng.uniform(0, 0.5, (W, F))
        d = rng.uniform(20, 200, F)
        n_amb = rng.uniform(1.4, 1.6, W)
        rt = thin_film_transfer_matrix(n_wf, d, wl, cos, n_amb)
        assert all(x.shape == (W, A) for x in rt)
        for i in range(W):  # per-wavelength indices and ambient equal a one-wavelength call each
            one = thin_film_transfer_matrix(n_wf[i], d, wl[i : i + 1], cos, n_amb[i])
            for x, y in zip(rt, one):
                np.testing.assert_allclose(x[i], y[0], rtol=1e-14, atol=1e-15)
        const = thin_film_transfer_matrix(n_wf[0], d, wl, cos, 1.5)
        tiled = thin_film_transfer_matrix(np.tile(n_wf[0], (W, 1)), d, wl, cos, np.full(W, 1.5))
        for x, y in zip(const, tiled):
            np.testing.assert_array_equal(x, y)

    def test_validation(self):
        wl, cos = [500.0], [0.5]
        with pytest.raises(ValueError, match="k < 0"):
            thin_film_transfer_matrix([1.5 - 0.1j], [10.0], wl, cos, 1.5)
        with pytest.raises(ValueError, match="shape"):
            thin_film_transfer_matrix([1.5, 2.0], [10.0], wl, cos, 1.5)
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            thin_film_transfer_matrix([1.5], [10.0], wl, [-0.2], 1.5)
        with pytest.raises(ValueError, match="n_ambient"):
            thin_film_transfer_matrix([1.5], [10.0], wl, cos, 1.5 + 0.1j)
        with pytest.raises(ValueError, match="d_films_nm"):
            thin_film_transfer_matrix([1.5], [-10.0], wl, cos, 1.5)
