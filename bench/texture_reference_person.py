"""Glint counts of one layer, model against the discrete-flake reference, on a patch of any size and seed (issue 36;
docs/texture.md §8, *Person-preset counts*; results in bench/texture_reference_person.jsonl).

    PYTHONPATH=$PWD python bench/texture_reference_person.py VF SIDE_UM PRESET SEED [SPECIES ALPHA] [--tiny] [--grey]

The layer is tests.texture.cases' recipe (20 µm flakes, 15 µm basecoat), light 15°, view 0°, the sky aside.
``--tiny``: the preset's source and aperture shrunk to 0.005° and 1e-5 rad (the beam is the flake's Airy pattern);
``--grey``: one channel, R = 0.9 at every flake cosine, 555 nm (monochromatic), where the textbook count without
hiding, N_A ∫ n(D) D(h') cos θ_h π (0.514 λ'/D)² dD / (4c), is printed beside the two.  One JSON line to stdout."""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np

from flakedb.reference.flake_sim import simulate
from flakedb.texture import model as tm
from flakedb.texture.instruments import PRESETS
from tests.texture.cases import sim_inputs, stack_of


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("vf", type=float)
    ap.add_argument("side_um", type=float)
    ap.add_argument("preset", choices=sorted(PRESETS))
    ap.add_argument("seed", type=int)
    ap.add_argument("species", nargs="?", default="metallic")
    ap.add_argument("alpha", nargs="?", type=float, default=0.2)
    ap.add_argument("--tiny", action="store_true")
    ap.add_argument("--grey", action="store_true")
    a = ap.parse_args()
    st = stack_of(species=a.species, vf=a.vf, alpha=a.alpha, D=20.0)
    if a.grey:
        f0 = st.flakes[0]
        f = dataclasses.replace(f0, R=np.full((1, np.size(f0.c)), 0.9), T=np.zeros((1, np.size(f0.c))))
        st = tm.TextureStack(st.eta, np.array([1.0]), (f,), ())
    o = dataclasses.replace(PRESETS[a.preset], light_deg=(15.0,))
    if a.tiny:
        o = dataclasses.replace(o, source_half_angle_deg=0.005, aperture_half_angle_rad=1e-5)
    m = tm.sparkle_indices(st, o, 15.0)
    out = dict(species=a.species, vf=a.vf, alpha=a.alpha, preset=a.preset, tiny=a.tiny, grey=a.grey, seed=a.seed,
               L=a.side_um, model=m["glints_per_mm2"])
    if a.grey:
        f = st.flakes[0]
        g = tm.directional_geometry(st.eta, 15.0, 0.0, o.source_half_angle_deg, o.aperture_half_angle_rad)
        lam = tm.DIFFRACTION_WAVELENGTH_NM * 1e-3 / st.eta
        p_h = 2.0 * float(tm.flake_distribution(f.distribution).ndf(np.array([g.cos_h]), f.alpha)[0])
        e_d2 = f.diameter_median_um ** -2 * np.exp(2.0 * np.log(f.diameter_gsd) ** 2)
        out["analytic_no_hiding"] = 1e6 * f.areal_density_per_um2 * p_h * np.pi * (0.514 * lam) ** 2 / (4 * g.c) * e_d2
    sp, ab = sim_inputs(st)
    t = time.time()
    wl = 555.0 if a.grey else st.wavelength_nm
    r = simulate(st.eta, np.asarray(st.y_weights), sp, ab, o.spot_um, o.aperture_half_angle_rad,
                 o.source_half_angle_deg, 0.0, (15.0,), L_um=a.side_um, seed=a.seed, wavelength_nm=wl, diffuse=False)
    d = r["directional"][0]
    out.update(ref=d["glints_per_mm2"], ref_sigma=d["sigma_glints_per_mm2"], glints=d["glints"],
               seconds=round(time.time() - t))
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
