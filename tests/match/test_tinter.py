"""Creating a tinter from drawdowns (flakedb.match.tinter, `flakedb calibrate --tinter`).

Guards against: the cheap Jacobian's premise failing (a solve's bands not independent, so that one
all-band perturbation would not give each band's derivative); a fit that does not recover a known
tinter from synthetic drawdowns (masstones over black and white, tints with a Mie white), exactly
without noise and within its stated standard errors with 0.2 % reflectance noise (docs/calibration.md,
"Tinters from drawdowns"); a written entry that composes differently from the fitted one; the command
not writing the user catalogue, or writing one from a Kubelka–Munk seed with the wrong conversion.
"""

import copy

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.colour.tolerance import delta_E_2000
from flakedb.match import tinter as tn
from flakedb.match.calibrate import Panel
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.match.targets import E2194_GEOMETRIES, Target, write_target
from flakedb.paint.catalog import load_catalog

SPAN = (400.0, 700.0)
#: A blue-ish tinter: absorbs in the red (ln σ_a/φ from ≈ −1.5 to 2.8), scatters weakly, g = 0.45.
TRUTH = tn.TinterParams(np.array([1.0, 1.2, -1.5, -0.8, 0.4]), np.array([-0.5, -0.6, 0.2, 0.0, 0.0]), 0.45)
#: The lab's design (docs/calibration.md): masstone over black and over white (incomplete hiding at 25 µm),
#: tints 1:5 and 1:20 with the white over black.  (name, φ tinter, φ white, primer)
DESIGN = [("mass-black", 0.05, 0.0, "black"), ("mass-white", 0.05, 0.0, "white"),
          ("tint5-black", 0.02, 0.10, "black"), ("tint20-black", 0.005, 0.10, "black")]
HELD_OUT = ("tint10-white", 0.01, 0.10, "white")


def panel_doc(species, vf, white, primer, step=20):
    parts = [{"species": species, "volume_fraction": vf}]
    if white:
        parts.append({"species": "titanium-white-r706", "volume_fraction": white})
    return {"flakedb": 1, "name": "panel", "spectral": {"mode": "spectral", "range_nm": [400, 700], "step_nm": step},
            "resolution": 16,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": 25, "ior": 1.5, "particles": parts}},
                       {"primer": {"color": primer}}]}


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(None)


def truth_catalog(catalog, params=TRUTH, name="true-tinter"):
    cat = copy.deepcopy(catalog)
    cat["particles"][name] = tn.tinter_entry(params, SPAN, "the synthetic truth", "tests")
    return cat


def synthetic_panels(catalog, design=DESIGN, noise=0.0, seed=0, params=TRUTH, step=20):
    """Panels whose targets are flakedb's own predictions with the true tinter (+ Gaussian noise of
    standard deviation ``noise`` in reflectance factor), recipes naming the new tinter ``my-tinter``."""
    cat = truth_catalog(catalog, params)
    rng = np.random.default_rng(seed)
    panels = []
    for name, vf, white, primer in design:
        pred = predict(recipe_from_doc(panel_doc("true-tinter", vf, white, primer, step), name, cat),
                       E2194_GEOMETRIES, 16, cat)
        R = pred.rf + noise * rng.standard_normal(pred.rf.shape)
        tgt = Target(geometries=np.array(E2194_GEOMETRIES, float), reflectance=R, wavelength_nm=pred.wavelength_nm,
                     source=name)
        panels.append(Panel(name, panel_doc("my-tinter", vf, white, primer, step), tgt))
    return panels


