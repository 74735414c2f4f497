"""Custom-media benchmarks (issue #12, item 3c): a smooth-coated slab with one albedo per band (16
bands) over a diffuse primer, von Mises–Fisher phase function against Henyey–Greenstein of the same
mean cosine, at n = 64 and 128 (same stack, same settings; the ratio is what to read)."""

import numpy as np

from flakedb.rt.scattering.media import PhaseMedium, vmf_mean_cosine
from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings, solve_stack


def _slab(kind, kappa, n, channels=16):
    def setup():
        alb = np.linspace(0.3, 0.95, channels)
        phase = ("vmf", kappa) if kind == "vmf" else ("hg", float(vmf_mean_cosine(kappa)))
        return n, Slab(10.0, PhaseMedium(np.full(channels, 0.2), alb, phase)), np.full(channels, 0.6)

    def run(arg):
        n, slab, prim = arg
        r = solve_stack(Smooth(1.5), [slab], Lambertian(prim), SolverSettings(n=n))
        return {"orders": int(r.info["orders"])}

    g = float(vmf_mean_cosine(kappa))
    return (f"media: smooth coat / {kind} slab (kappa {kappa:g}, g {g:.4f}) / diffuse, n={n}, {channels} bands",
            setup, run, {"n": n, "channels": channels, "phase": kind, "kappa": kappa, "g": g,
                         "what": "project + solve, orders from the physics"})


BENCHMARKS = [_slab(kind, kappa, n) for kappa, n in ((20.0, 64), (200.0, 64), (200.0, 128)) for kind in ("vmf", "hg")]
