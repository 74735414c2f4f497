"""Solver benchmarks (issue #3): a rough-coated HG slab over a Lambertian primer, all orders,
one and 16 channels, at n = 100 and 200; and a smooth-coated three-species basecoat (issue #4)."""

import numpy as np

from flakedb.rt.scattering.media import FlakeMedium, Mixture, PhaseMedium
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.adding.stack import Lambertian, Rough, Slab, Smooth, SolverSettings, solve_stack


def _rough_hg(n, channels):
    def setup():
        g = np.full(channels, 0.7)
        alb = np.linspace(0.5, 0.95, channels)
        return n, Slab(1.0, PhaseMedium(np.ones(channels), alb, ("hg", g))), np.full(channels, 0.5)

    def run(arg):
        n, slab, prim = arg
        r = solve_stack(Rough(1.5, 0.1), [slab], Lambertian(prim), SolverSettings(n=n))
        return {"orders": int(r.info["orders"])}

    return (f"solver: rough-coated HG slab, n={n}, {channels} channel(s)", setup, run,
            {"n": n, "channels": channels, "what": "build + add all layers, all orders"})


def _three_species(n, channels=16):
    def setup():
        c = np.linspace(0, 1, 33)
        R1 = np.tile(0.2 + 0.6 * (1 - c) ** 5, (channels, 1))
        T1 = np.tile(0.5 * c, (channels, 1))
        med = Mixture([
            FlakeMedium(0.2, FlakeOptics(c, R1, T1), 1.0),
            FlakeMedium(0.3, FlakeOptics.constant(np.full(channels, 0.7), np.zeros(channels)), 0.5),
            PhaseMedium(np.full(channels, 2.0), np.linspace(0.3, 0.95, channels), ("hg", 0.5)),
        ])
        return n, med

    def run(arg):
        n, med = arg
        r = solve_stack(Smooth(1.5), [Slab(15.0, med)], Lambertian(np.full(channels, 0.5)), SolverSettings(n=n))
        return {"orders": int(r.info["orders"])}

    return (f"solver: smooth coat + 3-species basecoat, n={n}, {channels} channels", setup, run,
            {"n": n, "channels": channels, "what": "two flake species + one HG pigment, 15 um"})


BENCHMARKS = [_rough_hg(100, 1), _rough_hg(100, 16), _rough_hg(200, 1), _three_species(100), _three_species(200)]
