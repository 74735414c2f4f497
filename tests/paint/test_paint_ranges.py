"""Catalogue paints that exist (issue #35 item 5): every recipe named in catalog/paint-ranges.yaml
composes to a colour inside the range real automotive paints of its kind show (each range cited there).

Guards against: a catalogue change (a species' optics, a recipe) that moves a realistic paint out of
its real-world range; a range without a source; a ranges file naming a recipe that does not exist.
Composed at the recipe's own spectral grid with n = 16 (what the other recipe tests use; the black's
L*, a*, b* move by < 0.001 from n = 16 to 32, measured).
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


def test_every_range_is_cited_and_names_a_recipe():
    for name, r in RANGES.items():
        assert (RECIPES_DIR / f"{name}.yaml").is_file(), name
        assert len(r["source"]) > 80, name
        assert set(r) <= {"kind", "aspecular_deg", "L", "a", "b", "flop_index", "source"}, name


def inside(value, bound):
    return bound.get("min", -np.inf) <= value <= bound.get("max", np.inf)


@pytest.mark.parametrize("name", sorted(RANGES))
def test_recipe_falls_in_its_range(name):
    r = RANGES[name]
    cat = load_catalog(None)
    doc = yaml.safe_load((RECIPES_DIR / f"{name}.yaml").read_text(encoding="utf-8"))
    g = [(45.0, float(a)) for a in r["aspecular_deg"]]
    lab = predict(recipe_from_doc(doc, catalog=cat), g + list(FLOP_GEOMETRIES), n=16, catalog=cat).lab("10", "D65")
    for (_, asp), (L, a, b) in zip(g, lab):
        for key, v in (("L", L), ("a", a), ("b", b)):
            if key in r:
                assert inside(v, r[key]), (name, asp, key, v, r[key])
    if "flop_index" in r:   # the colour report's X-Rite flop index from L* at its three geometries
        fi = flop_index_standard(*lab[len(g):, 0])
        assert inside(fi, r["flop_index"]), (name, fi, r["flop_index"])


def test_range_check_fails_outside():
    # the check itself: a navy black (the old magnetite iron-black's masstone b* ≈ −23) is outside
    assert not inside(-23.0, RANGES["black-solid"]["b"]) and inside(0.0, RANGES["black-solid"]["b"])
