"""The solver's components refuse non-finite and out-of-range parameters at construction, naming the
field, the value and the range (flakedb/rt/common/params.py).  Before, they reached the numerics: a NaN
primer albedo gave a NaN BSDF with no error, an albedo of 1.5 a BSDF that creates energy, a negative
roughness a 72 TiB allocation, a NaN thickness "cannot convert float NaN to integer"."""

import math

import numpy as np
import pytest

from flakedb.rt.scattering.media import FlakeMedium, PhaseMedium
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.adding.stack import (
    InnerRough,
    InnerSmooth,
    Lambertian,
    Rough,
    RoughConductor,
    Slab,
    Smooth,
    SolverSettings,
    solve_stack,
)

NAN, INF = math.nan, math.inf

BAD = [
    (lambda: Smooth(NAN), "Smooth.eta"),
    (lambda: Smooth(0.0), "Smooth.eta"),
    (lambda: Rough(1.5, -0.1), "Rough.alpha"),
    (lambda: Rough(1.5, 1e-6), "Rough.alpha"),
    (lambda: Rough(1.5, NAN), "Rough.alpha"),
    (lambda: Rough(INF, 0.1), "Rough.eta"),
    (lambda: InnerSmooth(-1.2), "InnerSmooth.eta"),
    (lambda: InnerRough(1.1, 2.0), "InnerRough.alpha"),
    (lambda: Slab(NAN, PhaseMedium(1.0, 0.5)), "Slab.thickness_um"),
    (lambda: Slab(-1.0, PhaseMedium(1.0, 0.5)), "Slab.thickness_um"),
    (lambda: Lambertian(NAN), "Lambertian.albedo"),
    (lambda: Lambertian([0.5, 1.2, 0.3]), "Lambertian.albedo"),
    (lambda: RoughConductor(complex(NAN, 1.0), 0.1), "RoughConductor.N"),
    (lambda: RoughConductor(complex(1.0, -2.0), 0.1), "RoughConductor.N"),
    (lambda: RoughConductor(complex(1.0, 2.0), 0.0), "RoughConductor.alpha"),
    (lambda: PhaseMedium(NAN, 0.5), "PhaseMedium.sigma_t_per_um"),
    (lambda: PhaseMedium(1.0, 1.5), "PhaseMedium.albedo"),
    (lambda: PhaseMedium(1.0, [0.5, -0.1]), "PhaseMedium.albedo"),
    (lambda: PhaseMedium(1.0, 0.5, ("hg", 1.0)), "PhaseMedium.phase g"),
    (lambda: PhaseMedium(1.0, 0.5, ("hg", NAN)), "PhaseMedium.phase g"),
    (lambda: PhaseMedium(1.0, 0.5, ("vmf", -3.0)), "PhaseMedium.phase kappa"),
    (lambda: PhaseMedium(1.0, 0.5, ("table", [1.0, -1.0], [0.1, 0.1])), "PhaseMedium.phase cos_theta"),
    (lambda: PhaseMedium(1.0, 0.5, ("table", [-1.0, 1.0], [0.1, -0.1])), "PhaseMedium.phase values"),
    (lambda: PhaseMedium(1.0, 0.5, "sphere"), "PhaseMedium.phase"),
    (lambda: FlakeMedium(0.0, FlakeOptics.constant(0.7, 0.0), 1.0), "FlakeMedium.alpha"),
    (lambda: FlakeMedium(0.2, FlakeOptics.constant(0.7, 0.0), NAN), "FlakeMedium.a_rho_per_um"),
]


@pytest.mark.parametrize("make, field", BAD, ids=[f for _, f in BAD])
def test_a_bad_parameter_is_refused_with_its_field(make, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")) as ei:
        make()
    assert "allowed range" in str(ei.value) or "use 'isotropic'" in str(ei.value) or "ascending" in str(ei.value)


def test_the_edges_of_the_ranges_are_accepted_and_solve():
    """The limits themselves are physical inputs: a black and a white primer, a conservative medium,
    the smallest and largest roughness, a zero-thickness slab."""
    for top in (Rough(1.5, 0.01), Rough(1.5, 1.0), Smooth(1.5)):
        for a in (0.0, 1.0):
            s = solve_stack(top, [Slab(0.0, PhaseMedium(1.0, 1.0, ("hg", 0.0)))], Lambertian(a), SolverSettings(n=8))
            assert np.all(np.isfinite(s.Rt))
            alb = s.albedo()
            assert alb.max() <= 1.0 + 1e-3 and alb.min() >= -1e-12
