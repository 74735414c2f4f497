"""GGX flakes end to end through the store (issue #21 item 3): recipe → solver → store → file.

Guards against: a store that keys flake factors by α alone, so that a GGX recipe silently gets Beckmann
data; a Beckmann store (or one written before the distribution was recorded) that does not refuse a GGX
recipe; stored GGX factors that are not the solver's projection of the GGX kernel; a Beckmann-only
request whose version name changes with the new field (old stores would no longer be found); a file
that does not record its flakes' distribution.
"""

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.bsdf import open_bsdf
from flakedb.cli.main import cli
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
GGX = f", orientation_distribution: ggx, orientation_alpha: {ALPHA}"


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """A Beckmann-only store (as every store before the distribution key) and one with GGX added."""
    root = tmp_path_factory.mktemp("dist")
    beck, both = str(root / "beck"), str(root / "both")
    # Beckmann α's named explicitly: the default also builds what shipped recipes ask for (silver-bright's Student-t)
    assert build(make_request(species=[FLAKE], n=N, wavelength_nm=WL, eta_top=ETA, alphas={FLAKE: [0.2, 0.25]}),
                 beck, scheduler="sync")["status"] == "built"
    req = make_request(species=[FLAKE], n=N, wavelength_nm=WL, eta_top=ETA, alphas={FLAKE: [ALPHA]},
                       distribution_alphas={FLAKE: {"ggx": [ALPHA]}})
    assert build(req, both, scheduler="sync")["status"] == "built"
    return st.open_version(beck), st.open_version(both), req


def test_the_key_and_the_version_name():
    old = make_request(species=[FLAKE], n=N, wavelength_nm=WL, eta_top=ETA, alphas={FLAKE: [ALPHA]})
    inp = old.inputs()
    assert "distribution_alphas" not in inp  # Beckmann-only: the inputs (hence the version name) as before
    assert [t.prefix for t in st.plan_build(old).tasks] == [f"species/{FLAKE}/n{N}/a{ALPHA:g}"]
    new = make_request(species=[FLAKE], n=N, wavelength_nm=WL, eta_top=ETA, alphas={FLAKE: [ALPHA]},
                       distribution_alphas={FLAKE: {"ggx": [ALPHA]}})
    plan = st.plan_build(new)
    assert plan.version != st.plan_build(old).version
    assert [t.prefix for t in plan.tasks] == [f"species/{FLAKE}/n{N}/a{ALPHA:g}", f"species/{FLAKE}/n{N}/ggx/a{ALPHA:g}"]
    assert st.schema_problems(st.metadata(plan), "metadata") == []
    bad = dict(st.metadata(plan))
    bad["inputs"] = {**bad["inputs"], "distribution_alphas": {FLAKE: {"phong": [0.2]}}}
    assert any("phong" in p for p in st.schema_problems(bad, "metadata"))
    # a recipe asks for exactly its (distribution, α)
    req = request_for_recipe(parse_recipe(_recipe(FLAKE, extra=GGX)))
    assert req.alphas == {} and req.distribution_alphas == {FLAKE: {"ggx": [ALPHA]}}


def test_stored_ggx_factors_are_the_projection_of_the_ggx_kernel(stores):
    beck, both, req = stores
    assert beck.distributions(FLAKE) == ["beckmann"] and both.distributions(FLAKE) == ["beckmann", "ggx"]
    assert both.alphas(FLAKE, "ggx") == [ALPHA] and beck.alphas(FLAKE, "ggx") == []
    f = both.flake_factors(FLAKE, N, ALPHA, "ggx")
    assert f.distribution == "ggx" and "ggx" in f.source
    with pytest.raises(st.StoreError, match="ggx"):
        beck.flake_factors(FLAKE, N, ALPHA, "ggx")
    q = _inside_nodes()
    optics = _same_table_optics(req.species[FLAKE])
    direct, _ = project_medium(FlakeMedium(ALPHA, optics, 0.7, "ggx"), q.x, q.w, 1e-5, 2 * N, renormalize=False)
    stored, _ = project_medium(StoredFlakeMedium(f, 0.7, np.eye(len(WL))), q.x, q.w, 1e-5, 2 * N, renormalize=False)
    L = max(direct.n_orders, stored.n_orders)
    (aT, aR), (bT, bR) = direct.blocks(0, L), stored.blocks(0, L)
    scale = max(np.abs(aT).max(), np.abs(aR).max())
    assert max(np.abs(aT - bT).max(), np.abs(aR - bR).max()) <= 1e-5 * scale
    med = StoredFlakeMedium(f, 0.7, np.eye(len(WL)))
    np.testing.assert_allclose(med.sigma_t(q.x), FlakeMedium(ALPHA, optics, 0.7, "ggx").sigma_t(q.x), rtol=1e-12)
    # and the Beckmann factors at the same α are different data (the key is not α alone)
    fb = both.flake_factors(FLAKE, N, ALPHA)
    assert fb.distribution == "beckmann"
    assert np.abs(StoredFlakeMedium(fb, 0.7, np.eye(len(WL))).sigma_t(q.x) - med.sigma_t(q.x)).max() > 1e-3 * \
        np.abs(med.sigma_t(q.x)).max()


def test_a_beckmann_store_refuses_a_ggx_recipe(stores, tmp_path):
    beck, both, _ = stores
    rec = parse_recipe(_recipe(FLAKE, extra=GGX))
    probs = store_problems(beck, rec, N)
    assert len(probs) == 1 and "orientation_distribution 'ggx' is not in the store" in probs[0]
    assert "layers[1].basecoat.particles[0]" in probs[0] and "beckmann" in probs[0]
    assert store_problems(both, rec, N) == []
    # an old store's metadata (no distribution recorded) reads as Beckmann
    assert "distribution_alphas" not in beck.metadata["inputs"]
    rp = tmp_path / "g.yaml"
    rp.write_text(_recipe(FLAKE, extra=GGX, name="g"))
    r = CliRunner().invoke(cli, ["compose", str(rp), "--out", str(tmp_path / "o"), "--store", beck.url])
    assert r.exit_code != 0 and "orientation_distribution 'ggx' is not in the store" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "o").exists()


def test_ggx_compose_from_the_store_matches_direct_and_the_file_records_it(stores, tmp_path):
    beck, both, _ = stores
    rec = parse_recipe(_recipe(FLAKE, extra=GGX))
    direct = compose(rec, tmp_path / "d")
    comp = compose(rec, tmp_path / "c", store=both.url)
    fd = _f(direct)
    assert np.abs(_f(comp) - fd).max() <= 3e-3 * np.abs(fd).max()
    assert delta_E_2000(_lab(comp), _lab(direct)).max() < 0.05
    # Beckmann at the same α is a different paint (the distribution reached the solver)
    bk = compose(parse_recipe(_recipe(FLAKE, extra=f", orientation_alpha: {ALPHA}", name="b")), tmp_path / "b")
    assert delta_E_2000(_lab(bk), _lab(direct)).max() > 0.5
    path = "layers[1].basecoat.particles[0]"
    for res, dist in ((direct, "ggx"), (comp, "ggx"), (bk, "beckmann")):
        bsdf = open_bsdf(Path(res.paths["bsdf"]))
        assert bsdf.metadata["flake_distributions"] == {path: dist}
        comps = open_bsdf(Path(res.paths["h5"])).metadata["components"]
        assert [c["orientation_distribution"] for c in comps if c["path"] == path] == [dist]