def test_bands_are_independent(catalog):
    """The premise of the 3-solve Jacobian: raising ln σ_a/φ in every band moves band b exactly as raising
    it in band b alone (each channel is its own adding-doubling solve)."""
    panel = synthetic_panels(catalog, design=[DESIGN[2]])[0]
    cat = truth_catalog(catalog, name="my-tinter")
    m = tn._PanelModel(panel, "my-tinter", cat, None)
    sa, ss = TRUTH.coefficients(m.wl, SPAN)
    h = 1e-4
    r0 = m.rf(sa, ss, TRUTH.g)
    r_all = m.rf(sa * np.exp(h), ss, TRUTH.g)
    for b in (3, 11):
        one = sa.copy()
        one[b] *= np.exp(h)
        r_one = m.rf(one, ss, TRUTH.g)
        np.testing.assert_allclose(r_all[:, b], r_one[:, b], rtol=1e-9, atol=1e-13)
        others = np.delete(np.arange(m.wl.size), b)
        np.testing.assert_allclose(r_one[:, others], r0[:, others], rtol=1e-12, atol=1e-15)  # untouched bands
    assert np.abs(r_all - r0).max() > 1e-6  # and it does move the colour


@pytest.mark.slow
def test_recovers_a_known_tinter_exactly(catalog):
    """Noise-free ladder, fitted at the truth's degree: the series coefficients and g are recovered to
    1e-4 and the written tinter composes to the targets (ΔE00 ≤ 1e-3 through the ordinary path)."""
    panels = synthetic_panels(catalog)
    res = tn.fit_tinter("my-tinter", panels, catalog, degree=4)
    np.testing.assert_allclose(res.params.a, TRUTH.a, atol=1e-4)
    np.testing.assert_allclose(res.params.b, TRUTH.b, atol=1e-4)
    assert res.params.g == pytest.approx(TRUTH.g, abs=1e-4)
    assert max(d.max() for d in res.de_fit) < 1e-3
    assert res.entry["kind"] == "tinter" and res.entry["specific_absorption_per_um"]["wavelength_nm"][0] == 400.0


@pytest.mark.slow
def test_recovers_a_transparent_yellow_from_a_flat_start(catalog):
    """A weakly scattering yellow (σ_s′/φ ≈ 0.1 /µm, absorbing below 500 nm), far from the flat start
    (σ/φ = 1 /µm): recovered exactly (no continuation stages needed)."""
    truth = tn.TinterParams(np.array([0.5, -2.5, 0.5, 0.5, -0.3]), np.array([-2.0, -0.5, 0.0, 0.0, 0.0]), 0.2)
    res = tn.fit_tinter("my-tinter", synthetic_panels(catalog, params=truth), catalog, degree=4)
    np.testing.assert_allclose(res.params.a, truth.a, atol=1e-4)
    np.testing.assert_allclose(res.params.b, truth.b, atol=1e-4)
    assert res.params.g == pytest.approx(truth.g, abs=1e-4)


@pytest.mark.slow
def test_recovers_a_tinter_from_a_noisy_ladder(catalog):
    """0.2 % reflectance noise (σ = 0.002 in every reading), fitted at the default degree 6 (two more than
    the truth): ln σ_a/φ within 0.02 and 3 standard errors in every band, ln σ_s′/φ within 3 standard
    errors (and 0.35), g within 3 standard errors; a held-out tint (1:10 over white) predicted within
    ΔE00 0.3 of the truth's prediction.  Measured values: docs/calibration.md."""
    panels = synthetic_panels(catalog, noise=0.002, seed=20261207)
    res = tn.fit_tinter("my-tinter", panels, catalog)
    wl = res.ln_sigma_stderr["wavelength_nm"]
    sa, ss = res.params.coefficients(wl, SPAN)
    ta, ts = TRUTH.coefficients(wl, SPAN)
    ea = np.log(sa / ta)
    eb = np.log(ss * (1 - res.params.g) / (ts * (1 - TRUTH.g)))
    se_a, se_b = res.ln_sigma_stderr["ln_sigma_a"], res.ln_sigma_stderr["ln_sigma_s_reduced"]
    assert np.all(np.abs(ea) <= np.maximum(3 * se_a, 1e-3)) and np.abs(ea).max() < 0.02, (ea, se_a)
    assert np.all(np.abs(eb) <= 3 * se_b) and np.abs(eb).max() < 0.35, (eb, se_b)
    assert abs(res.params.g - TRUTH.g) <= 3 * res.stderr[-1], (res.params.g, res.stderr[-1])
    assert 0.0015 < res.rms_residual / 100 < 0.0025  # the noise itself: no misfit left
    # the held-out panel
    name, vf, white, primer = HELD_OUT
    user = copy.deepcopy(catalog)
    user["particles"]["my-tinter"] = res.entry
    cat_t = truth_catalog(catalog)
    p_fit = predict(recipe_from_doc(panel_doc("my-tinter", vf, white, primer), name, user), E2194_GEOMETRIES, 16, user)
    p_true = predict(recipe_from_doc(panel_doc("true-tinter", vf, white, primer), name, cat_t), E2194_GEOMETRIES, 16,
                     cat_t)
    assert delta_E_2000(p_true.lab(), p_fit.lab()).max() < 0.3


