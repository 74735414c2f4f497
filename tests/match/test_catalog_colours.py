"""The catalogue pigments' masstone and tint colours quoted in catalog/pigment-colours.md are what
flakedb computes (so the comparison with published values there stays true when the catalogue
changes: this test fails and the table must be regenerated with ``python -m tests.match.test_catalog_colours``).
"""

import re
import sys

import numpy as np
import pytest

from flakedb.colour.tolerance import delta_E_2000
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.paint.catalog import load_catalog
from flakedb.resources import CATALOG_DIR

PIGMENTS = ("titanium-white", "cadmium-yellow", "iron-black")
GEOMETRY = [(45.0, 45.0)]          # 45°/0°, the solid-colour geometry of datasheets
TABLE = CATALOG_DIR / "pigment-colours.md"


def panel(species, vf, white_vf=0.0, primer="black"):
    parts = [{"species": species, "volume_fraction": vf}]
    if white_vf:
        parts.append({"species": "titanium-white", "volume_fraction": white_vf})
    return {"flakedb": 1, "name": "p", "spectral": {"mode": "spectral", "range_nm": [380, 780], "step_nm": 10},
            "resolution": 16,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": 30, "ior": 1.5, "particles": parts}},
                       {"primer": {"color": primer}}]}


def colours(catalog=None):
    """{pigment: {'masstone': Lab, 'masstone_white': Lab, 'tint': Lab}} at 45as45, D65/10°."""
    cat = catalog or load_catalog(None)
    out = {}
    for sp in PIGMENTS:
        lab = lambda d: predict(recipe_from_doc(d, catalog=cat), GEOMETRY, catalog=cat).lab("10", "D65")[0]
        row = {"masstone": lab(panel(sp, 0.15)), "masstone_white": lab(panel(sp, 0.15, primer="white"))}
        if sp != "titanium-white":
            row["tint"] = lab(panel(sp, 0.01, 0.10))
        out[sp] = row
    return out


def table_values():
    text = TABLE.read_text(encoding="utf-8")
    vals = {}
    for m in re.finditer(r"^\| `([\w-]+)` \| (masstone|masstone_white|tint) \| ([-\d.]+) \| ([-\d.]+) \| ([-\d.]+) \|",
                         text, re.M):
        vals[(m.group(1), m.group(2))] = np.array([float(m.group(k)) for k in (3, 4, 5)])
    return vals


def test_table_is_what_flakedb_computes():
    quoted = table_values()
    got = colours()
    assert len(quoted) == sum(len(v) for v in got.values())
    for sp, rows in got.items():
        for kind, lab in rows.items():
            assert delta_E_2000(quoted[(sp, kind)], lab) < 0.02, (sp, kind, lab)


if __name__ == "__main__":  # print the table rows
    for sp, rows in colours().items():
        for kind, lab in rows.items():
            sys.stdout.write(f"| `{sp}` | {kind} | {lab[0]:.2f} | {lab[1]:.2f} | {lab[2]:.2f} |\n")
