"""What palette.yaml's assumptions move: each organic tinter's colour when g, the pigment fraction φ_P or
the white anchor's φ_W changes alone (docs/colourants.md, "What the assumptions move").

    PYTHONPATH=$PWD python tools/palette_sensitivity.py      # ~1-2 min: 4 species x 4 panels x 7 catalogues

Prints ΔE00 (45as45, D65/10°) against the shipped tables for an opaque masstone (10 % in 200 µm over
black), a 10 µm glaze over white at 10 %, a 1:9 tint with the catalogue white and a 2 % glaze in 15 µm
over white, all under a 40 µm clear coat.
"""

import copy

import numpy as np
import yaml

from flakedb.colour.colorimetry import delta_E_2000
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.paint.catalog import load_catalog
from flakedb.paint.km_palette import PALETTE_FILE, palette_tables

SPECIES = ["phthalo-blue", "quinacridone-red", "pyrrole-red", "hansa-yellow-opaque"]
VARIANTS = [("g=0", dict(g=0.0)), ("g=0.5", dict(g=0.5)), ("phiP=0.05", dict(phip=0.05)),
            ("phiP=0.2", dict(phip=0.2)), ("phiW=0.15", dict(phiw=0.15)), ("phiW=0.25", dict(phiw=0.25))]


def doc(parts, um, primer):
    return {"flakedb": 1, "name": "t", "spectral": {"mode": "spectral", "range_nm": [380, 780], "step_nm": 10},
            "resolution": 16,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": um, "ior": 1.5,
                                     "particles": [{"species": s, "volume_fraction": v} for s, v in parts]}},
                       {"primer": {"color": primer}}]}


def variant(base, pal, g=None, phiw=None, phip=None):
    p = copy.deepcopy(pal)
    for sp in p["species"].values():
        if g is not None:
            sp["asymmetry_g"] = {"value": g}
        if phip is not None:
            sp["pigment_volume_fraction"] = {"value": phip}
    if phiw is not None:
        p["reference"]["volume_fraction"]["value"] = phiw
    cat = copy.deepcopy(base)
    for name, t in palette_tables(p, base, PALETTE_FILE.parent).items():
        e = cat["particles"][name]
        e["specific_absorption_per_um"]["value"] = list(t["sigma_a_per_um"])
        e["specific_scattering_per_um"]["value"] = list(t["sigma_s_per_um"])
        e["asymmetry_g"]["value"] = t["asymmetry_g"]
    return cat


def panels(cat, name):
    P = {"masstone": doc([(name, 0.1)], 200, "black"), "glaze10": doc([(name, 0.1)], 10, "white"),
         "tint": doc([(name, 0.01), ("titanium-white-r706", 0.18)], 200, "black"),
         "glaze2pc": doc([(name, 0.02)], 15, "white")}
    return {k: predict(recipe_from_doc(d, catalog=cat), [(45.0, 45.0)], catalog=cat).lab("10", "D65")[0]
            for k, d in P.items()}


def main():
    base, pal = load_catalog(None), yaml.safe_load(PALETTE_FILE.read_text(encoding="utf-8"))
    ref = {n: panels(base, n) for n in SPECIES}
    for label, kw in VARIANTS:
        cat = variant(base, pal, **kw)
        for n in SPECIES:
            v = panels(cat, n)
            print(f"{label:10s} {n:22s} "
                  + "  ".join(f"{k} {float(delta_E_2000(ref[n][k], v[k])):5.2f}" for k in ref[n]))
    for n in SPECIES:
        print(n, {k: np.round(v, 1).tolist() for k, v in ref[n].items()})


if __name__ == "__main__":
    main()