@pytest.mark.slow
def test_command_fits_writes_and_composes(catalog, tmp_path):
    """`flakedb calibrate --tinter` end to end on a degree-1 tinter over two panels (20 nm bands): the user
    catalogue is written, and a recipe naming the tinter composes to the held-out target's colour."""
    truth = tn.TinterParams(np.array([0.5, 1.0]), np.array([0.3, -0.4]), 0.3)
    design = [("mass-black", 0.05, 0.0, "black"), ("tint-black", 0.01, 0.10, "black")]
    panels = synthetic_panels(catalog, design=design, params=truth)
    entries = []
    for p in panels:
        (tmp_path / f"{p.name}.yaml").write_text(yaml.safe_dump(p.recipe_doc, sort_keys=False))
        write_target(tmp_path / f"{p.name}.csv", p.target.geometries, reflectance=p.target.reflectance,
                     wavelength_nm=p.target.wavelength_nm)
        entries.append({"recipe": f"{p.name}.yaml", "target": f"{p.name}.csv"})
    (tmp_path / "ladder.yaml").write_text(yaml.safe_dump({"tinter": "my-tinter", "colour_index": "PB15:3",
                                                          "panels": entries}, sort_keys=False))
    out = tmp_path / "user.yaml"
    r = CliRunner().invoke(cli, ["calibrate", "--tinter", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out),
                                 "--tinter-degree", "1", "--report", str(tmp_path / "fit.json")])
    assert r.exit_code == 0, r.output
    user = load_catalog(out)
    e = user["particles"]["my-tinter"]
    assert e["kind"] == "tinter" and e["colour_index"] == "PB15:3"
    held = panel_doc("my-tinter", 0.01, 0.10, "white")
    cat_t = truth_catalog(catalog, truth)
    p_fit = predict(recipe_from_doc(held, "h", user), E2194_GEOMETRIES, 16, user)
    p_true = predict(recipe_from_doc(panel_doc("true-tinter", 0.01, 0.10, "white"), "h", cat_t), E2194_GEOMETRIES,
                     16, cat_t)
    assert delta_E_2000(p_true.lab(), p_fit.lab()).max() < 0.01


def test_command_writes_a_kubelka_munk_seed(catalog, tmp_path):
    """A ladder with a seed and no panels writes the seed itself: σ_a/φ = K/2, σ_s/φ = (S + K/8) 4/(3(1 − g))."""
    (tmp_path / "km.csv").write_text("wavelength_nm,K,S\n380,8,2\n780,0.4,3\n")
    (tmp_path / "ladder.yaml").write_text("tinter: km-red\nseed: {km: km.csv, asymmetry_g: 0.5}\npanels: []\n")
    out = tmp_path / "user.yaml"
    r = CliRunner().invoke(cli, ["calibrate", "--tinter", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out)])
    assert r.exit_code == 0, r.output
    e = load_catalog(out)["particles"]["km-red"]
    assert e["specific_absorption_per_um"]["value"] == pytest.approx([4.0, 0.2])
    assert e["specific_scattering_per_um"]["value"] == pytest.approx([(2 + 1) * 8 / 3, (3 + 0.05) * 8 / 3])
    assert e["asymmetry_g"]["value"] == 0.5


