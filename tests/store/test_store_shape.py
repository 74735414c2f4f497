"""Student-t and mixture flakes end to end through the store (issue #35 item 3): recipe → plan → store → file.

Guards against: factors keyed by the family alone (a γ = 1.75 store serving a γ = 2.5 recipe, or one mixture
serving another), a plan that writes a name the recipe will not ask for (non-canonical spelling), stored
factors that are not the projection of the Student-t kernel, a compose from the store that differs from
the direct compose, a file that does not record its flakes' parametrised distribution.
"""

from pathlib import Path

import numpy as np
import pytest

from flakedb.bsdf import open_bsdf
from flakedb.colour.colorimetry import delta_E_2000
from flakedb.compose.orchestrate import compose
from flakedb.solve.store_context import store_problems
from flakedb.paint.recipe import parse_recipe
from flakedb.pipelines.build import build, make_request, request_for_recipe
from flakedb.rt.scattering.media import FlakeMedium
from flakedb.rt.adding.stack import project_medium
from flakedb.rt.scattering.stored import StoredFlakeMedium
from flakedb.store import versions as st
from tests.store.test_stored import ETA, FLAKE, N, WL, _f, _inside_nodes, _lab, _recipe, _same_table_optics

ALPHA = 0.25
STD = "student_t(1.75)"
MIX = "mix(beckmann,0.3,student_t(3.0),0.6)"
STD_FIELDS = f", orientation_distribution: student_t, orientation_shape: 1.75, orientation_alpha: {ALPHA}"
MIX_FIELDS = (f", orientation_alpha: {ALPHA}, orientation_mixture: {{weight: 0.3, orientation_alpha: 0.6, "
              "orientation_distribution: student_t, orientation_shape: 3}")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    url = str(tmp_path_factory.mktemp("shape") / "s")
    req = make_request(species=[FLAKE], n=N, wavelength_nm=WL, eta_top=ETA, alphas={},
                       distribution_alphas={FLAKE: {"Student_T(1.750)": [ALPHA], MIX: [ALPHA]}})
    assert build(req, url, scheduler="sync")["status"] == "built"
    return st.open_version(url), req


def test_keys_name_the_parameters():
    req = make_request(species=[FLAKE], n=N, wavelength_nm=WL, eta_top=ETA, alphas={},
                       distribution_alphas={FLAKE: {"Student_T( 1.750 )": [ALPHA], MIX: [ALPHA]}})
    plan = st.plan_build(req)
    assert sorted(t.prefix for t in plan.tasks) == sorted(
        [f"species/{FLAKE}/n{N}/{STD}/a{ALPHA:g}", f"species/{FLAKE}/n{N}/{MIX}/a{ALPHA:g}"])
    assert st.schema_problems(st.metadata(plan), "metadata") == []
    other = make_request(species=[FLAKE], n=N, wavelength_nm=WL, eta_top=ETA, alphas={},
                         distribution_alphas={FLAKE: {"student_t(2.5)": [ALPHA], MIX: [ALPHA]}})
    assert st.plan_build(other).version != plan.version
    # a recipe asks for exactly its canonical (distribution, α)
    assert request_for_recipe(parse_recipe(_recipe(FLAKE, extra=STD_FIELDS))).distribution_alphas == {
        FLAKE: {STD: [ALPHA]}}
    assert request_for_recipe(parse_recipe(_recipe(FLAKE, extra=MIX_FIELDS))).distribution_alphas == {
        FLAKE: {MIX: [ALPHA]}}
    with pytest.raises(ValueError, match="gamma must be in"):
        st.plan_build(make_request(species=[FLAKE], n=N, wavelength_nm=WL, alphas={},
                                   distribution_alphas={FLAKE: {"student_t(1.1)": [ALPHA]}}))


def test_stored_factors_are_the_projection_and_other_shapes_are_refused(store):
    v, req = store
    assert v.distributions(FLAKE) == sorted([MIX, STD])
    f = v.flake_factors(FLAKE, N, ALPHA, STD)
    assert f.distribution == STD
    q = _inside_nodes()
    optics = _same_table_optics(req.species[FLAKE])
    direct, _ = project_medium(FlakeMedium(ALPHA, optics, 0.7, STD), q.x, q.w, 1e-5, 2 * N, renormalize=False)
    stored, _ = project_medium(StoredFlakeMedium(f, 0.7, np.eye(len(WL))), q.x, q.w, 1e-5, 2 * N, renormalize=False)
    L = max(direct.n_orders, stored.n_orders)
    (aT, aR), (bT, bR) = direct.blocks(0, L), stored.blocks(0, L)
    assert max(np.abs(aT - bT).max(), np.abs(aR - bR).max()) <= 1e-5 * max(np.abs(aT).max(), np.abs(aR).max())
    np.testing.assert_allclose(StoredFlakeMedium(f, 0.7, np.eye(len(WL))).sigma_t(q.x),
                               FlakeMedium(ALPHA, optics, 0.7, STD).sigma_t(q.x), rtol=1e-12)
    fm = v.flake_factors(FLAKE, N, ALPHA, MIX)
    np.testing.assert_allclose(StoredFlakeMedium(fm, 0.7, np.eye(len(WL))).sigma_t(q.x),
                               FlakeMedium(ALPHA, optics, 0.7, MIX).sigma_t(q.x), rtol=1e-12)
    # the same family with another shape, and a Beckmann recipe, are not in this store
    probs = store_problems(v, parse_recipe(_recipe(FLAKE, extra=STD_FIELDS.replace("1.75", "2.5"))), N)
    assert len(probs) == 1 and "orientation_distribution 'student_t(2.5)' is not in the store" in probs[0]
    assert "student_t(1.75)" in probs[0]
    assert store_problems(v, parse_recipe(_recipe(FLAKE, extra=STD_FIELDS)), N) == []
    assert store_problems(v, parse_recipe(_recipe(FLAKE, extra=MIX_FIELDS.replace("weight: 0.3", "weight: 0.4"))), N)


@pytest.mark.parametrize("fields, dist", [(STD_FIELDS, STD), (MIX_FIELDS, MIX)], ids=["student_t", "mix"])
def test_compose_from_the_store_matches_direct_and_the_file_records_it(store, tmp_path, fields, dist):
    v, _ = store
    rec = parse_recipe(_recipe(FLAKE, extra=fields))
    direct = compose(rec, tmp_path / "d")
    comp = compose(rec, tmp_path / "c", store=v.url)
    fd = _f(direct)
    assert np.abs(_f(comp) - fd).max() <= 3e-3 * np.abs(fd).max()
    assert delta_E_2000(_lab(comp), _lab(direct)).max() < 0.05
    path = "layers[1].basecoat.particles[0]"
    for res in (direct, comp):
        assert open_bsdf(Path(res.paths["bsdf"])).metadata["flake_distributions"] == {path: dist}
