"""Every catalogue species and every recipe field family through the texture model (issue #35; docs/texture.md):
the report's numbers are finite and inside their physical bounds, and a field that changes the flakes or what lies
above them changes the texture.

Bounds that can fail (docs/texture.md §3): counts ≥ 0, an area fraction in [0, 1], the opposition (hot-spot)
factor of shared light and view paths ≥ 1 (sharing the flakes above can only raise the mean), and hiding: doubling
a flake loading more than keeps but at most doubles its glints and their mean luminance (the added flakes also hide
some below).  A species without flakes beside the metallic carrier only attenuates: the carrier's glints and their
mean luminance are no higher with it than alone (its extinction of the direct beam, σ_t > 0).

Guards against: a species whose optics the texture inputs read wrongly (NaN or negative counts, a pigment that
brightens the glints), a tinter or a pigment with a size override left out of the texture, a recipe field (films,
orientation family, diameter, opacity) that the texture silently ignores.
"""

from __future__ import annotations

import math

import pytest

from flakedb.paint.texture_inputs import texture_report
from flakedb.texture.instruments import PRESETS
from tests.every.cases import CARRIER, document, field_params, field_recipe, is_flake, particle, recipe_of, species_params, tiny

OBSERVERS = [PRESETS["byk-mac-like"]]
#: Rounding of the model's sums (a handful of float64 operations per row): the slack of the inequalities.
SLACK = 1e-9


def _rows(report):
    assert report["sparkle"], report.get("summary")
    return [r for o in report["observers"] for r in o["directional"]]


def _numbers(obj):
    if isinstance(obj, bool):
        return
    if isinstance(obj, (int, float)):
        yield float(obj)
    elif isinstance(obj, dict):
        for v in obj.values():
            yield from _numbers(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            yield from _numbers(v)


def _check_bounds(report):
    assert all(math.isfinite(v) for v in _numbers(report["observers"])), report["observers"]
    for r in _rows(report):
        for k in ("glints_per_mm2", "glints_per_mm2_above_threshold", "glints_per_spot", "sparkle_intensity",
                  "peak_luminance_factor", "flake_luminance_factor", "sparkle_contrast"):
            assert r[k] >= 0.0, (k, r[k])
        assert 0.0 <= r["sparkle_area_fraction"] <= 1.0
        assert r["hot_spot_factor"] >= 1.0 - SLACK
        assert r["flake_luminance_factor_discs"] >= r["flake_luminance_factor"] * (1.0 - SLACK)
    for o in report["observers"]:
        d = o["diffuse"]
        assert d["flake_luminance_factor"] >= 0.0 and d["luminance_sd"] >= 0.0
        if d.get("valid"):
            assert d["graininess"] >= 0.0


def _loading(species, vf):
    return recipe_of(document([particle(species, volume_fraction=vf)], name=f"every-{species}-{vf:g}"))


@pytest.mark.parametrize("species", species_params(slow_ok=True))
def test_every_species_texture_is_finite_and_bounded(species):
    rep = texture_report(tiny(species), OBSERVERS)
    _check_bounds(rep)
    names = [f["species"] for f in rep["flakes"]]
    if is_flake(species):
        assert names == [species]
        one, two = (_rows(texture_report(_loading(species, vf), OBSERVERS)) for vf in (0.01, 0.02))
        for a, b in zip(one, two):
            for k in ("glints_per_mm2", "flake_luminance_factor"):
                assert a[k] * (1.0 + 1e-6) < b[k] <= 2.0 * a[k] * (1.0 + SLACK), (k, a["light_deg"], a[k], b[k])
    else:
        assert names == [CARRIER]   # the texture sees the carrier's flakes through the species
        alone = _rows(texture_report(recipe_of(document([particle(CARRIER)], name="every-carrier")), OBSERVERS))
        for a, w in zip(alone, _rows(rep)):
            assert w["flake_luminance_factor"] < a["flake_luminance_factor"], (a["light_deg"], w, a)
            assert w["glints_per_mm2"] <= a["glints_per_mm2"] * (1.0 + SLACK)


#: The indices a field is expected to move, by more than 1 % at some light angle.
MOVED = ("glints_per_mm2", "flake_luminance_factor", "sparkle_intensity")


@pytest.mark.parametrize("species,fields", field_params())
def test_every_field_reaches_the_texture(species, fields):
    base = _rows(texture_report(tiny(species), OBSERVERS))
    rep = texture_report(field_recipe(species, fields), OBSERVERS)
    _check_bounds(rep)
    rows = _rows(rep)
    change = max(abs(r[k] / b[k] - 1.0) for r, b in zip(rows, base) for k in MOVED if b[k] > 0)
    assert change > 0.01, f"{fields}: texture moved by {change:.2g} only"
    if fields.get("opaque"):   # T = 0: the lower flakes are hidden, nothing is added
        assert all(r["flake_luminance_factor"] <= b["flake_luminance_factor"] * (1 + SLACK) for r, b in zip(rows, base))


def test_orientation_families_are_distinct_textures():
    """Beckmann, GGX, Student-t (γ = 3) and a two-population mixture at one α are four different glint statistics."""
    fams = [{"orientation_alpha": 0.2},
            {"orientation_alpha": 0.2, "orientation_distribution": "ggx"},
            {"orientation_alpha": 0.2, "orientation_distribution": "student_t", "orientation_shape": 3.0},
            {"orientation_alpha": 0.2, "orientation_mixture": {"weight": 0.3, "orientation_alpha": 0.5}}]
    glints = [tuple(r["glints_per_mm2"] for r in _rows(texture_report(field_recipe(CARRIER, f), OBSERVERS)))
              for f in fams]
    for i in range(len(glints)):
        for j in range(i):
            assert max(abs(a / b - 1.0) for a, b in zip(glints[i], glints[j])) > 0.01, (fams[i], fams[j])