def test_command_refuses_bad_ladders(catalog, tmp_path):
    (tmp_path / "ladder.yaml").write_text("tinter: titanium-white\npanels: []\nseed: {km: km.csv}\n")
    (tmp_path / "km.csv").write_text("wavelength_nm,K,S\n380,8,2\n780,0.4,3\n")
    out = tmp_path / "user.yaml"
    r = CliRunner().invoke(cli, ["calibrate", "--tinter", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out)])
    assert r.exit_code != 0 and "already a species" in r.output and not out.exists()
    (tmp_path / "ladder.yaml").write_text("tinter: new-one\npanels: []\n")
    r = CliRunner().invoke(cli, ["calibrate", "--tinter", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out)])
    assert r.exit_code != 0 and "panels must be a non-empty list" in r.output and not out.exists()
    (tmp_path / "ladder.yaml").write_text("tinter: new-one\nspecies: x\npanels: []\n")
    r = CliRunner().invoke(cli, ["calibrate", "--tinter", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out)])
    assert r.exit_code != 0 and "unknown key(s) ['species']" in r.output and not out.exists()


@pytest.mark.slow
def test_fit_from_a_kubelka_munk_seed(catalog):
    """A seed from KM data (a scattering tinter's K, S by the Star 1988 relation, at a wrong g = 0.2): KM
    keeps σ_s′, so the seeded curves are the truth's and only g is off; the fit, in one stage at the seed's
    degree, finds the true g and keeps the curves (two panels, 20 nm bands)."""
    from flakedb.optics.kubelka_munk import rt_to_km

    truth = tn.TinterParams(np.array([0.0, 0.8, -0.5]), np.array([1.2, -0.3, 0.1]), 0.45)
    design = [("mass-white", 0.05, 0.0, "white"), ("tint5-black", 0.02, 0.10, "black")]
    panels = synthetic_panels(catalog, design=design, params=truth)
    wl = np.arange(400.0, 701.0, 10.0)
    K, S = rt_to_km(*truth.coefficients(wl, SPAN), truth.g)
    assert np.all(S > 0)  # inside the relation's range (σ_s′ > σ_a / 3)
    res = tn.fit_tinter("my-tinter", panels, catalog, seed=tn.seed_from_km(wl, K, S, 0.2), degree=2)
    assert [h["degree"] for h in res.history] == [2] * len(res.history)
    assert res.history[0]["z"][-1] == pytest.approx(0.2)
    np.testing.assert_allclose(res.history[0]["z"][:6], np.concatenate([truth.a, truth.b]), atol=1e-3)
    assert res.params.g == pytest.approx(truth.g, abs=1e-4)
    np.testing.assert_allclose(res.params.a, truth.a, atol=1e-4)
    np.testing.assert_allclose(res.params.b, truth.b, atol=1e-4)


def test_command_refuses_bad_kubelka_munk_files(tmp_path):
    out = tmp_path / "user.yaml"
    (tmp_path / "ladder.yaml").write_text("tinter: km-x\nseed: {km: km.csv}\npanels: []\n")
    for text, why in [("wavelength,K,S\n400,1,2\n700,1,1\n", "the first line must be the header wavelength_nm,K,S"),
                      ("wavelength_nm,K,S\n400,-1,2\n700,1,1\n", "line 2: wavelength > 0 and K, S >= 0"),
                      ("wavelength_nm,K,S\n400,1,2\n", "at least two rows"),
                      ("wavelength_nm,K,S\n400,1,x\n700,1,1\n", "line 2: three numbers")]:
        (tmp_path / "km.csv").write_text(text)
        r = CliRunner().invoke(cli, ["calibrate", "--tinter", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out)])
        assert r.exit_code != 0 and why in r.output and "Traceback" not in r.output and not out.exists(), r.output
    (tmp_path / "km.csv").unlink()
    r = CliRunner().invoke(cli, ["calibrate", "--tinter", str(tmp_path / "ladder.yaml"), "--out-catalog", str(out)])
    assert r.exit_code != 0 and "km.csv: no such file" in r.output
