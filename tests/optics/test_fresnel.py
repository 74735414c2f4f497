"""Fresnel equations (flakedb.optics.fresnel).

Guards against: a wrong sign convention for r_p or for k (n - ik), confusing eta with 1/eta or the
direction of arrival (negative cosines), the wrong branch of the transmitted cosine under total
internal reflection (growing instead of decaying waves, |r| != 1), NaN or floating-point warnings at
grazing incidence / the critical angle / eta == 1, loss of the cos² term near grazing (R = 1 for an
interface between identical media), broken broadcasting, and disagreement with independent codes
(Byrnes' tmm interface formulas, the a²/b² conductor formula of Born & Wolf §14.2 as used by pbrt).
"""

import numpy as np
import pytest
import tmm
from hypothesis import given, settings
from hypothesis import strategies as st

from flakedb.optics.fresnel import fresnel_amplitudes, fresnel_conductor, fresnel_dielectric
from tests import tolerances as tol

RAISE = dict(divide="raise", over="raise", invalid="raise")  # underflow to 0 is benign


def _sin_tan_reference(cos_i, eta):
    """Fresnel formulae in angle form (Born & Wolf §1.5.2).

    r_s = -sin(θi-θt)/sin(θi+θt), r_p = tan(θi-θt)/tan(θi+θt).
    """
    ti = np.arccos(cos_i)
    tt = np.arcsin(np.sin(ti) / eta)
    return -np.sin(ti - tt) / np.sin(ti + tt), np.tan(ti - tt) / np.tan(ti + tt)


