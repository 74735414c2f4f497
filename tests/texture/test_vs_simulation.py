"""The texture model against the independent discrete-flake simulation (flakedb/reference/flake_sim.py,
which shares no code with the model, nor its shortcuts since issue 36: hiding traced from 64 points of each
flake, graininess rendered per ray (the topmost flake), each flake's Airy pattern at its colours): glints per
mm² (half their own peak, and above the fixed threshold, itself compared), the sparkle area fraction, the
sparkle intensity (the brightest pixel), the flakes' mean luminance factor in a layer of discs under a
directional source, and the graininess and mean under a uniform sky, for recipes that vary the loading (×4),
the median diameter (10–40 µm), α (0.05–0.3), the flake (metallic, pearlescent) and a hiding pigment.
Agreement: within 3σ + 10 % (σ the simulation's statistical error).  A perturbed orientation term must fail;
the reference with the old shortcuts switched back on must disagree.  The wider sweep at the BYK-like and
person presets: bench/texture_reference.py, docs/texture.md §8."""

import json
from pathlib import Path

import numpy as np
import pytest

from flakedb.reference.flake_sim import simulate
from flakedb.texture import model as tm
from tests.texture.cases import TEST_OBSERVER, sim_inputs, stack_of

#: name: (recipe arguments, patch side µm, simulate the sky too)
CASES = {
    "metallic-2%-20um-a0.2": (dict(species="metallic", vf=0.02, alpha=0.2, D=20.0), 4000.0, True),
    # 4000 µm (was 2500): at 2500 the 30° row held 28 glints above β_t, 4.5 ± 0.85 per mm², where a 5000 µm patch
    # (seed 12) reads 7.96 ± 0.56 and the model 7.90 (docs/texture.md §8)
    "metallic-8%-20um-a0.2": (dict(species="metallic", vf=0.08, alpha=0.2, D=20.0), 4000.0, True),
    "metallic-2%-10um-a0.05": (dict(species="metallic", vf=0.02, alpha=0.05, D=10.0), 2500.0, False),
    "metallic-2%-40um-a0.3": (dict(species="metallic", vf=0.02, alpha=0.3, D=40.0), 6000.0, True),
    "pearlescent-3%-20um-a0.15": (dict(species="pearlescent", vf=0.03, alpha=0.15, D=20.0), 3500.0, True),
    "metallic-2%-20um-black-pigment": (dict(species="metallic", vf=0.02, alpha=0.2, D=20.0, pigment="iron-black",
                                            pv=0.003), 4000.0, True),
}


#: The sky rendered per ray in a window of this many 20 µm pixels per side, rays this far apart (µm).
SKY_PIXELS, RAY_UM = 100, 2.0


def _close(model, sim, sigma, rel=0.10):
    return abs(model - sim) <= 3.0 * sigma + rel * abs(model)


@pytest.fixture(scope="module")
def runs():
    out = {}
    o = TEST_OBSERVER
    for name, (kw, L, sky) in CASES.items():
        st = stack_of(**kw)
        sp, ab = sim_inputs(st)
        res = simulate(st.eta, st.y_weights, sp, ab, o.spot_um, o.aperture_half_angle_rad, o.source_half_angle_deg,
                       o.view_deg, o.light_deg, L_um=L, seed=11, diffuse=sky,
                       wavelength_nm=st.wavelength_nm, ray_um=RAY_UM, sky_pixels=SKY_PIXELS)
        out[name] = (st, res)
    return out


def _directional_rows(st, res):
    o = TEST_OBSERVER
    for a, r in zip(o.light_deg, res["directional"]):
        yield tm.sparkle_indices(st, o, a), r


@pytest.mark.slow
@pytest.mark.parametrize("name", list(CASES))
def test_glints_agree_with_the_simulation(runs, name):
    st, res = runs[name]
    bad = []
    for m, r in _directional_rows(st, res):
        n = max(r["glints"], 1)
        expected = m["glints_per_mm2"] * res["area_mm2"]
        if expected < 5:  # too few glints in the patch for anything but the count
            if abs(expected - r["glints"]) > 3.0 * np.sqrt(max(expected, 1.0)) + 0.1 * expected:
                bad.append(f"{r['light_deg']:g}° glints: model {expected:.3g} sim {r['glints']} in the patch")
            continue
        checks = [
            ("glints_per_mm2", m["glints_per_mm2"], r["glints_per_mm2"], r["sigma_glints_per_mm2"]),
            ("sparkle_area_fraction", m["sparkle_area_fraction"], r["sparkle_area_fraction"],
             r["sparkle_area_fraction"] / np.sqrt(n) + 1.0 / res["pixels"]),
            ("flake_luminance_factor_discs", m["flake_luminance_factor_discs"], r["flake_luminance_factor"],
             r["sigma_flake_luminance_factor"]),
            ("glints_per_mm2_above_threshold", m["glints_per_mm2_above_threshold"],
             r["glints_per_mm2_above_threshold"], r["sigma_glints_per_mm2_above_threshold"]),
            ("glint_threshold_luminance_factor", m["glint_threshold_luminance_factor"],
             r["glint_threshold_luminance_factor"], 0.0),
        ]
        if r["glints"] >= 10:
            checks.append(("sparkle_intensity", m["sparkle_intensity"], r["sparkle_intensity"], r["sigma_sparkle_intensity"]))
        bad += [f"{r['light_deg']:g}° {k}: model {a:.4g} sim {b:.4g} ± {s:.2g}" for k, a, b, s in checks if not _close(a, b, s)]
    assert not bad, "\n".join(bad)


