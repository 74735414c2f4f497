"""One decision, one place (issue #21): the node-count limits, the roughness range and the rough-top rule.

Guards against the limits drifting apart again (they were stated in eight places with four bounds): the
schema restates flakedb.paint.limits' numbers, and every path that resolves a node count (compose,
match, build) goes through flakedb.solve.resolution.resolve_node_count with the same precedence and refusal.
"""

import json

import pytest

from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.paint import limits
from flakedb.paint.mapping import build_paint
from flakedb.paint.components import recipe_top_alpha
from flakedb.solve.resolution import resolve_node_count
from flakedb.paint.recipe import RecipeError, parse_recipe
from flakedb.pipelines.build import recipe_top, request_for_recipe
from flakedb.resources import SCHEMAS_DIR

BASE = """flakedb: 1
name: limits-test
resolution: {res}
layers:
  - clearcoat: {{thickness_um: 40, ior: {ior}, roughness: {rough}}}
  - basecoat:
      thickness_um: 15
      ior: {ior}
      particles:
        - {{species: metallic, volume_fraction: 0.02}}
  - primer: {{color: gray}}
"""


def recipe(res="auto", ior=1.5, rough=0):
    return parse_recipe(BASE.format(res=res, ior=ior, rough=rough), "<test>")


def test_schema_states_the_same_limits():
    schema = json.loads((SCHEMAS_DIR / "recipe.schema.json").read_text())
    n = schema["properties"]["resolution"]["oneOf"][1]
    assert (n["minimum"], n["maximum"], n["multipleOf"]) == (limits.NODE_COUNT_MIN, limits.NODE_COUNT_MAX, 2)
    text = json.dumps(schema)
    assert f'"minimum": {limits.ROUGHNESS_MIN}' in text and f'"maximum": {limits.ROUGHNESS_MAX:g}' in text


def test_flake_spread_bounds_stated_once_and_restated_alike():
    """Issue #34: the flake α bounds lived in two schemas and cli/build.py; the solver's
    flakedb.rt.scattering.microflake.FLAKE_ALPHA_RANGE is their home and every restatement agrees with it."""
    from flakedb.rt.scattering.microflake import FLAKE_ALPHA_RANGE
    from flakedb.rt.common.params import ALPHA_MAX, ALPHA_MIN

    assert (limits.ROUGHNESS_MIN, limits.ROUGHNESS_MAX) == (ALPHA_MIN, ALPHA_MAX)
    lo, hi = FLAKE_ALPHA_RANGE
    found = []

    def walk(node, path):
        if isinstance(node, dict):
            for k, v in node.items():
                if k == "orientation_alpha" and isinstance(v, dict) and "minimum" in v:
                    found.append((path, v["minimum"], v["maximum"]))
                if k == "flake_alpha" and isinstance(v, dict):   # the catalogue's {value, source}
                    found.append((path, v["properties"]["value"]["minimum"], v["properties"]["value"]["maximum"]))
                walk(v, path + "/" + str(k))
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, f"{path}/{i}")

    for name in ("recipe.schema.json", "catalog.schema.json"):
        walk(json.loads((SCHEMAS_DIR / name).read_text()), name)
    assert found and all((mn, mx) == (lo, hi) for _, mn, mx in found), found
    r = CliRunner().invoke(cli, ["build", "--dry-run", "--alpha", f"metallic={hi * 1.5:g}"])
    assert r.exit_code != 0 and f"{lo:g} ≤ α ≤ {hi:g}" in r.output, r.output


@pytest.mark.parametrize("n", [6, 7, 9, 514, 1024, 64.0, True])
def test_node_count_refused_everywhere_alike(n):
    assert limits.node_count_problem(n) is not None
    with pytest.raises(ValueError, match="even, 8 ≤ n ≤ 512"):
        resolve_node_count(recipe(), n)


def test_node_count_precedence():
    assert resolve_node_count(recipe(48), 96) == (96, "--n")
    assert resolve_node_count(recipe(48)) == (48, "recipe resolution")
    n, reason = resolve_node_count(recipe())
    assert limits.NODE_COUNT_MIN <= n <= limits.NODE_COUNT_MAX and "→ n =" in reason
    # build --recipe takes the same decision
    assert request_for_recipe(recipe(48)).resolutions == (48,)
    assert request_for_recipe(recipe(48), n=96).resolutions == (96,)


@pytest.mark.parametrize("alpha", [0.001, 0.009, 1.5, float("inf")])
def test_roughness_range(alpha):
    assert limits.roughness_problem(alpha) is not None
    with pytest.raises(RecipeError, match="roughness"):
        recipe(rough=alpha)


def test_rough_top_rule_one_place():
    """α > 0 and η ≠ 1 ⇔ rough: the solver input, the store's top kind and the file's α all follow it."""
    r = recipe(rough=0.2)
    p = build_paint(r)
    assert recipe_top_alpha(r) == 0.2 and recipe_top(r) == "rough" and p.top_alpha == 0.2 and p.eta == 1.5
    s = recipe(rough=0)
    assert recipe_top_alpha(s) == 0.0 and recipe_top(s) == "smooth" and build_paint(s).top_alpha == 0.0
    assert limits.is_rough_interface(1.0, 0.3) is False
