"""The shared validation cases: one plane-parallel problem each, as solver inputs and as the
independent Monte Carlo's problem (tests/reference/test_solver_vs_montecarlo.py validates them;
tests/compose/test_validation_recipes.py checks their recipes compose to the same stacks)."""

import threading

import numpy as np
from click.testing import CliRunner

import flakedb.reference.montecarlo as mc
from flakedb.cli.main import cli
from flakedb.rt.scattering import media as rm
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.adding.stack import Lambertian, Rough, Slab, Smooth

N_PATHS = 400_000
C_GRID = np.linspace(0.0, 1.0, 33)


def angle_dependent_flake():
    """A flake whose R rises towards grazing (Schlick-like) and whose T falls: R + T ≤ 1."""
    R = 0.15 + 0.6 * (1.0 - C_GRID) ** 5
    T = 0.5 * C_GRID
    return R, T


def case(name):
    """(solver top, solver slabs, solver bottom, MC problem, n) for a named validation case."""
    if name == "isotropic-slab":  # issue #3: albedo 0.9, τ 1, index-matched, no bottom
        return None, [Slab(1.0, rm.PhaseMedium(1.0, 0.9))], None, mc.Problem(
            [mc.Slab(1.0, [mc.PhaseMedium(1.0, 0.9, "isotropic")])]), 32
    if name == "hg-over-lambertian":  # issue #3: HG g 0.7 over a Lambertian primer
        return None, [Slab(1.0, rm.PhaseMedium(2.0, 0.95, ("hg", 0.7)))], Lambertian(0.6), mc.Problem(
            [mc.Slab(1.0, [mc.PhaseMedium(2.0, 0.95, ("hg", 0.7))])], bottom=mc.Lambertian(0.6)), 32
    if name == "smooth-hg-gray":  # issue #3: smooth η 1.5 coat / HG slab / gray primer
        return Smooth(1.5), [Slab(1.0, rm.PhaseMedium(1.0, 0.9, ("hg", 0.7)))], Lambertian(0.18), mc.Problem(
            [mc.Slab(1.0, [mc.PhaseMedium(1.0, 0.9, ("hg", 0.7))])], top=mc.Smooth(1.5),
            bottom=mc.Lambertian(0.18)), 48
    if name in ("mirror-flakes-black", "mirror-flakes-white"):  # issue #4
        a = 0.0 if name.endswith("black") else 1.0
        return Smooth(1.5), [Slab(2.0, rm.FlakeMedium(0.2, FlakeOptics.constant(0.8, 0.0), 1.0))], Lambertian(a), \
            mc.Problem([mc.Slab(2.0, [mc.FlakeMedium(1.0, 0.2, 0.8, 0.0)])], top=mc.Smooth(1.5),
                       bottom=mc.Lambertian(a)), 64
    if name == "translucent-flakes-gray":  # issue #4: R 0.3, T 0.6, α 0.3 on a gray primer
        return Smooth(1.5), [Slab(3.0, rm.FlakeMedium(0.3, FlakeOptics.constant(0.3, 0.6), 1.0))], Lambertian(0.18), \
            mc.Problem([mc.Slab(3.0, [mc.FlakeMedium(1.0, 0.3, 0.3, 0.6)])], top=mc.Smooth(1.5),
                       bottom=mc.Lambertian(0.18)), 64
    if name == "angle-dependent-flakes":  # issue #4
        R, T = angle_dependent_flake()
        opt = FlakeOptics(C_GRID, R[None], T[None])
        return Smooth(1.5), [Slab(2.0, rm.FlakeMedium(0.25, opt, 1.5))], Lambertian(0.5), \
            mc.Problem([mc.Slab(2.0, [mc.FlakeMedium(1.5, 0.25, R, T, c_grid=C_GRID)])], top=mc.Smooth(1.5),
                       bottom=mc.Lambertian(0.5)), 64
    if name == "flakes-and-hg-pigment":  # issue #4: a mixture of flakes and a pigment in one layer
        med = rm.Mixture([rm.FlakeMedium(0.2, FlakeOptics.constant(0.7, 0.1), 0.8),
                          rm.PhaseMedium(1.5, 0.85, ("hg", 0.6))])
        return Smooth(1.5), [Slab(2.0, med)], Lambertian(0.3), mc.Problem(
            [mc.Slab(2.0, [mc.FlakeMedium(0.8, 0.2, 0.7, 0.1), mc.PhaseMedium(1.5, 0.85, ("hg", 0.6))])],
            top=mc.Smooth(1.5), bottom=mc.Lambertian(0.3)), 64
    if name == "smooth-vmf-spectral":  # issue #12: smooth coat / vMF slab (κ 20) with a per-band albedo / diffuse
        alb = np.linspace(0.95, 0.3, 6)  # the recipe's spectrum 0.95 (400 nm) → 0.3 (500 nm) at its 6 bands
        return Smooth(1.5), [Slab(10.0, rm.PhaseMedium(0.2, alb, ("vmf", 20.0)))], Lambertian(0.6), mc.Problem(
            [mc.Slab(10.0, [mc.PhaseMedium(0.2, alb, mc.VonMisesFisher(20.0))])], top=mc.Smooth(1.5),
            bottom=mc.Lambertian(0.6)), 48
    if name == "rough-coat-lambertian":  # issue #3: rough coat α 0.1 over a Lambertian primer
        return Rough(1.5, 0.1), [], Lambertian(0.5), mc.Problem([mc.Slab(1.0, [])], top=mc.Rough(1.5, 0.1),
                                                                  bottom=mc.Lambertian(0.5)), 128
    raise KeyError(name)


