"""The texture model takes a pigment's extinction from the store the solve used (no second Mie run),
and the store's cross-sections give the same indices as the direct Mie evaluation."""

import numpy as np
import pytest

import flakedb
from flakedb.solve.store_context import StoreContext
from flakedb.paint import texture_inputs
from flakedb.paint.texture_inputs import texture_report, texture_stack
from flakedb.pipelines.build import build, request_for_recipe
from flakedb.texture.instruments import PRESETS
from tests.cases import basecoat_recipe

RECIPE = basecoat_recipe("tex-store", ["{species: metallic, volume_fraction: 0.04, orientation_alpha: 0.2}",
                                      "{species: cadmium-yellow, volume_fraction: 0.02}"],
                         spectral="{mode: spectral, range_nm: [500, 540], step_nm: 20}", resolution=8,
                         primer="{albedo: 0.5}")


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    recipe = flakedb.parse_recipe(RECIPE)
    url = str(tmp_path_factory.mktemp("texstore") / "store")
    build(request_for_recipe(recipe, n=8), url, scheduler="sync")
    return recipe, StoreContext.open_for_recipe(url, recipe, 8, False)


def test_store_extinction_equals_direct_mie(stored, monkeypatch):
    recipe, ctx = stored
    direct, _ = texture_stack(recipe)
    r_direct = texture_report(recipe, [PRESETS["byk-mac-like"]])
    # with the store, the Mie code is not called at all
    monkeypatch.setattr(texture_inputs, "pigment_optics", lambda *a, **k: pytest.fail("Mie evaluated again"))
    from_store, _ = texture_stack(recipe, ctx)
    (a,), (b,) = direct.absorbers, from_store.absorbers
    # the store's size quadrature is the one of its own grid (flakedb.paint.species.pigment_n_quad), the
    # same bands here: the cross-sections agree to the quadrature's rounding
    np.testing.assert_allclose(b.sigma_per_um, a.sigma_per_um, rtol=1e-10)
    r_store = texture_report(recipe, [PRESETS["byk-mac-like"]], stored=ctx)
    for x, y in zip(r_direct["observers"][0]["directional"], r_store["observers"][0]["directional"]):
        assert x["glints_per_mm2"] == pytest.approx(y["glints_per_mm2"], rel=1e-9)
