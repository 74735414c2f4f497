"""Fits reuse each species' optics and projected kernel between evaluations that change only loadings
(flakedb.rt.common.reuse; issue 39 item 1).

Guards against: a cached solve that differs from the uncached one; a change of a non-loading field (the
flakes' orientation α, a coating film's thickness, a pigment's size) served from the cache; and a `match` whose
fit differs with the cache (the fit's evaluations, its path and its result are the uncached ones).
"""

import copy

import numpy as np
import pytest
import yaml

from flakedb.match.fit import match, predict, recipe_from_doc
from flakedb.match.targets import E2194_GEOMETRIES, read_target, format_target
from flakedb.paint.catalog import load_catalog
from flakedb.rt.common.reuse import reusing
from flakedb.solve.pipeline import solve_recipe
from tests.tolerances import ulps
from tests.cases import basecoat_recipe

DOC = yaml.safe_load(basecoat_recipe("reuse", ["{species: metallic, volume_fraction: 0.04, orientation_alpha: 0.3}",
                                               "{species: cadmium-yellow, volume_fraction: 0.02}"]))


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(None)


def _doc(**fields):
    """DOC with particle fields set: ``{(particle index, field): value}`` given as ``f0_name=value``."""
    d = copy.deepcopy(DOC)
    for k, v in fields.items():
        i, name = int(k[1]), k[3:]
        d["layers"][1]["basecoat"]["particles"][i][name] = v
    return d


def _rt(doc, catalog):
    return np.asarray(solve_recipe(recipe_from_doc(doc, catalog=catalog), None, catalog=catalog, verify=False).stack.Rt)


CHANGES = {  # a non-loading change of each kind, and the cache entry it must not be served from
    "orientation alpha": ({"f0_orientation_alpha": 0.2}, "basis coefficients"),
    "coating thickness": ({"f0_coating_thickness_nm": 150.0}, "flake optics"),
    "pigment size": ({"f1_median_diameter_um": 0.6}, "pigment optics"),
}


def test_loading_changes_are_served_from_the_cache_and_equal_the_uncached_solve(catalog):
    with reusing() as cache:
        _rt(DOC, catalog)
        kinds = {k[0] for k in cache._items}
        assert {"flake optics", "pigment optics"} <= kinds    # each species' optics per unit loading is kept
        misses = cache.misses
        for loads in ({"f0_volume_fraction": 0.05}, {"f1_volume_fraction": 0.01}):
            got = _rt(_doc(**loads), catalog)
            assert cache.misses == misses                      # nothing recomputed: only loadings moved
            ref_doc = _doc(**loads)
            with reusing():                                    # a fresh (empty) cache: computed afresh
                ref = _rt(ref_doc, catalog)
            np.testing.assert_allclose(got, ref, rtol=0, atol=ulps(64, np.abs(ref).max()))


@pytest.mark.parametrize("change", list(CHANGES), ids=list(CHANGES))
def test_a_non_loading_change_is_computed_afresh(catalog, change):
    fields, kind = CHANGES[change]
    with reusing() as cache:
        before = _rt(DOC, catalog)
        n_kind = sum(k[0] == kind for k in cache._items)
        got = _rt(_doc(**fields), catalog)
        assert sum(k[0] == kind for k in cache._items) > n_kind   # a new entry: not served from the old one
    ref = _rt(_doc(**fields), catalog)                           # no scope: the path without any cache
    np.testing.assert_allclose(got, ref, rtol=0, atol=ulps(64, np.abs(ref).max()))
    L = min(got.shape[0], before.shape[0])                           # and the change does show
    assert got.shape != before.shape or np.abs(got[:L] - before[:L]).max() > 1e-4 * np.abs(before).max()
    assert np.abs(got[:1] - before[:1]).max() > 1e-4 * np.abs(before[:1]).max()


@pytest.mark.slow
def test_match_with_the_cache_is_the_fit_without_it(catalog):
    """About 20 s: the fit twice (with its cache, then the undecorated fit without)."""
    true = _doc(f0_volume_fraction=0.03, f1_volume_fraction=0.015)
    pr = predict(recipe_from_doc(true, catalog=catalog), E2194_GEOMETRIES, catalog=catalog)
    target = read_target(format_target(pr.geometries, reflectance=pr.rf, wavelength_nm=pr.wavelength_nm))
    base = _doc(f0_volume_fraction={"fit": [0.005, 0.2], "start": 0.06}, f1_volume_fraction={"fit": [0.002, 0.1]})
    fast = match(base, target, catalog=catalog)
    slow = match.__wrapped__(base, target, catalog=catalog)     # the undecorated fit: no cache
    assert fast.n_compose == slow.n_compose and fast.iterations == slow.iterations
    np.testing.assert_allclose(fast.values, slow.values, rtol=1e-9)
    np.testing.assert_allclose(fast.lab_fit, slow.lab_fit, rtol=0, atol=1e-9)
    assert fast.values == pytest.approx([0.03, 0.015], rel=0.02)