FAST = ["isotropic-slab", "hg-over-lambertian", "smooth-hg-gray", "mirror-flakes-black",
        "mirror-flakes-white", "translucent-flakes-gray", "angle-dependent-flakes", "flakes-and-hg-pigment"]


def small_mono_recipe(name):
    """A small mono recipe (smooth coat, one isotropic custom medium of optical depth 1, a 0.5 primer,
    n = 16) named ``name``: the command-line tests' input that composes in a fraction of a second."""
    return f"""\
flakedb: 1
name: {name}
spectral: {{mode: mono}}
resolution: 16
layers:
  - clearcoat: {{thickness_um: 40, ior: 1.5}}
  - basecoat:
      thickness_um: 10
      ior: 1.5
      particles:
        - custom: {{kind: medium, albedo: 0.9, phase: isotropic}}
          optical_depth: 1.0
  - primer: {{albedo: 0.5}}
"""


def basecoat_recipe(name, particles, *, spectral="{mode: spectral, range_nm: [400, 700], step_nm: 20}",
                    resolution=16, primer="{color: gray}"):
    """Recipe text of a smooth 1.5 coat (40 µm) over one 15 µm basecoat of index 1.5 holding ``particles``
    (the YAML flow mappings, one per entry) over ``primer``: the catalogue-species tests' input."""
    lines = "\n".join(f"        - {p}" for p in particles)
    return (f"flakedb: 1\nname: {name}\nspectral: {spectral}\nresolution: {resolution}\nlayers:\n"
            f"  - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}\n"
            f"  - basecoat:\n      thickness_um: 15\n      ior: 1.5\n      particles:\n{lines}\n"
            f"  - primer: {primer}\n")


def run_cli(args, bound=60):
    """``flakedb ARGS`` through click's runner in a thread, so that a hang fails the test (after ``bound`` s)
    instead of stalling the suite."""
    box = {}

    def go():
        box["r"] = CliRunner().invoke(cli, [str(a) for a in args])

    t = threading.Thread(target=go, daemon=True)
    t.start()
    t.join(bound)
    assert not t.is_alive(), f"flakedb {' '.join(map(str, args))} did not finish in {bound} s (a hang)"
    return box["r"]
