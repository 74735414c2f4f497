"""The hard-sphere structure factor of tools/white_flop_experiment.py (docs/validation.md, section 5: the
dependent-scattering check of the white's flop).  Against the Percus–Yevick direct correlation function
integrated numerically (Wertheim 1963: c(r) = −λ1 − 6φλ2 r/d − ½φλ1 (r/d)³ inside the sphere,
S = 1 / (1 − ρ ĉ(q))), its q → 0 compressibility limit and the dilute limit."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("white_flop_experiment", ROOT / "tools" / "white_flop_experiment.py")
wfe = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(wfe)


def s_from_direct_correlation(qd, phi, n=20001):
    """S(q) of hard spheres (d = 1) from the PY c(r), its 3-D Fourier transform by Simpson's rule."""
    from scipy.integrate import simpson
    l1 = (1 + 2 * phi) ** 2 / (1 - phi) ** 4
    l2 = -(1 + phi / 2) ** 2 / (1 - phi) ** 4
    r = np.linspace(0.0, 1.0, n)
    c = -l1 - 6 * phi * l2 * r - 0.5 * phi * l1 * r**3
    rho = 6 * phi / np.pi
    out = []
    for q in np.atleast_1d(qd):
        c_hat = 4 * np.pi * simpson(c * r**2 * np.sinc(q * r / np.pi), x=r)
        out.append(1.0 / (1.0 - rho * c_hat))
    return np.array(out)


@pytest.mark.parametrize("phi", [0.05, 0.15, 0.3])
def test_closed_form_matches_the_direct_correlation_function(phi):
    qd = np.array([0.06, 0.5, 2.0, 4.0, 7.0, 10.0, 20.0, 40.0])
    np.testing.assert_allclose(wfe.percus_yevick_S(qd, phi), s_from_direct_correlation(qd, phi), rtol=1e-6)


def test_limits():
    phi = 0.15
    s0 = (1 - phi) ** 4 / (1 + 2 * phi) ** 2          # PY compressibility: S(0)
    assert wfe.percus_yevick_S(0.0, phi) == pytest.approx(s0)
    assert wfe.percus_yevick_S(0.06, phi) == pytest.approx(s0, rel=2e-3)   # continuous at the switch
    assert wfe.percus_yevick_S(200.0, phi) == pytest.approx(1.0, abs=2e-3)
    np.testing.assert_allclose(wfe.percus_yevick_S(np.linspace(0, 30, 61), 1e-9), 1.0, atol=1e-7)