class TestFresnelDielectric:
    def test_normal_incidence_closed_form(self):
        eta = np.array([1.0, 1.33, 1.5, 2.4, 0.5, 1 / 1.5])
        R = fresnel_dielectric(1.0, eta).R
        tol.assert_ulps(R, ((eta - 1) / (eta + 1)) ** 2, 8)  # ≤ 8 roundings each side (r, |r|², (R_s + R_p)/2): 8 ulps
        # glass in air: the textbook 4 % (Hecht, Optics, §4.6.2)
        assert fresnel_dielectric(1.0, 1.5).R == pytest.approx(0.04, abs=1e-15)
        # light from below sees 1/eta: same normal-incidence reflectance
        # 1/η rounded (u) through d ln R / d ln η = 4η/(η² − 1), and 8 ulps (η = 1: both exactly 0)
        tol.assert_ulps(fresnel_dielectric(-1.0, eta).R, R, 8 + 2 * eta / np.maximum(np.abs(eta**2 - 1), 1e-300))

    def test_angle_form_and_tmm(self):
        rng = np.random.default_rng(3)
        cos_i = rng.uniform(0.05, 1.0, 400)
        eta = rng.uniform(1.01, 3.0, 400)
        f = fresnel_dielectric(cos_i, eta)
        rs, rp = _sin_tan_reference(cos_i, eta)
        np.testing.assert_allclose(f.r_s.real, rs, atol=1e-12)
        np.testing.assert_allclose(f.r_p.real, rp, atol=1e-12)
        assert np.all(f.r_s.imag == 0) and np.all(f.r_p.imag == 0)
        th_i = np.arccos(cos_i)
        th_t = np.arcsin(np.sin(th_i) / eta)
        for pol, r in (("s", f.r_s), ("p", f.r_p)):
            ref = tmm.interface_r(pol, 1.0, eta, th_i, th_t)
            np.testing.assert_allclose(r.real, ref, atol=1e-13)

    def test_brewster(self):
        eta = np.array([1.33, 1.5, 2.0, 1 / 1.5])
        cos_b = 1 / np.sqrt(1 + eta**2)  # tan θ_B = η
        f = fresnel_dielectric(cos_b, eta)
        # r_p = N/D, N = η²c − √(η² − s²) cancels: ≤ 8 rounded ops in each term (÷ D = 2η²c: 8u), and cos_b's 3 roundings
        # through ∂r_p/∂ln c = (1 − η⁻⁴)/2 at Brewster
        tol.assert_within(np.abs(f.r_p), 0.0, tol.U * (8 + 1.5 * np.abs(1 - eta**-4.0)))
        # R_s at Brewster = ((η² - 1)/(η² + 1))² (Born & Wolf §1.5.3)
        np.testing.assert_allclose(np.abs(f.r_s) ** 2, ((eta**2 - 1) / (eta**2 + 1)) ** 2, rtol=1e-13)
        assert np.degrees(np.arctan(1.5)) == pytest.approx(56.31, abs=0.005)  # Hecht: 56.3° for glass

    def test_snell_and_sign_of_cos_t(self):
        rng = np.random.default_rng(4)
        c = rng.uniform(-1, 1, 500)
        eta = rng.uniform(0.3, 3.0, 500)
        f = fresnel_dielectric(c, eta)
        eta_rel = np.where(c < 0, 1 / eta, eta)
        ok = f.cos_theta_t != 0
        sin_t = np.sqrt(1 - f.cos_theta_t[ok] ** 2)
        np.testing.assert_allclose(eta_rel[ok] * sin_t, np.sqrt(1 - c[ok] ** 2), atol=1e-12)
        assert np.all(np.sign(f.cos_theta_t[ok]) == np.sign(c[ok]))

    def test_negative_cos_means_inverse_eta(self):
        rng = np.random.default_rng(5)
        c = rng.uniform(0, 1, 300)
        eta = rng.uniform(0.3, 3.0, 300)
        a = fresnel_dielectric(-c, eta)
        b = fresnel_dielectric(c, 1 / eta)
        np.testing.assert_allclose(a.R, b.R, rtol=1e-13, atol=1e-15)
        np.testing.assert_allclose(a.r_s, b.r_s, atol=1e-13)
        np.testing.assert_allclose(a.cos_theta_t, -b.cos_theta_t, atol=1e-14)

    def test_reciprocity(self):
        """R seen from above at θ_i equals R seen from below at the refracted angle θ_t."""
        rng = np.random.default_rng(6)
        c = rng.uniform(0.0, 1.0, 300)
        eta = rng.uniform(0.4, 3.0, 300)
        above = fresnel_dielectric(c, eta)
        ok = above.cos_theta_t > 0  # no TIR
        below = fresnel_dielectric(-above.cos_theta_t[ok], eta[ok])
        np.testing.assert_allclose(below.R, above.R[ok], rtol=1e-10, atol=1e-13)
        np.testing.assert_allclose(np.abs(below.r_s), np.abs(above.r_s[ok]), atol=1e-10)
        np.testing.assert_allclose(np.abs(below.r_p), np.abs(above.r_p[ok]), atol=1e-10)
        np.testing.assert_allclose(-below.cos_theta_t, c[ok], atol=1e-7)  # round trip (sqrt near grazing)

    def test_total_internal_reflection(self):
        eta = 1.5  # light from below (glass -> air): critical sin θ_c = 1/1.5
        sin_i = np.linspace(1 / 1.5 + 1e-9, 1.0, 200)
        c = -np.sqrt(1 - sin_i**2)
        with np.errstate(**RAISE):
            f = fresnel_dielectric(c, eta)
        assert np.all(f.R == 1.0) and np.all(f.cos_theta_t == 0.0)
        np.testing.assert_allclose(np.abs(f.r_s), 1.0, atol=1e-14)
        np.testing.assert_allclose(np.abs(f.r_p), 1.0, atol=1e-14)
        # TIR phase shifts (Born & Wolf §1.5.4): tan(δ_s/2) = sqrt(sin²θ - n²)/cos θ,
        # tan(δ_p/2) = sqrt(sin²θ - n²)/(n² cos θ), n = 1/1.5 the relative index.
        n = 1 / eta
        g = np.sqrt(sin_i**2 - n**2)
        np.testing.assert_allclose(np.abs(np.angle(f.r_s)), 2 * np.arctan2(g, -c), atol=1e-12)
        np.testing.assert_allclose(np.abs(np.angle(f.r_p)), 2 * np.arctan2(g, n**2 * -c), atol=1e-12)
        # decaying branch: Im(r) < 0 with exp(-iωt), r_s = (c - i g)/(c + i g)
        assert np.all(f.r_s.imag[:-1] < 0)

    def test_grazing_and_critical_no_warnings(self):
        eta = np.array([1.5, 1 / 1.5, 1.0, 1.0, 2.0, 1.0])
        c = np.array([0.0, 0.0, 0.0, 1e-300, 1e-9, 2.2250738585e-313])  # the last one is subnormal
        with np.errstate(**RAISE):
            f = fresnel_dielectric(c, eta)
            fb = fresnel_dielectric(-c, eta)
            crit = fresnel_dielectric(-np.sqrt(1 - (1 / 1.5) ** 2), 1.5)  # exactly at the critical angle
        for g in (f, fb, crit):
            for x in g:
                assert np.all(np.isfinite(x))
        np.testing.assert_array_equal(f.R[:2], 1.0)
        np.testing.assert_array_equal(f.R[[2, 3, 5]], 0.0)  # eta == 1: no interface, even at 1e-300
        assert f.R[4] == pytest.approx(1.0, abs=1e-8)
        assert crit.R == pytest.approx(1.0, abs=1e-6)

    def test_R_s_monotone_in_angle(self):
        c = np.linspace(1, 0, 2001)
        for eta in (1.2, 1.5, 3.0):
            Rs = np.abs(fresnel_dielectric(c, eta).r_s) ** 2
            assert np.all(np.diff(Rs) >= -1e-15)

    def test_broadcasting(self):
        c = np.linspace(-1, 1, 7)[:, None]
        eta = np.array([1.2, 1.5, 2.0])
        f = fresnel_dielectric(c, eta)
        assert all(x.shape == (7, 3) for x in f)
        for j, e in enumerate(eta):
            np.testing.assert_array_equal(f.R[:, j], fresnel_dielectric(c[:, 0], e).R)

    def test_validation(self):
        with pytest.raises(ValueError, match="eta"):
            fresnel_dielectric(0.5, -1.5)
        with pytest.raises(ValueError, match="cos_theta_i"):
            fresnel_dielectric(1.5, 1.5)

    @settings(max_examples=200, deadline=None)
    @given(st.floats(-1, 1), st.floats(0.1, 10))
    def test_property_bounds(self, c, eta):
        with np.errstate(**RAISE):
            f = fresnel_dielectric(c, eta)
        assert 0.0 <= f.R <= 1.0
        assert abs(f.r_s) <= 1 + 1e-14 and abs(f.r_p) <= 1 + 1e-14
        assert abs(f.r_p) <= abs(f.r_s) + 1e-14  # |r_p| <= |r_s| for any dielectric interface


