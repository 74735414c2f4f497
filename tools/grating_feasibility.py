"""Issue 35, docs/validation.md §4a: fit a single-scattering population of sinusoidal-grating (holographic,
SpectraFlair-type) aluminium flakes (flakedb.match.grating) to a measured multi-angle target and print the
per-geometry table.

    python tools/grating_feasibility.py tools/validation/targets/irid_flake_paint2_rgb.csv [--distribution beckmann]

Free: period Λ [nm], groove amplitude a [nm], orientation α, coverage c (the flakes' projected area per coat area,
times R_Al in the binder), a grey Lambertian floor k_d; orders 0-3 with the scalar-theory efficiencies.  Least
squares on the 11 ΔE00 from a few starts, then Nelder-Mead on the worst ΔE00 (minimax) from the best."""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import least_squares, minimize

from flakedb.colour.colorimetry import XYZ_to_Lab, delta_E_2000, reflectance_to_XYZ
from flakedb.match.grating import grating_paint_reflectance
from flakedb.match.targets import read_target
from flakedb.paint.materials import refractive_index

ORDERS = (0, 1, 2, 3)
NAMES = ("period_nm", "amplitude_nm", "alpha", "coverage", "k_d")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("target")
    ap.add_argument("--distribution", default="beckmann")
    ap.add_argument("--step-nm", type=float, default=20.0)
    ap.add_argument("--n-phi", type=int, default=96)
    ap.add_argument("--start", default="700,44,0.094,0.245,5e-4;900,80,0.2,0.3,0.01;550,40,0.08,0.2,0.01",
                    help="starts, ';'-separated, each " + ",".join(NAMES))
    ap.add_argument("--no-fit", action="store_true", help="evaluate the first start only")
    ap.add_argument("--polish", action="store_true", help="Nelder-Mead on the worst ΔE00 from the first start only "
                    "(no least-squares stage): a restart of a minimax result")
    ap.add_argument("--specular", action="store_true",
                    help="add a plain (specular) aluminium flake population: its coverage and α, two more free")
    ap.add_argument("--second-grating", action="store_true",
                    help="add a second grating population (its period, amplitude and coverage; α shared)")
    a = ap.parse_args(argv)
    t = read_target(a.target)
    geo, lab = np.asarray(t.geometries)[:, :2], np.asarray(t.lab)
    wl = np.arange(400.0, 700.0 + 1e-9, a.step_nm)
    N = refractive_index("Al", wl)
    r_al = np.abs((N - 1.5) / (N + 1.5)) ** 2                                # normal incidence, in the binder

    names = NAMES + (("spec_coverage", "spec_alpha") if a.specular else ()) + (
        ("period2_nm", "amplitude2_nm", "coverage2") if a.second_grating else ())

    def model(p):
        d, amp, alpha, c, kd = np.exp(p[:5])
        R = grating_paint_reflectance(geo, wl, d, alpha, np.tile(c * r_al, (len(ORDERS), 1)), kd,
                                      a.distribution, ORDERS, n_phi=a.n_phi, depth_nm=amp)
        if a.specular:
            cs, alpha_s = np.exp(p[5:7])
            R = R + grating_paint_reflectance(geo, wl, 1e3, alpha_s, (cs * r_al)[None, :], 0.0, a.distribution, (0,))
        if a.second_grating:
            d2, amp2, c2 = np.exp(p[-3:])
            R = R + grating_paint_reflectance(geo, wl, d2, alpha, np.tile(c2 * r_al, (len(ORDERS), 1)), 0.0,
                                              a.distribution, ORDERS, n_phi=a.n_phi, depth_nm=amp2)
        return XYZ_to_Lab(reflectance_to_XYZ(R, wl))

    de = lambda p: delta_E_2000(lab, model(p))
    starts = [np.log([float(x) for x in s.split(",")]) for s in a.start.split(";")]
    if a.specular:
        starts = [np.r_[s, np.log([0.05, 0.1])] if s.size == 5 else s for s in starts]
    if a.second_grating:
        starts = [s if s.size == len(names) else np.r_[s, np.log([1000.0, 60.0, 0.05])] for s in starts]
    if a.no_fit:
        x = starts[0]
    else:
        fits = [starts[0]] if a.polish else [least_squares(de, p0, method="trf", max_nfev=60).x for p0 in starts]
        x0 = min(fits, key=lambda p: de(p).max())
        x = minimize(lambda p: de(p).max(), x0, method="Nelder-Mead",
                     options=dict(maxiter=1500, xatol=1e-5, fatol=1e-4)).x
    d, m = de(x), model(x)
    print(f"worst dE00 {d.max():.2f}; " + ", ".join(f"{n} {v:.4g}" for n, v in zip(names, np.exp(x))))
    print("| geometry | target L*, a*, b* | fitted L*, a*, b* | dE00 |\n|---|---|---|---|")
    for g, tl, ml, e in zip(geo, lab, m, d):
        print(f"| {g[0]:g}as{g[1]:g} | {tl[0]:.1f}, {tl[1]:.1f}, {tl[2]:.1f} | {ml[0]:.1f}, {ml[1]:.1f}, "
              f"{ml[2]:.1f} | {e:.2f} |")


if __name__ == "__main__":
    main()
