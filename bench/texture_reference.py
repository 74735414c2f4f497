"""The texture model against the discrete-flake reference without shortcuts (issue 36 item 5;
docs/texture.md §8, "Against the reference without shortcuts").

    PYTHONPATH=$PWD python bench/texture_reference.py sim CASE... --out bench/texture_reference.jsonl
    PYTHONPATH=$PWD python bench/texture_reference.py table bench/texture_reference.jsonl
    PYTHONPATH=$PWD python bench/texture_reference.py sky CASE... --seed 37 --side 2600 --out bench/texture_reference_sky37.jsonl

``sim`` runs :func:`flakedb.reference.flake_sim.simulate` (area hiding, per-ray sky, true diffraction) for each
named case and appends one JSON line per case; ``table`` evaluates the model on the same inputs and prints the
markdown table of docs/texture.md with the 3σ + 10 % verdict per index.  The simulation calls no model code
(tests/texture/cases.py hands it the recipe's arrays)."""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from flakedb.texture.instruments import PRESETS

#: name: (recipe arguments of tests.texture.cases.recipe, observer preset, lights, patch side µm, sky ray spacing µm)
CASES = {
    "byk/met-2%-20um-a0.2": (dict(species="metallic", vf=0.02, alpha=0.2, D=20.0), "byk-mac-like", (15.0, 45.0), 13000.0, 1.25),
    "byk/met-8%-20um-a0.2": (dict(species="metallic", vf=0.08, alpha=0.2, D=20.0), "byk-mac-like", (15.0, 45.0), 12000.0, 1.25),
    "byk/met-16%-20um-a0.2": (dict(species="metallic", vf=0.16, alpha=0.2, D=20.0), "byk-mac-like", (15.0, 45.0), 12000.0, 1.25),
    "byk/met-4%-10um-a0.2": (dict(species="metallic", vf=0.04, alpha=0.2, D=10.0), "byk-mac-like", (15.0, 45.0), 4000.0, 1.25),
    "byk/met-4%-40um-a0.2": (dict(species="metallic", vf=0.04, alpha=0.2, D=40.0), "byk-mac-like", (15.0, 45.0), 20000.0, 1.25),
    "byk/met-4%-20um-a0.05": (dict(species="metallic", vf=0.04, alpha=0.05, D=20.0), "byk-mac-like", (15.0,), 12000.0, 1.25),
    "byk/met-4%-20um-a0.5": (dict(species="metallic", vf=0.04, alpha=0.5, D=20.0), "byk-mac-like", (15.0, 45.0), 20000.0, 1.25),
    "byk/pearl-4%-20um-a0.15": (dict(species="pearlescent", vf=0.04, alpha=0.15, D=20.0), "byk-mac-like", (15.0, 45.0), 8000.0, 1.25),
    "byk/met-4%-20um-black": (dict(species="metallic", vf=0.04, alpha=0.2, D=20.0, pigment="iron-black", pv=0.003),
                              "byk-mac-like", (15.0, 45.0), 15000.0, 1.25),
    "p1m/met-2%-20um-a0.2": (dict(species="metallic", vf=0.02, alpha=0.2, D=20.0), "person-1m", (15.0,), 16000.0, 4.0),
    "p1m/met-8%-20um-a0.2": (dict(species="metallic", vf=0.08, alpha=0.2, D=20.0), "person-1m", (15.0,), 15000.0, 4.0),
    "p1m/pearl-4%-20um-a0.15": (dict(species="pearlescent", vf=0.04, alpha=0.15, D=20.0), "person-1m", (15.0,), 10000.0, 4.0),
    "p1m/met-4%-20um-black": (dict(species="metallic", vf=0.04, alpha=0.2, D=20.0, pigment="iron-black", pv=0.003),
                              "person-1m", (15.0,), 18000.0, 4.0),
}


#: Pixels per side of the window the sky is rendered in (per ray: the cost), per observer.
SKY_PIXELS = {"byk-mac-like": 160, "person-1m": 24}


def _observer(name, lights):
    import dataclasses
    return dataclasses.replace(PRESETS[name], light_deg=tuple(lights))


def run_sky(names, out, seed=37, side_um=2600.0):
    """The sky alone (no light: no glints) of each named case on a ``side_um`` patch just larger than its sky window:
    another placement of the graininess reference in seconds to a minute (docs/texture.md §8, seed 37)."""
    from flakedb.reference.flake_sim import simulate
    from tests.texture.cases import sim_inputs, stack_of
    for name in names:
        kw, obs, lights, L, ray = CASES[name]
        o = _observer(obs, lights)
        st = stack_of(**kw)
        sp, ab = sim_inputs(st)
        t = time.time()
        res = simulate(st.eta, st.y_weights, sp, ab, o.spot_um, o.aperture_half_angle_rad, o.source_half_angle_deg,
                       o.view_deg, (), L_um=side_um, seed=seed, wavelength_nm=st.wavelength_nm, ray_um=ray,
                       sky_pixels=SKY_PIXELS[obs])
        res.update(name=name, seconds=time.time() - t, seed=seed, side_um=side_um)
        with open(out, "a") as fh:
            fh.write(json.dumps(res) + "\n")
        print(name, f"{res['seconds']:.0f} s", flush=True)


