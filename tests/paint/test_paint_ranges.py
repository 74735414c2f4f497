"""Catalogue paints that exist (issue #35 item 5): every recipe named in catalog/paint-ranges.yaml
composes to a colour inside the range real automotive paints of its kind show (each range cited there).

Guards against: a catalogue change (a species' optics, a recipe) that moves a realistic paint out of
its real-world range; a range without a source; a ranges file naming a recipe that does not exist; a
bound kind the checker does not know (it would be silently ignored).
Composed at the recipe's own spectral grid with n = 16 (what the other recipe tests use; the black's
L*, a*, b* move by < 0.001 from n = 16 to 32, measured).  The bound kinds are defined in the ranges
file's header; `violations` below is their one implementation.
"""

import numpy as np
import pytest
import yaml

from flakedb.colour.settings import FLOP_GEOMETRIES
from flakedb.appearance.report import flop_index_standard
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.paint.catalog import load_catalog
from flakedb.resources import CATALOG_DIR, RECIPES_DIR

RANGES = yaml.safe_load((CATALOG_DIR / "paint-ranges.yaml").read_text(encoding="utf-8"))["ranges"]
KEYS = {"kind", "aspecular_deg", "L", "a", "b", "C", "h", "at", "flop_index", "hue_travel", "source"}
COLOUR = ("L", "a", "b", "C", "h")
#: recipes whose compose takes more than a few seconds: colour-shift's flake table averages three
#: films' thickness distributions (~20 s here; docs/flakes.md)
SLOW = {"colour-shift"}


def inside(value, bound, key="L"):
    """Whether value lies in bound {min, max}; a hue bound with min > max wraps through 0°."""
    lo, hi = bound.get("min", -np.inf), bound.get("max", np.inf)
    if key == "h" and lo > hi:
        return value >= lo or value <= hi
    return lo <= value <= hi


def lch(lab):
    """L*, a*, b*, C*ab, h_ab (degrees in [0, 360)) of (..., 3) CIELAB."""
    L, a, b = np.moveaxis(np.asarray(lab, float), -1, 0)
    return {"L": L, "a": a, "b": b, "C": np.hypot(a, b), "h": np.degrees(np.arctan2(b, a)) % 360.0}


def hue_difference_deg(h1, h2):
    """|h2 − h1| along the shorter arc, degrees."""
    d = abs(h2 - h1) % 360.0
    return min(d, 360.0 - d)


def violations(r, lab, flop):
    """The bounds of range r that a paint with CIELAB lab (one row per r["aspecular_deg"]) and flop
    index flop breaks, as (what, value, bound) tuples; empty when the paint is inside."""
    angles = [float(a) for a in r["aspecular_deg"]]
    c = lch(lab)
    out = []
    for i, asp in enumerate(angles):
        own = {float(k): v for k, v in r.get("at", {}).items()}.get(asp, {})
        for key in COLOUR:
            for bound in (r.get(key), own.get(key)):
                if bound is not None and not inside(float(c[key][i]), bound, key):
                    out.append((f"{key} at 45as{asp:g}", float(c[key][i]), bound))
    if "flop_index" in r and (flop is None or not inside(flop, r["flop_index"])):
        out.append(("flop_index", flop, r["flop_index"]))
    if "hue_travel" in r:
        t = r["hue_travel"]
        d = hue_difference_deg(c["h"][angles.index(float(t["from"]))], c["h"][angles.index(float(t["to"]))])
        if not inside(d, t):
            out.append(("hue_travel", d, t))
    return out


def test_every_range_is_cited_and_names_a_recipe():
    for name, r in RANGES.items():
        assert (RECIPES_DIR / f"{name}.yaml").is_file(), name
        assert len(r["source"]) > 80, name
        assert set(r) <= KEYS, (name, set(r) - KEYS)
        angles = [float(a) for a in r["aspecular_deg"]]
        for asp, own in r.get("at", {}).items():
            assert float(asp) in angles and set(own) <= set(COLOUR), (name, asp)
        if "hue_travel" in r:
            assert {float(r["hue_travel"]["from"]), float(r["hue_travel"]["to"])} <= set(angles), name


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n for n in sorted(RANGES)])
def test_recipe_falls_in_its_range(name):
    r = RANGES[name]
    cat = load_catalog(None)
    doc = yaml.safe_load((RECIPES_DIR / f"{name}.yaml").read_text(encoding="utf-8"))
    g = [(45.0, float(a)) for a in r["aspecular_deg"]]
    lab = predict(recipe_from_doc(doc, catalog=cat), g + list(FLOP_GEOMETRIES), n=16, catalog=cat).lab("10", "D65")
    flop = flop_index_standard(*lab[len(g):, 0])   # the colour report's X-Rite flop index
    assert violations(r, lab[:len(g)], flop) == [], name


def test_range_check_fails_outside():
    # the check itself: a navy black (the old magnetite iron-black's masstone b* ≈ −23) is outside
    assert not inside(-23.0, RANGES["black-solid"]["b"]) and inside(0.0, RANGES["black-solid"]["b"])
    # a wrapping hue sector: 350° and 20° are red, 90° (yellow) and 270° (blue) are not
    red = {"min": 315, "max": 45}
    assert inside(350.0, red, "h") and inside(20.0, red, "h")
    assert not inside(90.0, red, "h") and not inside(270.0, red, "h")
    assert hue_difference_deg(350.0, 20.0) == pytest.approx(30.0)
    # each bound kind catches a paint outside it: an orange (h 60°) "red", a grey "red" (C* 10), a
    # solid-looking metallic (flop index 2), a colour-shift that only darkens (no hue travel)
    r = {"aspecular_deg": [15, 45], "h": red, "at": {15: {"C": {"min": 20}}}, "flop_index": {"min": 5},
         "hue_travel": {"from": 15, "to": 45, "min": 30}}
    red_lab = [[50, 40, 10], [30, 40, -10]]           # h 14° and 346°: 28° apart
    assert [v[0] for v in violations(r, red_lab, 8.0)] == ["hue_travel"]
    orange = [[50, 20, 35], [30, 20, 35]]
    assert {v[0] for v in violations(r, orange, 8.0)} == {"h at 45as15", "h at 45as45", "hue_travel"}
    grey = [[50, 9, 2], [30, 40, -30]]
    assert "C at 45as15" in [v[0] for v in violations(r, grey, 8.0)]
    assert "flop_index" in [v[0] for v in violations(r, red_lab, 2.0)]