class TestFresnelConductor:
    @staticmethod
    def _pbrt_reference(cos_i, eta, k):
        """Born & Wolf §14.2 in the a², b² form (pbrt-v3 FrConductor), an independent code path."""
        c2 = cos_i**2
        s2 = 1 - c2
        t0 = eta**2 - k**2 - s2
        a2pb2 = np.sqrt(t0**2 + 4 * eta**2 * k**2)
        a = np.sqrt(0.5 * (a2pb2 + t0))
        Rs = (a2pb2 + c2 - 2 * a * cos_i) / (a2pb2 + c2 + 2 * a * cos_i)
        t3 = c2 * a2pb2 + s2**2
        t4 = 2 * a * cos_i * s2
        Rp = Rs * (t3 - t4) / (t3 + t4)
        return Rs, Rp

    def test_normal_incidence_closed_form(self):
        n = np.array([0.2, 1.0728, 0.05, 2.0])
        k = np.array([3.0, 6.7839, 4.0, 0.0])
        R = fresnel_conductor(1.0, n + 1j * k).R
        # q = √(η² − 1 + c²) (complex ×, ±, √: ≤ 6u) amplified in r = (1 − q)/(1 + q) by |2η/(1 − η²)| ≤ 2.1 for these η,
        # the complex ÷ (6u), |r|² doubles it, ½(R_s + R_p), the closed form's 7 roundings: ≤ 24 ulps
        tol.assert_ulps(R, ((n - 1) ** 2 + k**2) / ((n + 1) ** 2 + k**2), 24)
        # Al at 563.57 nm (Rakić 1995, N = 1.0728 + 6.7839i): R ≈ 0.915 in air, the familiar ~91-92 %
        assert R[1] == pytest.approx(0.9147, abs=5e-4)

    def test_against_a2b2_form(self):
        rng = np.random.default_rng(7)
        c = rng.uniform(0, 1, 2000)
        n = rng.uniform(0.05, 4, 2000)
        k = rng.uniform(0.0, 10, 2000)
        f = fresnel_conductor(c, n + 1j * k)
        Rs, Rp = self._pbrt_reference(c, n, k)
        np.testing.assert_allclose(f.R_s, Rs, atol=1e-12)
        np.testing.assert_allclose(f.R_p, Rp, atol=1e-12)
        np.testing.assert_allclose(f.R, 0.5 * (Rs + Rp), atol=1e-12)

    def test_real_eta_equals_dielectric(self):
        c = np.linspace(0, 1, 101)
        for eta in (1.2, 1.5, 2.5):
            np.testing.assert_allclose(fresnel_conductor(c, eta).R, fresnel_dielectric(c, eta).R, atol=1e-14)

    def test_abeles_relation_and_pseudo_brewster(self):
        """Abelès (1950): r_p = r_s (r_s - cos 2θ)/(1 - r_s cos 2θ) for any isotropic interface."""
        rng = np.random.default_rng(8)
        c = rng.uniform(0, 1, 1000)
        N = rng.uniform(0.05, 5, 1000) + 1j * rng.uniform(0, 10, 1000)
        a = fresnel_amplitudes(c, 1.0, N)
        cos2 = 2 * c**2 - 1
        np.testing.assert_allclose(a.r_p, a.r_s * (a.r_s - cos2) / (1 - a.r_s * cos2), atol=1e-10)
        f = fresnel_conductor(c, N)
        assert np.all(f.R_p <= f.R_s + 1e-14)

    def test_grazing_and_sign(self):
        with np.errstate(**RAISE):
            f = fresnel_conductor(np.array([0.0, -0.5, 0.5]), 1.0728 + 6.7839j)
        assert f.R[0] == 1.0
        assert f.R[1] == f.R[2]  # only |cos| is used

    def test_gain_rejected(self):
        with pytest.raises(ValueError, match="k >= 0"):
            fresnel_conductor(0.5, 1.0 - 2.0j)


