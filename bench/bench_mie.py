"""Mie (Du 2004) timings (see bench/run.py for the BENCHMARKS protocol).

- efficiencies of 1000 random (m, x) pairs with x <= 100 (requirement: < 0.2 s), and their phase
  functions at 181 angles;
- one large sphere, x = 1e4, m = 10 + 10i (the hardest of Wiscombe's and Du's cases), efficiencies and
  amplitudes at 1001 angles;
- log-normal pigments on 41 bands (400-800 nm, binder n = 1.5, gsd 1.4): magnetite (Fe3O4, strongly
  absorbing, catalogue 'iron-black', d_med 0.32 µm) and rutile (TiO2, lossless in most of the visible,
  'titanium-white', d_med 0.25 µm), efficiencies only and with the phase function at 361 angles
  (the 0.5° grid of flakedb.paint.components.phase_cos_grid).  Default quadrature (flakedb.optics.mie.default_n_quad).
"""

import numpy as np

from flakedb.optics.mie import amplitude, default_n_quad, lognormal_pigment, mie, phase_function
from flakedb.paint.materials import refractive_index

N_BINDER = 1.5
WL = np.linspace(400.0, 800.0, 41)


def _pairs(n=1000, seed=0):
    rng = np.random.default_rng(seed)
    m = rng.uniform(1.05, 3.0, n) + 1j * rng.uniform(0.0, 1.0, n) * (rng.uniform(size=n) < 0.5)
    x = rng.uniform(0.01, 100.0, n)
    return m, x


def _run_eff(arg):
    m, x = arg
    r = mie(m, x)
    return {"checksum_qext_sum": float(np.sum(r.qext))}


def _setup_phase():
    m, x = _pairs()
    return m[:, None], x[:, None], np.cos(np.linspace(np.pi, 0.0, 181))


def _run_phase(arg):
    m, x, mu = arg
    phase_function(m, x, mu)


def _run_big(arg):
    r = mie(10 + 10j, 1e4)
    return {"qext": float(r.qext), "qsca": float(r.qsca), "g": float(r.g)}


def _run_big_amp(mu):
    amplitude(10 + 10j, 1e4, mu)


def _setup_pigment(material, d_med, with_mu):
    m = refractive_index(material, WL) / N_BINDER
    mu = np.cos(np.linspace(np.pi, 0.0, 361)) if with_mu else None
    return m, d_med, mu


def _run_pigment(arg):
    m, d_med, mu = arg
    r = lognormal_pigment(m, WL, N_BINDER, d_med, 1.4, mu=mu)
    return {"n_quad": default_n_quad(np.pi * N_BINDER / (WL.min() * 1e-3), d_med, 1.4),
            "c_sca_um2_at_550nm": float(np.interp(550.0, WL, r.c_sca_um2))}


BENCHMARKS = [
    ("mie/efficiencies_1000_pairs_x_le_100", _pairs, _run_eff,
     {"n_pairs": 1000, "x_max": 100.0, "requirement_s": 0.2}),
    ("mie/phase_function_1000_pairs_x_le_100_181_angles", _setup_phase, _run_phase,
     {"n_pairs": 1000, "x_max": 100.0, "n_angles": 181}),
    ("mie/efficiencies_x_1e4_m_10+10i", lambda: None, _run_big, {"x": 1e4, "m": "10+10i"}),
    ("mie/amplitudes_x_1e4_m_10+10i_1001_angles", lambda: np.linspace(-1.0, 1.0, 1001), _run_big_amp,
     {"x": 1e4, "m": "10+10i", "n_angles": 1001}),
    ("mie/lognormal_Fe3O4_41_bands", lambda: _setup_pigment("Fe3O4", 0.32, False), _run_pigment,
     {"n_bands": 41, "median_diameter_um": 0.32, "gsd": 1.4, "n_angles": 0}),
    ("mie/lognormal_Fe3O4_41_bands_phase_361", lambda: _setup_pigment("Fe3O4", 0.32, True), _run_pigment,
     {"n_bands": 41, "median_diameter_um": 0.32, "gsd": 1.4, "n_angles": 361}),
    ("mie/lognormal_TiO2_41_bands", lambda: _setup_pigment("TiO2-rutile-powder", 0.25, False), _run_pigment,
     {"n_bands": 41, "median_diameter_um": 0.25, "gsd": 1.4, "n_angles": 0}),
    ("mie/lognormal_TiO2_41_bands_phase_361", lambda: _setup_pigment("TiO2-rutile-powder", 0.25, True),
     _run_pigment, {"n_bands": 41, "median_diameter_um": 0.25, "gsd": 1.4, "n_angles": 361}),
]
