"""Hostile recipes (issue 13): every bad input is one clear error with the field path, found before
any work (refusal times: bench/bench_hostile.py); nothing silent (NaN passing range checks, duplicate keys, a name with a
trailing newline), no MemoryError from an alias bomb, stated limits in the messages."""

import json
import math
import textwrap
from pathlib import Path

import pytest
import yaml

from flakedb.paint import checks
from flakedb.paint.checks import MAX_ALIAS_NODES, MAX_RECIPE_BYTES, MAX_RESOLUTION, value_problems
from flakedb.paint.recipe import RecipeError, load_recipe, parse_recipe, schema_path

BASE = textwrap.dedent("""\
    flakedb: 1
    name: hostile
    spectral: {mode: mono}
    resolution: 16
    layers:
      - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0, absorption_per_um: 0.01}
      - basecoat:
          thickness_um: 15
          ior: 1.5
          particles:
            - custom: {kind: medium, albedo: 0.9, phase: {hg: 0.5}}
              optical_depth: 1.0
      - primer: {albedo: 0.5}
""")


def problems(text):
    with pytest.raises(RecipeError) as ei:
        parse_recipe(text, source="h.yaml")
    return ei.value.problems


def with_line(old, new):
    assert old in BASE
    return BASE.replace(old, new)


def test_base_is_valid():
    assert parse_recipe(BASE).name == "hostile"


@pytest.mark.parametrize("old,new,path", [
    ("absorption_per_um: 0.01", "absorption_per_um: .nan", "layers[0].clearcoat.absorption_per_um"),
    ("roughness: 0,", "roughness: .nan,", "layers[0].clearcoat.roughness"),
    ("ior: 1.5, r", "ior: .nan, r", "layers[0].clearcoat.ior"),
    ("albedo: 0.9", "albedo: .NaN", "layers[1].basecoat.particles[0].custom.albedo"),
    ("hg: 0.5", "hg: -.inf", "layers[1].basecoat.particles[0].custom.phase.hg"),
    ("optical_depth: 1.0", "optical_depth: .inf", "layers[1].basecoat.particles[0].optical_depth"),
    ("primer: {albedo: 0.5}", "primer: {albedo: .nan}", "layers[2].primer.albedo"),
])
def test_nan_and_inf_refused_with_the_path(old, new, path):
    p = problems(with_line(old, new))
    assert len(p) == 1 and p[0].startswith(path + ":") and "not a finite number" in p[0]


def test_nan_wavelength_entry_refused():
    text = BASE.replace("spectral: {mode: mono}", "spectral: {mode: spectral, range_nm: [400, 700], step_nm: 20}") \
        .replace("primer: {albedo: 0.5}", "primer: {spectrum: {wavelength_nm: [300, .nan, 800], value: [0.5, 0.5, 0.5]}}")
    p = problems(text)
    assert p[0].startswith("layers[2].primer.spectrum.wavelength_nm[1]:") and "finite" in p[0]


@pytest.mark.parametrize("value", ["1e308", "1.0e+300", ".inf"])
def test_huge_values_in_unbounded_tables_refused(value):
    text = BASE.replace("phase: {hg: 0.5}", "phase: {table: {cos_theta: [-1, 1], value: [1, %s]}}" % value)
    p = problems(text)
    assert p and p[0].startswith("layers[1].basecoat.particles[0].custom.phase.table.value[1]")


def test_huge_integer_refused():
    p = problems(with_line("optical_depth: 1.0", "optical_depth: " + "9" * 400))
    assert "2^53" in p[0] and p[0].startswith("layers[1].basecoat.particles[0].optical_depth")


def test_duplicate_keys_refused():
    p = problems(BASE.replace("name: hostile\n", "name: hostile\nname: other\n"))
    assert "duplicate key 'name'" in p[0] and "line 3" in p[0]
    p = problems(with_line("ior: 1.5, r", "ior: 1.5, ior: 1.2, r"))
    assert "duplicate key 'ior'" in p[0]


def test_alias_bomb_refused_fast():
    bomb = ["a: &a [x, x, x, x, x, x, x, x, x, x]"]
    for i in range(1, 9):
        prev, cur = chr(ord("a") + i - 1), chr(ord("a") + i)
        bomb.append(f"{cur}: &{cur} [*{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}]")
    text = "\n".join(bomb) + "\n" + BASE.replace("name: hostile", "name: hostile\ndescription: *i")
    p = problems(text)
    assert len(p) == 1 and f"more than the limit of {MAX_ALIAS_NODES:,}" in p[0]
    # a bomb inside a typed field (the validator formatted the expanded value into its message)
    text = "x: &a [1,1,1,1,1,1,1,1,1,1]\n" + "\n".join(
        f"y{i}: &b{i} [" + ", ".join([f"*{'a' if i == 0 else f'b{i - 1}'}"] * 10) + "]" for i in range(8)) + "\n"
    p = problems(text + BASE.replace("thickness_um: 40", "thickness_um: *b7"))
    assert f"more than the limit of {MAX_ALIAS_NODES:,}" in p[0]


def test_small_aliases_still_work():
    assert parse_recipe(BASE.replace("optical_depth: 1.0", "optical_depth: &t 0.5").replace(
        "primer: {albedo: 0.5}", "primer: {albedo: *t}")).primer.albedo == 0.5