class TestFresnelAmplitudes:
    def test_against_tmm_interface_formulas(self):
        rng = np.random.default_rng(9)
        for _ in range(300):
            n1 = rng.uniform(1.0, 2.5)
            n2 = rng.uniform(0.1, 3.0) + 1j * rng.choice([0.0, rng.uniform(0, 8)])
            th1 = rng.uniform(0, np.pi / 2 - 1e-6)
            th2 = tmm.snell(n1, n2, th1)
            a = fresnel_amplitudes(np.cos(th1), n1, n2)
            for pol, r, t in (("s", a.r_s, a.t_s), ("p", a.r_p, a.t_p)):
                assert abs(r - tmm.interface_r(pol, n1, n2, th1, th2)) < 1e-12
                assert abs(t - tmm.interface_t(pol, n1, n2, th1, th2)) < 1e-12
            assert abs(a.cos_theta_t - np.cos(th2)) < 1e-9

    def test_energy_conservation_lossless(self):
        rng = np.random.default_rng(10)
        c = rng.uniform(0, 1, 1000)
        n1 = rng.uniform(1.0, 3.0, 1000)
        n2 = rng.uniform(1.0, 3.0, 1000)  # includes TIR (n2 < n1 sin θ)
        a = fresnel_amplitudes(c, n1, n2)
        q1 = n1 * c
        q2 = n2 * a.cos_theta_t
        Ts = np.abs(a.t_s) ** 2 * q2.real / q1
        Tp = np.abs(a.t_p) ** 2 * (n2 * np.conj(a.cos_theta_t)).real / (n1 * c)
        np.testing.assert_allclose(np.abs(a.r_s) ** 2 + Ts, 1.0, atol=1e-12)
        np.testing.assert_allclose(np.abs(a.r_p) ** 2 + Tp, 1.0, atol=1e-12)

    def test_stokes_relations(self):
        """Stokes: r' = -r and t t' = 1 - r² for the same pair of plane waves seen both ways."""
        rng = np.random.default_rng(11)
        c = rng.uniform(0.01, 1, 500)
        n1 = rng.uniform(1.0, 2.0, 500)
        n2 = rng.uniform(1.0, 2.0, 500) + 1j * rng.uniform(0, 2, 500)
        f = fresnel_amplitudes(c, n1, n2)
        b = fresnel_amplitudes(f.cos_theta_t, n2, n1)
        np.testing.assert_allclose(b.r_s, -f.r_s, atol=1e-12)
        np.testing.assert_allclose(b.r_p, -f.r_p, atol=1e-12)
        np.testing.assert_allclose(f.t_s * b.t_s, 1 - f.r_s**2, atol=1e-12)
        np.testing.assert_allclose(f.t_p * b.t_p, 1 - f.r_p**2, atol=1e-12)

    def test_normal_incidence_sign_convention(self):
        a = fresnel_amplitudes(1.0, 1.0, 1.5)
        assert a.r_s == pytest.approx(-0.2) and a.r_p == pytest.approx(0.2)  # r_p = -r_s (Born & Wolf)
        assert a.t_s == pytest.approx(0.8) and a.t_p == pytest.approx(0.8)

    def test_grazing_identical_media(self):
        with np.errstate(**RAISE):
            a = fresnel_amplitudes(0.0, 1.5, 1.5)
            g = fresnel_amplitudes(0.0, 1.0, 1.5)
        assert (a.r_s, a.r_p, a.t_s, a.t_p) == (0, 0, 1, 1)
        assert g.r_s == -1 and g.r_p == -1 and g.t_s == 0 and g.t_p == 0

    def test_validation(self):
        with pytest.raises(ValueError, match="Re >= 0"):
            fresnel_amplitudes(-0.5, 1.0, 1.5)
        with pytest.raises(ValueError, match="k >= 0"):
            fresnel_amplitudes(0.5, 1.0, 1.5 - 0.1j)