def run_sim(names, out, seed=36, side_um=None):
    from flakedb.reference.flake_sim import simulate
    from tests.texture.cases import sim_inputs, stack_of
    for name in names:
        kw, obs, lights, L, ray = CASES[name]
        L = side_um or L
        o = _observer(obs, lights)
        st = stack_of(**kw)
        sp, ab = sim_inputs(st)
        t = time.time()
        res = simulate(st.eta, st.y_weights, sp, ab, o.spot_um, o.aperture_half_angle_rad, o.source_half_angle_deg,
                       o.view_deg, o.light_deg, L_um=L, seed=seed, wavelength_nm=st.wavelength_nm, ray_um=ray,
                       sky_pixels=SKY_PIXELS[obs])
        res.update(name=name, seconds=time.time() - t, seed=seed, side_um=L)
        with open(out, "a") as fh:
            fh.write(json.dumps(res) + "\n")
        print(name, f"{res['seconds']:.0f} s", flush=True)


def model_row(name):
    from flakedb.texture import model as tm
    from tests.texture.cases import stack_of
    kw, obs, lights, L, ray = CASES[name]
    o = _observer(obs, lights)
    st = stack_of(**kw)
    return [tm.sparkle_indices(st, o, a) for a in lights], tm.graininess_indices(st, o)


def _ok(m, s, sig, rel=0.10):
    return abs(m - s) <= 3.0 * sig + rel * abs(m)


def table(path):
    rows = [json.loads(l) for l in open(path)]
    print("| case | light | glints/mm² model | sim. (count) | above β_t model | sim. | intensity model | sim. | ok |")
    print("|---|---|---|---|---|---|---|---|---|")
    sky = []
    n_ok = n_all = 0
    for r in rows:
        mrows, g = model_row(r["name"])
        for m, d in zip(mrows, r["directional"]):
            checks = [_ok(m["glints_per_mm2"], d["glints_per_mm2"], d["sigma_glints_per_mm2"]),
                      _ok(m["glints_per_mm2_above_threshold"], d["glints_per_mm2_above_threshold"],
                          d["sigma_glints_per_mm2_above_threshold"])]
            if d["glints"] >= 10:
                checks.append(_ok(m["sparkle_intensity"], d["sparkle_intensity"], d["sigma_sparkle_intensity"]))
            n_ok += sum(checks)
            n_all += len(checks)
            print(f"| {r['name']} | {d['light_deg']:g}° | {m['glints_per_mm2']:.3g} | {d['glints_per_mm2']:.3g} ± "
                  f"{d['sigma_glints_per_mm2']:.2g} ({d['glints']}) | {m['glints_per_mm2_above_threshold']:.3g} | "
                  f"{d['glints_per_mm2_above_threshold']:.3g} ± {d['sigma_glints_per_mm2_above_threshold']:.2g} | "
                  f"{m['sparkle_intensity']:.3g} | {d['sparkle_intensity']:.3g} ± {d['sigma_sparkle_intensity']:.2g} | "
                  f"{'yes' if all(checks) else 'no'} |")
        dd = r["diffuse"]
        gok = g["graininess"] is not None and _ok(g["graininess"], dd["graininess"], dd["sigma_graininess"])
        n_ok += gok
        n_all += 1
        sky.append(f"| {r['name']} | {g['graininess'] if g['graininess'] is None else format(g['graininess'], '.3g')} | "
                   f"{dd['graininess']:.3g} ± {dd['sigma_graininess']:.2g} | {g['flake_luminance_factor']:.4g} | "
                   f"{dd['mean']:.4g} ± {dd['sigma_mean']:.2g} | {'yes' if gok else 'no'} |")
    print()
    print("| case | G model | G sim. | sky mean model | sim. | ok |")
    print("|---|---|---|---|---|---|")
    print("\n".join(sky))
    print(f"\n{n_ok} of {n_all} within 3σ + 10 %")


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=("sim", "sky", "table", "sizes"))
    ap.add_argument("args", nargs="*")
    ap.add_argument("--out", default="bench/texture_reference.jsonl")
    ap.add_argument("--seed", type=int, default=36, help="the simulation's seed (a second placement: another seed)")
    ap.add_argument("--side", type=float, default=None, help="patch side µm (default: the case's)")
    a = ap.parse_args()
    if a.what == "sim":
        run_sim(a.args or list(CASES), a.out, a.seed, a.side)
    elif a.what == "sky":
        run_sky(a.args, a.out, a.seed, a.side or 2600.0)
    elif a.what == "table":
        table(a.args[0] if a.args else a.out)
    else:
        for name in (a.args or CASES):
            m, g = model_row(name)
            L = CASES[name][3]
            print(name, [f"{r['glints_per_mm2']:.3g}/mm² → {r['glints_per_mm2'] * (L / 1000) ** 2:.0f} in patch" for r in m],
                  f"G {g['graininess']}", flush=True)
    sys.exit(0)
