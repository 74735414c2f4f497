"""The node count is decided in one room (flakedb.solve.resolution) and every public entry point asks it.

Guards against (issue #34): the node count decided or re-derived in several rooms (compose refined auto's n while
compare and match never did; match resolved n and then solve_recipe resolved it again), and a new entry point
that picks its own n.  The check is behavioural: ``auto_resolution`` is replaced by a spy that answers an n no
rule would choose; every entry point must solve at that n, and compose, compare and match must agree on it.
A second, static check: no module outside flakedb/solve/ calls the auto rules or the refinement itself.
"""

import ast
import textwrap
from pathlib import Path

import numpy as np
import pytest

from flakedb.compose.orchestrate import compose
from flakedb.match import fit
from flakedb.match.targets import E2194_GEOMETRIES, Target
from flakedb.paint.recipe import parse_recipe
from flakedb.pipelines.build import request_for_recipe
from flakedb.solve import pipeline, resolution

PKG = Path(__file__).resolve().parents[2] / "flakedb"

RECIPE = textwrap.dedent("""\
    flakedb: 1
    name: one-home
    spectral: {mode: mono}
    resolution: auto
    layers:
      - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}
      - basecoat:
          thickness_um: 10
          ior: 1.5
          particles:
            - custom: {kind: medium, albedo: 0.8, phase: {hg: 0.3}}
              optical_depth: 1.0
      - primer: {albedo: 0.5}
    """)
SPY_N = 24  # below every auto rule's minimum (32): only the spy can have chosen it


@pytest.fixture
def spied(monkeypatch):
    calls = []

    def spy(recipe):
        calls.append(recipe.name)
        return SPY_N, "spy"

    monkeypatch.setattr(resolution, "auto_resolution", spy)
    return calls


def test_every_entry_point_solves_at_the_one_rooms_n(spied, tmp_path):
    rec = parse_recipe(RECIPE)
    res = compose(rec, tmp_path / "c")
    assert res.n == SPY_N and "spy" in res.n_reason
    pred = fit.predict(rec, E2194_GEOMETRIES)                                  # compare's prediction
    assert pred.n == SPY_N
    assert pipeline.settle_node_count(rec) == SPY_N                            # match and calibrate's n
    assert pipeline.solve_recipe(rec).n == SPY_N
    assert resolution.resolve_node_count(rec)[0] == SPY_N
    assert resolution.resolve_node_count(rec, 32)[0] == 32                    # --n wins over auto
    # match: one n for the whole fit, from the same room
    lab = pred.lab()
    target = Target(geometries=np.asarray(E2194_GEOMETRIES), lab=lab, observer="10", illuminant="D65",
                    name="self")
    doc = __import__("yaml").safe_load(RECIPE.replace("optical_depth: 1.0", "optical_depth: {fit: [0.5, 2.0]}"))
    m = fit.match(doc, target, max_nfev=2)
    assert m.n == SPY_N and m.prediction.n == SPY_N
    assert len(spied) >= 5


def test_build_plans_the_same_n_as_compose(spied):
    lines = RECIPE.splitlines()
    k = next(i for i, line in enumerate(lines) if "custom:" in line)
    lines[k:k + 2] = ["        - {species: cadmium-yellow, volume_fraction: 0.02}"]
    rec = parse_recipe("\n".join(lines).replace("{mode: mono}", "{mode: rgb}") + "\n")
    assert request_for_recipe(rec).resolutions == (SPY_N,)


def _calls(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            yield f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)


def test_no_room_outside_solve_decides_n():
    rules = {"auto_resolution", "refine_auto_n", "second_solve_n", "_colour_needs"}
    bad = []
    for p in PKG.rglob("*.py"):
        if p.parent.name == "solve":
            continue
        used = rules & set(_calls(ast.parse(p.read_text(encoding="utf-8"))))
        if used:
            bad.append(f"{p.relative_to(PKG)} calls {sorted(used)}")
    assert not bad, bad


def test_second_solve_beside_the_main_one_gives_the_same_estimate(tmp_path, monkeypatch):
    """The discretisation's second solve runs beside the main solve for small paints
    (flakedb.solve.pipeline.CONCURRENT_SECOND_BYTES) and before it for large ones: the estimate is the same, bit
    for bit, either way (the two solves share no state)."""
    rec = parse_recipe(RECIPE.replace("resolution: auto", "resolution: 40"))
    beside = pipeline.solve_reported(rec)
    monkeypatch.setattr(pipeline, "CONCURRENT_SECOND_BYTES", 0.0)
    before = pipeline.solve_reported(rec)
    assert beside.report["discretisation"] == before.report["discretisation"]
    assert beside.report["discretisation"]["n_second"] == resolution.second_solve_n(40)


def test_colour_conditions_are_chosen_in_one_place():
    """The rule "the caller's conditions, else the target's, else the defaults" lives in
    flakedb.colour.settings.for_target (issue #34: it was coded four times, and match refused an RGB paint
    against a spectral target that compare accepted).  No module reads a target's observer or illuminant to
    choose conditions itself, and every entry point that compares with a target asks for_target."""
    offenders, askers = [], set()
    for p in PKG.rglob("*.py"):
        rel = str(p.relative_to(PKG))
        tree = ast.parse(p.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and node.attr in ("observer", "illuminant")
                    and isinstance(node.value, (ast.Name, ast.Attribute))
                    and (getattr(node.value, "id", None) or getattr(node.value, "attr", None)) in ("target", "t", "tgt")
                    and rel not in ("colour/settings.py", "match/targets.py")):
                offenders.append(f"{rel}:{node.lineno}")
        if "for_target" in set(_calls(tree)):
            askers.add(rel)
    assert not offenders, offenders
    assert {"cli/compare.py", "match/batch.py", "match/fit.py", "match/calibrate.py"} <= askers, askers