def test_conductor_reflectance_in_real_arithmetic_is_the_complex_one():
    """fresnel_conductor_real (the rough conductor's hot path) against fresnel_conductor (complex
    amplitudes, checked against tmm above) over metals, dielectrics (k = 0, also n < 1 with its
    critical angle) and η = 1, at every angle including normal and grazing incidence; and the closed
    form at normal incidence ((n − 1)² + k²) / ((n + 1)² + k²)."""
    from flakedb.optics.fresnel import fresnel_conductor_real

    rng = np.random.default_rng(7)
    n = np.concatenate([rng.uniform(0.02, 6.0, 3000), [1.0, 1.5, 0.5, 0.999, 0.18, 1.0]])
    k = np.concatenate([rng.uniform(0.0, 12.0, 3000), [0.0, 0.0, 0.0, 0.0, 2.3, 1e-9]])
    k[:300] = 0.0
    eta = (n + 1j * k)[None, :]
    c = np.concatenate([[0.0, 1e-12, 1e-6, 1.0], np.linspace(0.0, 1.0, 97)])[:, None]
    ref = fresnel_conductor(c, eta).R
    got = fresnel_conductor_real(c, eta)
    assert np.all(np.isfinite(got))
    assert np.abs(got - ref).max() < 1e-12
    assert np.all(got[:, n == 1.0][:, k[n == 1.0] == 0.0] == 0.0)             # no interface, no reflection
    normal = ((n - 1) ** 2 + k ** 2) / ((n + 1) ** 2 + k ** 2)
    np.testing.assert_allclose(fresnel_conductor_real(1.0, n + 1j * k), normal, rtol=1e-13, atol=1e-16)


@pytest.mark.parametrize("eta", [1.5, 1.0 / 1.5, 1.0, 1.0001, 0.9999, 3.0, 0.4])
def test_real_dielectric_in_place_path_is_the_broadcast_expressions_bit_for_bit(eta):
    """Guards fresnel_dielectric_real's in-place evaluation (a scalar index and a float64 array, the rough
    interfaces' hot path): the same values as the broadcast expressions of the general path (here the
    0-d path, element by element, which never takes it), total internal reflection and grazing included
    (against fresnel_dielectric: test_fast_fresnel_of_rough_interface_matches_reference, tests/rt)."""
    from flakedb.optics.fresnel import fresnel_dielectric_real

    rng = np.random.default_rng(11)
    c = np.concatenate([rng.random(500), np.linspace(0.0, 1.0, 257), [1e-300, 1e-17, -0.2, 1.2]])
    F = fresnel_dielectric_real(c.reshape(-1, 1), eta)[:, 0]
    one_by_one = np.array([fresnel_dielectric_real(v, eta) for v in c])
    np.testing.assert_array_equal(F, one_by_one)
