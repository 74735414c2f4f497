"""Thin-film transfer matrix timings (see bench/run.py for the BENCHMARKS protocol).

The flake precompute evaluates R(c, λ) and T(c, λ) of every interference species on a (λ, c) grid;
this times one 3-film flake (TiO2 / Al / TiO2 in a binder of index 1.5, per-wavelength indices) over
81 wavelengths (380-780 nm, 5 nm steps) × 200 incidence cosines, s and p.  For scale, the same
physics through S. Byrnes' tmm (one call per wavelength, angle and polarisation) is timed on a
subset of the grid; compare ``best_s / evaluations`` of the two rows.
"""

import numpy as np

from flakedb.optics.thinfilm import thin_film_transfer_matrix

W, A = 81, 200
TMM_ANGLES = 4  # tmm subset: all 81 wavelengths x 4 angles x 2 polarisations


def _stack():
    wl = np.linspace(380.0, 780.0, W)
    cos = np.linspace(0.0, 1.0, A)
    # Benchmark inputs only (timing does not depend on the values): a dispersive high-index coat
    # (Cauchy form) around an absorbing metal core of roughly aluminium's index.
    n_coat = 2.4 + 0.08 * (550.0 / wl) ** 2
    n_core = np.full(W, 1.07 + 6.8j)
    n = np.stack([n_coat + 0j, n_core, n_coat + 0j], axis=1)  # (W, 3)
    d = np.array([60.0, 40.0, 60.0])
    return n, d, wl, cos


def _setup_flakedb():
    return _stack()


def _run_flakedb(arg):
    n, d, wl, cos = arg
    rt = thin_film_transfer_matrix(n, d, wl, cos, 1.5)
    return {"mean_R": float(rt.R.mean())}


def _setup_tmm():
    import tmm

    n, d, wl, cos = _stack()
    return tmm, n, d, wl, cos[:: A // TMM_ANGLES][:TMM_ANGLES]


def _run_tmm(arg):
    tmm, n, d, wl, cos = arg
    d_list = [np.inf, *d, np.inf]
    acc = 0.0
    for i, w in enumerate(wl):
        n_list = [1.5, *n[i], 1.5]
        for c in cos:
            th = np.arccos(c)
            for pol in ("s", "p"):
                acc += tmm.coh_tmm(pol, n_list, d_list, th, w)["R"]
    return {"mean_R_subset": acc / (2 * len(wl) * len(cos))}


BENCHMARKS = [
    (
        "thinfilm/transfer_matrix_3films_81wl_200angles",
        _setup_flakedb,
        _run_flakedb,
        {"films": 3, "wavelengths": W, "angles": A, "polarisations": 2, "evaluations": 2 * W * A,
         "units": "seconds per call (all wavelengths, angles, s and p)"},
    ),
    (
        "thinfilm/tmm_reference_3films_81wl_4angles",
        _setup_tmm,
        _run_tmm,
        {"films": 3, "wavelengths": W, "angles": TMM_ANGLES, "polarisations": 2,
         "evaluations": 2 * W * TMM_ANGLES, "units": "seconds per call (tmm 0.2.0, one coh_tmm per evaluation)"},
    ),
]