@pytest.mark.slow
@pytest.mark.parametrize("name", [k for k, v in CASES.items() if v[2]])
def test_graininess_agrees_with_the_simulation(runs, name):
    st, res = runs[name]
    g = tm.graininess_indices(st, TEST_OBSERVER)
    d = res["diffuse"]
    assert _close(g["flake_luminance_factor"], d["mean"], d["sigma_mean"], rel=0.03)
    assert _close(g["graininess"], d["graininess"], d["sigma_graininess"])


@pytest.mark.slow
@pytest.mark.parametrize("scale,least", [(1.3, 2), (1.0 / 1.3, 3)])
def test_a_perturbed_orientation_term_is_caught(runs, monkeypatch, scale, least):
    """The same comparison with the flake-normal density's α scaled by 1/1.3 in the model fails (glints per mm²,
    half-peak and above the fixed threshold) in at least three geometries (measured 7), by 1.3 in at least two
    (measured 3; the model's counts run high in the seed-11 placement of the 2 % and black-pigment cases, so a
    sparser density moves those toward the reference)."""
    import dataclasses

    from flakedb.rt.scattering.microflake import FLAKE_DISTRIBUTIONS

    beck = FLAKE_DISTRIBUTIONS["beckmann"]
    monkeypatch.setitem(FLAKE_DISTRIBUTIONS, "beckmann", dataclasses.replace(beck, ndf=lambda c, a: beck.ndf(c, scale * a)))
    failures = 0
    for name in CASES:
        st, res = runs[name]
        for m, r in _directional_rows(st, res):
            failures += not (_close(m["glints_per_mm2"], r["glints_per_mm2"], r["sigma_glints_per_mm2"])
                             and _close(m["glints_per_mm2_above_threshold"], r["glints_per_mm2_above_threshold"],
                                        r["sigma_glints_per_mm2_above_threshold"]))
    print(f"α × {scale:.3f}: {failures} geometries fail")
    assert failures >= least


@pytest.mark.slow
def test_the_old_shortcuts_are_not_the_reference():
    """The reference with its old shortcuts switched back on (hiding decided from the flake's centre, the sky's
    footprints added per flake) reproduces the model's earlier errors at 8 % metallic: more glints than the
    area hiding gives and a graininess far above the per-ray mosaic (the issue: +72–80 %), which the model
    (eq. G5) does not follow."""
    st = stack_of(**CASES["metallic-8%-20um-a0.2"][0])
    sp, ab = sim_inputs(st)
    o = TEST_OBSERVER
    kw = dict(L_um=1500.0, seed=5, wavelength_nm=st.wavelength_nm, ray_um=RAY_UM, sky_pixels=75)
    new = simulate(st.eta, st.y_weights, sp, ab, o.spot_um, o.aperture_half_angle_rad, o.source_half_angle_deg,
                   o.view_deg, (15.0,), **kw)
    old = simulate(st.eta, st.y_weights, sp, ab, o.spot_um, o.aperture_half_angle_rad, o.source_half_angle_deg,
                   o.view_deg, (15.0,), hiding="centre", sky="deposit", **kw)
    assert old["directional"][0]["glints"] > 1.15 * new["directional"][0]["glints"]
    g = tm.graininess_indices(st, o)["graininess"]
    assert old["diffuse"]["graininess"] > 1.5 * new["diffuse"]["graininess"]
    assert not _close(g, old["diffuse"]["graininess"], old["diffuse"]["sigma_graininess"])
    assert _close(g, new["diffuse"]["graininess"], new["diffuse"]["sigma_graininess"])


def _bench():
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "bench" / "texture_reference.py"
    spec = importlib.util.spec_from_file_location("texture_reference_bench", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_SWEEP = Path(__file__).resolve().parents[2] / "bench" / "texture_reference.jsonl"


@pytest.mark.parametrize("row", [json.loads(line) for line in _SWEEP.read_text().splitlines()], ids=lambda r: r["name"])
def test_the_bench_sweep_holds_against_the_stored_reference(row):
    """docs/texture.md §8's BYK-like and person sweep (loading 2–16 %, diameter 10–40 µm, α 0.05–0.5, metallic and
    pearlescent, with and without a black pigment) re-evaluated by bench/texture_reference.py's own model rows
    against the stored reference (bench/texture_reference.jsonl, flakedb.reference.flake_sim with area hiding,
    per-ray sky and true diffraction): glints per mm² (half-peak and above β_t) and, with ≥ 10 glints, the sparkle
    intensity within 3σ + 10 %, G within 3σ + 10 % (the 16 % metallic graininess too since the sky coupling, eq. G6:
    without it +15 %, outside).
    Guards the table the documentation prints: the occlusion's flakes above 30 % too dense put the 16 % metallic
    and both pearlescent counts outside (tried)."""
    bench = _bench()
    mrows, g = bench.model_row(row["name"])
    for m, d in zip(mrows, row["directional"]):
        assert bench._ok(m["glints_per_mm2"], d["glints_per_mm2"], d["sigma_glints_per_mm2"]), (d["light_deg"], m["glints_per_mm2"])
        assert bench._ok(m["glints_per_mm2_above_threshold"], d["glints_per_mm2_above_threshold"],
                         d["sigma_glints_per_mm2_above_threshold"]), d["light_deg"]
        if d["glints"] >= 10:
            assert bench._ok(m["sparkle_intensity"], d["sparkle_intensity"], d["sigma_sparkle_intensity"]), d["light_deg"]
    dd = row["diffuse"]
    assert bench._ok(g["graininess"], dd["graininess"], dd["sigma_graininess"]), \
        (g["graininess"], dd["graininess"])
