"""A fit of a non-loading field under ``resolution: auto`` (flakedb.match.fit, "Resolution of a fit").

Guards against: a fit whose reported colours are not those its fitted recipe composes to (the fit's n chosen
for the start values, where the auto resolution of the fitted recipe picks another, left a ΔE00 of 0.028 between
the fit's report and `compose` of its result in the α bench); a search at the coarse n that is not refined (the
result at the search's n); and the search used where it must not be (a given n, a recipe resolution, fields that leave the auto resolution
alone).
"""

import numpy as np
import pytest
import yaml

from flakedb.colour.settings import E2194_GEOMETRIES
from flakedb.match.fit import find_fit_parameters, match, predict, recipe_from_doc, search_node_count
from flakedb.match.targets import Target
from flakedb.solve.pipeline import settle_node_count

TEXT = """flakedb: 1
name: search
spectral: {mode: mono}
resolution: RES
layers:
  - clearcoat: {thickness_um: 40, ior: 1.5}
  - basecoat: {thickness_um: 10, ior: 1.5, particles: [{custom: {kind: flake, R: {c: [0, 1], value: [0.9, 0.5]},
      T: {c: [0, 1], value: [0.1, 0.5]}, orientation_alpha: ALPHA}, optical_depth: TAU}]}
  - primer: {color: gray}
"""


def _doc(alpha, tau=1.0, res="auto"):
    return yaml.safe_load(TEXT.replace("ALPHA", str(alpha)).replace("TAU", str(tau)).replace("RES", str(res)))


def test_search_node_count_only_for_auto_resolution_and_a_non_loading_field():
    doc = _doc({"fit": [0.05, 0.5], "start": 0.1})
    params = find_fit_parameters(doc)
    rec = recipe_from_doc(_doc(0.1))
    n_auto = settle_node_count.__globals__["resolve_node_count"](rec)[0]
    assert search_node_count(rec, None, params) == max(16, 2 * (n_auto // 4)) < n_auto
    assert search_node_count(rec, 32, params) is None                                  # --n given
    assert search_node_count(recipe_from_doc(_doc(0.1, res=48)), None, params) is None  # the recipe's resolution
    loading = find_fit_parameters(_doc(0.1, {"fit": [0.1, 5.0]}))
    assert search_node_count(rec, None, loading) is None                               # a loading only
    thick = _doc(0.1)
    thick["layers"][1]["basecoat"]["thickness_um"] = {"fit": [5, 20]}
    assert search_node_count(rec, None, find_fit_parameters(thick)) is None             # leaves auto n alone


def test_alpha_fit_searches_coarse_and_ends_at_the_fitted_recipes_resolution():
    """Target from α = 0.17 (auto resolution n = 64 there); fit from α = 0.1 (auto n = 96, so the search runs at
    48): the fit ends at the n the auto resolution settles on the fitted recipe, not the search's, reaches the
    target there, and its colours are exactly the fitted recipe's prediction at that n."""
    true = recipe_from_doc(_doc(0.17))
    n_true = settle_node_count(true)
    pred = predict(true, E2194_GEOMETRIES, n_true)
    target = Target(np.asarray(E2194_GEOMETRIES), lab=pred.lab("2", "D65"), observer="2", illuminant="D65")
    lines = []
    res = match(_doc({"fit": [0.05, 0.5], "start": 0.1}), target, log=lines.append)
    n_search = search_node_count(recipe_from_doc(_doc(0.1)), None, find_fit_parameters(_doc({"fit": [0.05, 0.5]})))
    assert any(line.startswith(f"search (n = {n_search}) ") for line in lines) and n_search != n_true
    assert res.n == n_true == settle_node_count(recipe_from_doc(_doc(float(res.values[0]))))
    assert res.values[0] == pytest.approx(0.17, rel=1e-3) and res.de_fit.max() <= 0.01
    again = predict(recipe_from_doc(_doc(float(res.values[0]))), E2194_GEOMETRIES, res.n)
    np.testing.assert_array_equal(again.lab("2", "D65"), res.lab_fit)