def test_recursive_alias_refused():
    p = problems(BASE + "extra: &r [*r]\n")
    assert "refers to the collection that contains it" in p[0]


def test_name_with_trailing_newline_or_control_character_refused():
    p = problems(BASE.replace("name: hostile", 'name: "hostile\\n"'))
    assert p[0].startswith("name:") and "U+000A" in p[0]
    p = problems(BASE.replace("name: hostile", 'name: "hos\\x07tile"'))
    assert p[0].startswith("name:") and "U+0007" in p[0]
    # a description may hold line breaks
    assert parse_recipe(BASE.replace("name: hostile", 'name: hostile\ndescription: "two\\nlines"')).description


def test_recipe_size_limit_before_parsing(tmp_path, monkeypatch):
    big = BASE + "# " + "x" * (MAX_RECIPE_BYTES + 10) + "\n"
    f = tmp_path / "big.yaml"
    f.write_text(big)

    def no_parse(*a, **k):
        raise AssertionError("the recipe was parsed before its size was checked")

    monkeypatch.setattr(checks.StrictLoader, "__init__", no_parse)
    p = problems(big)
    assert f"the limit is {MAX_RECIPE_BYTES:,} bytes" in p[0]
    monkeypatch.setattr(Path, "read_text", no_parse)
    with pytest.raises(RecipeError, match="the limit is"):
        load_recipe(f)


def test_long_description_refused_and_not_echoed():
    p = problems(BASE.replace("name: hostile", "name: hostile\ndescription: " + "d" * 200_000))
    assert p[0].startswith("description:") and "at most 10000" in p[0] and len(p[0]) < 400


def test_long_name_not_echoed_in_full():
    p = problems(BASE.replace("name: hostile", "name: " + "n" * 100_000))
    assert p[0].startswith("name:") and "at most 100" in p[0] and len(p[0]) < 400


def test_table_length_limit_states_it():
    vals = ", ".join(["0.5"] * 10_001)
    cts = ", ".join(f"{-1 + 2 * i / 10_000:.6f}" for i in range(10_001))
    p = problems(BASE.replace("phase: {hg: 0.5}", f"phase: {{table: {{cos_theta: [{cts}], value: [{vals}]}}}}"))
    assert any("10001 entries; the allowed range is at most 10000 entries" in x for x in p)
    assert all(len(x) < 400 for x in p)


def test_resolution_limit_states_it():
    p = problems(with_line("resolution: 16", "resolution: 100000"))
    assert f"≤ {MAX_RESOLUTION}" in p[0]
    schema = json.loads(Path(schema_path()).read_text())
    assert schema["properties"]["resolution"]["oneOf"][1]["maximum"] == MAX_RESOLUTION


def test_version_as_a_string_explained():
    p = problems(BASE.replace("flakedb: 1", 'flakedb: "1"'))
    assert p[0].startswith("flakedb:") and "is a str, not the number 1" in p[0]


def test_value_problems_walk():
    assert value_problems({"a": [1.0, {"b": math.nan}], "c": "ok"}) == [
        "a[1].b: value nan is not a finite number (NaN and infinity are refused everywhere) (hint: give a finite number)"]
    assert value_problems(yaml.safe_load(BASE)) == []


def test_exponent_without_a_dot_explained():
    p = problems(BASE.replace("albedo: 0.9", "albedo: 9e-1"))
    assert "has the wrong type" in p[0] and "write 1.0e-3" in p[0]


@pytest.mark.parametrize("rough", ["0.000001", "0.005"])
def test_a_coat_rougher_than_smooth_but_below_the_solvers_range_is_refused(rough):
    """A clear coat roughness in (0, 0.01) is refused with its field and range, as the basecoat's
    interface_roughness is (it reached the solver and ran out of memory: 1e-6 at n = 16)."""
    p = problems(BASE.replace("roughness: 0,", f"roughness: {rough},"))
    assert any("layers[0].clearcoat.roughness" in m and "0.01-1" in m for m in p), p


def test_a_flake_narrower_than_it_is_thick_is_refused():
    """A schema-valid 0.1 µm diameter on a catalogue flake (metallic: 0.7 µm thick: its film stack) is a pillar, not a platelet:
    the micro-flake and texture models take flat facets (the texture model's graininess stopped falling with
    loading for such flakes: hostile review, 2026-12-08).  One error naming the field, the value and the thickness."""
    text = textwrap.dedent("""\
        flakedb: 1
        name: pillar
        resolution: 16
        layers:
          - clearcoat: {thickness_um: 40, ior: 1.5, roughness: 0}
          - basecoat:
              thickness_um: 15
              ior: 1.5
              particles:
                - {species: metallic, volume_fraction: 0.05, diameter_um: DIAMETER}
          - primer: {albedo: 0.5}
        """)
    p = problems(text.replace("DIAMETER", "0.1"))
    assert len(p) == 1 and p[0].startswith("layers[1].basecoat.particles[0].diameter_um: 0.1 µm") and "platelets" in p[0]
    assert parse_recipe(text.replace("DIAMETER", "12"), source="ok.yaml").name == "pillar"
