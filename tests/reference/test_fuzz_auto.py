"""Recipes a random search of valid recipes at ``resolution: auto`` broke (issue 26: auto must never pick a
resolution that compose's own check refuses), each reduced to its smallest form and composed through the
shipped path (:func:`flakedb.compose.orchestrate.compose`, its ``check_physical`` included), with a
physical check of the result.

* A flake whose reflectance is 0 near c = 1 (a pearlescent flake's interference minimum in one RGB channel:
  the random recipe was a smooth 1.38 coat over pearl-white flakes over a 1.46 basecoat of
  ``pearlescent-tio2-100nm`` flakes, α 0.07, auto n 144) scatters nothing at near-normal incidence:
  σ_s(μ_i) = 0 there.  The kernel's renormalisation divided 0 by 0 (flakedb.rt.medium_projection.renormalization)
  and compose refused the NaN BSDF at every n.
"""

import numpy as np
import pytest

import flakedb.reference.montecarlo as mc
from flakedb.compose.orchestrate import check_physical, compose
from flakedb.paint.recipe import parse_recipe

#: R(c) of the zero-reflectance flake: 0 for c ≥ 0.7 (at α 0.1 the normal density there is exp(−1/α²·1.04) ≈ e^−104
#: of its peak at normal incidence, so σ_s(μ_i = 1) is 0 in floating point).
ZERO_R_C = [0.0, 0.6, 0.7, 1.0]
ZERO_R = [0.6, 0.3, 0.0, 0.0]
ZERO_R_RECIPE = f"""\
flakedb: 1
name: zero-r-flake
spectral: {{mode: mono}}
resolution: auto
layers:
  - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}
  - basecoat:
      thickness_um: 10
      ior: 1.5
      particles:
        - custom:
            kind: flake
            R: {{c: {ZERO_R_C}, value: {ZERO_R}}}
            T: 0.3
            orientation_alpha: 0.1
          optical_depth: 1.0
  - primer: {{albedo: 0.5}}
"""


@pytest.mark.slow
def test_flake_with_zero_reflectance_near_normal_composes_and_matches_monte_carlo(tmp_path):
    """Composes at auto (n 96) with no problem from check_physical (before: 'non-finite values'), a finite
    albedo ≤ 1, and the albedo within 3σ + 0.5 % of the Monte Carlo (its flakes drawn from D, reflecting
    with R(c) interpolated in the same table) at normal, 45° and 70° incidence."""
    res = compose(parse_recipe(ZERO_R_RECIPE), tmp_path)
    st = res.stack
    assert check_physical(st) == []
    A = st.albedo(include_delta=False)[0]
    assert np.all(np.isfinite(A)) and np.all(st.albedo() <= 1.0)
    med = res.paint.slabs[0].medium
    prob = mc.Problem((mc.Slab(10.0, (mc.FlakeMedium(float(med.a_rho_per_um), 0.1, np.array(ZERO_R), 0.3,
                                                     c_grid=np.array(ZERO_R_C)),)),),
                      top=mc.Smooth(1.5), bottom=mc.Lambertian(0.5))
    for j, frac in enumerate((1.0, 0.7, 0.35)):
        k = int(np.argmin(np.abs(st.x - frac)))
        r = mc.simulate(prob, float(st.x[k]), 100_000, seed=131 + j)
        tol = 3 * r.albedo_se[0] + 0.005 * r.diffuse_albedo[0]
        assert abs(A[k] - r.diffuse_albedo[0]) <= tol, (res.n, float(st.x[k]), A[k], r.diffuse_albedo[0], tol)
