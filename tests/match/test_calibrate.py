"""Calibrating a species from a ladder (flakedb.match.calibrate, `flakedb calibrate`).

Guards against: a calibrated k-factor or size that does not reach the optics (the recipe keeps its
parse-time entry, or the factor is dropped); a user catalogue that does not validate or that compose
reads differently; and a fit that does not recover a known perturbation of a catalogue pigment from
a synthetic masstone / let-down ladder with instrument-like noise (the issue's done-when).
"""

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.colour.tolerance import delta_E_2000
from flakedb.compose.orchestrate import compose
from flakedb.match import calibrate as cal
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.match.targets import E2194_GEOMETRIES, write_target
from flakedb.paint.catalog import load_catalog
from flakedb.paint.materials import refractive_index
from flakedb.paint.species import binder_index, pigment_optics

SP = "cadmium-yellow"


def panel_doc(vf_pigment, vf_white, name):
    parts = [{"species": SP, "volume_fraction": vf_pigment}]
    if vf_white:
        parts.append({"species": "titanium-white", "volume_fraction": vf_white})
    return {"flakedb": 1, "name": name, "spectral": {"mode": "spectral", "range_nm": [400, 700], "step_nm": 20},
            "resolution": 16,
            "layers": [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": 30, "ior": 1.5, "particles": parts}},
                       {"primer": {"color": "black"}}]}


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(None)


def test_absorption_factor_reaches_the_optics(catalog):
    """Factor 1 is the catalogue pigment exactly.  Factor 2 doubles k: where the particles are weak
    absorbers (k x ≪ 1, the volume-absorption limit C_abs ∝ k) their absorption C_ext − C_sca doubles; where
    CdS absorbs strongly (k ≈ 0.3 below 480 nm) the absorption is near saturation and barely moves (more
    surface reflection), and where k = 0 nothing changes."""
    base = catalog["particles"][SP]
    params = cal.free_parameters(base, degree=0)
    wl = np.arange(400.0, 701.0, 20.0)
    nb = binder_index(catalog, wl)
    p0 = pigment_optics(base, wl, nb)
    one = cal.calibrated_entry(base, params, [0.0, 0.0])
    np.testing.assert_array_equal(pigment_optics(one, wl, nb).c_ext_um2, p0.c_ext_um2)
    two = cal.calibrated_entry(base, params, [np.log(2.0), 0.0])
    assert two["absorption_factor"]["value"] == pytest.approx([2.0] * len(cal.factor_grid()), rel=1e-5)
    p2 = pigment_optics(two, wl, nb)
    k = refractive_index(base["material"], wl).imag
    ratio = (p2.c_ext_um2 - p2.c_sca_um2) / np.where(k > 1e-9, p0.c_ext_um2 - p0.c_sca_um2, 1.0)
    weak = (k > 1e-9) & (k < 0.005)                             # 540 nm: k = 0.0015
    assert weak.any() and np.all(np.abs(ratio[weak] - 2.0) < 0.05), ratio
    assert np.all(ratio[k > 0.25] < 1.2), ratio                # saturated
    np.testing.assert_allclose(p2.c_ext_um2[k < 1e-12], p0.c_ext_um2[k < 1e-12], rtol=1e-9)
    size = cal.calibrated_entry(base, params, [0.0, np.log(1.5)])
    assert size["median_diameter_um"]["value"] == pytest.approx(1.5 * base["median_diameter_um"]["value"], rel=1e-5)


def test_user_catalogue_is_used_by_compose(catalog, tmp_path):
    """A calibrated species written into a user catalogue composes to the colour the fit predicted."""
    base = catalog["particles"][SP]
    params = cal.free_parameters(base, degree=1)
    z = np.array([0.4, -0.3, 0.2])
    entry = cal.calibrated_entry(base, params, z)
    path = cal.write_user_catalog(tmp_path / "user.yaml", catalog, "cy-lab", entry)
    user = load_catalog(path)
    assert user["particles"]["cy-lab"]["absorption_factor"] == entry["absorption_factor"]
    doc = panel_doc(0.02, 0.1, "with-lab")
    doc["layers"][1]["basecoat"]["particles"][0]["species"] = "cy-lab"
    rep = compose(recipe_from_doc(doc, catalog=user), tmp_path, catalog=user).report
    lab_compose = np.array([[g["L"], g["a"], g["b"]] for g in rep["geometries"]])
    cat2 = cal._catalog_with(catalog, SP, entry)
    lab_fit = predict(recipe_from_doc(panel_doc(0.02, 0.1, "x"), catalog=cat2), E2194_GEOMETRIES, catalog=cat2).lab()
    np.testing.assert_allclose(lab_compose, lab_fit, atol=1e-9)
    lab_base = predict(recipe_from_doc(panel_doc(0.02, 0.1, "x"), catalog=catalog), E2194_GEOMETRIES,
                       catalog=catalog).lab()
    assert delta_E_2000(lab_base, lab_fit).min() > 1.0          # the calibration changed the colour
    with pytest.raises(ValueError, match="already in the base catalogue"):
        cal.write_user_catalog(tmp_path / "u2.yaml", catalog, SP, entry)


@pytest.mark.slow
def test_recovers_a_known_perturbation_from_a_noisy_ladder(catalog, tmp_path):
    """The issue's done-when.  Truth: cadmium yellow with ln k-factor 0.3 − 0.25 x (k × 1.7 at 380 nm,
    × 1.0 at 700 nm) and 20 % larger particles.  Ladder: masstone and a 1:5 let-down with titanium
    white, 6 geometries, spectra with 0.3 % relative Gaussian noise per band (an instrument's
    repeatability is of this order: ΔE00 ≈ 0.1).  `flakedb calibrate` recovers every parameter within 3
    standard errors, and the calibrated species predicts a held-out let-down (1:20, not in the ladder)
    to ΔE00 < 0.3 where the catalogue species is off by > 1."""
    base = catalog["particles"][SP]
    params = cal.free_parameters(base, degree=1)
    z_true = np.array([0.3, -0.25, np.log(1.2)])
    truth = cal._catalog_with(catalog, SP, cal.calibrated_entry(base, params, z_true))
    rng = np.random.default_rng(20261202)
    panels = []
    for vp, vw, name in ((0.1, 0.0, "masstone"), (0.02, 0.1, "letdown-1-5")):
        doc = panel_doc(vp, vw, name)
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump(doc))
        pr = predict(recipe_from_doc(doc, catalog=truth), E2194_GEOMETRIES, catalog=truth)
        R = pr.rf * (1.0 + 0.003 * rng.standard_normal(pr.rf.shape))
        write_target(tmp_path / f"{name}.csv", pr.geometries, reflectance=R, wavelength_nm=pr.wavelength_nm)
        panels.append({"recipe": f"{name}.yaml", "target": f"{name}.csv"})
    (tmp_path / "ladder.yaml").write_text(yaml.safe_dump({"species": SP, "name": "cy-lab", "panels": panels}))
    r = CliRunner().invoke(cli, ["calibrate", str(tmp_path / "ladder.yaml"), "--out-catalog",
                                 str(tmp_path / "user.yaml"), "--degree", "1", "--report", str(tmp_path / "fit.json")])
    assert r.exit_code == 0, r.output
    fit = json.loads((tmp_path / "fit.json").read_text())
    z = np.array([p["fitted"] for p in fit["parameters"]])
    se = np.array([p["stderr"] for p in fit["parameters"]])
    assert np.all(np.abs(z - z_true) <= 3 * se), (z, z_true, se)
    assert np.all(se < [0.15, 0.25, 0.02])                  # and the ladder determines them usefully
    user = load_catalog(tmp_path / "user.yaml")
    held = panel_doc(0.005, 0.1, "held-out")
    lab_true = predict(recipe_from_doc(held, catalog=truth), E2194_GEOMETRIES, catalog=truth).lab()
    lab_cat = predict(recipe_from_doc(held, catalog=catalog), E2194_GEOMETRIES, catalog=catalog).lab()
    held["layers"][1]["basecoat"]["particles"][0]["species"] = "cy-lab"
    lab_cal = predict(recipe_from_doc(held, catalog=user), E2194_GEOMETRIES, catalog=user).lab()
    assert delta_E_2000(lab_true, lab_cal).max() < 0.3 < 1.0 < delta_E_2000(lab_true, lab_cat).min()


def test_chained_weights_are_the_derivative_of_ln_k(catalog):
    """band_chained_columns' weight of a_j at a band is ∂ln k(λ)/∂a_j of the k-factor compose reads (the
    calibrated entry's samples, interpolated), here by central differences of that factor, at bands off the
    factor's 10 nm samples and over a base entry with its own factor; nothing is chained for an RGB panel
    or a flake."""
    base = dict(catalog["particles"][SP])
    base["absorption_factor"] = {"wavelength_nm": [380.0, 600.0, 780.0], "value": [1.3, 0.8, 1.1], "source": "test"}
    params = cal.free_parameters(base, degree=3)
    z = np.array([0.2, -0.3, 0.15, 0.1, 0.05])
    wl = np.array([383.0, 457.5, 512.0, 640.0, 776.0])
    w = cal.band_chained_columns(params, base, z, [cal._Bands(wl), cal._Bands(wl[::2])])
    assert sorted(w) == [1, 2, 3]                      # a1..a3 chained from a0; size (column 4) is not
    d = 0.05
    for j in (1, 2, 3):
        ln_k = []
        for s in (d, -d):
            zs = z.copy()
            zs[j] += s
            ln_k.append(np.log(cal.absorption_factor(cal.calibrated_entry(base, params, zs)["absorption_factor"], wl)))
        fd = (ln_k[0] - ln_k[1]) / (2 * d)
        # the written factor's 6 significant digits (≤ 5e-6 relative per sample), twice, over the step 2d; the
        # central difference is exact on ln k at the samples (linear in a_j) and O(d²) between them
        np.testing.assert_allclose(w[j][0], fd, rtol=0, atol=2 * 5e-6 / (2 * d) + d**2 / 10)
        np.testing.assert_array_equal(w[j][1], w[j][0][::2])
    assert cal.band_chained_columns(params, base, z, [cal._Bands(wl, mode="rgb")]) == {}
    flake = catalog["particles"]["metallic"]
    assert cal.band_chained_columns(cal.free_parameters(flake), flake, [0.0, 0.0], [cal._Bands(wl)]) == {}


def test_chained_jacobian_column_agrees_with_finite_differences(catalog):
    """The bands of a solve are independent, so the lead step (a0: ln k raised by h in every band) times a
    band's weight is a1's column.  Against forward differences of a1 itself at a larger step, where the
    solve's own rounding matters less (the chained column's step moves every band by h): within 1 % of the
    column's largest entry (measured 0.5 % on this panel, 16 bands, n = 16, where a1's own forward difference
    at the fit's step 1e-3 is off by 2.9 %; a weight of 1 instead of P_1's is off by 460 %)."""
    base = catalog["particles"][SP]
    params = cal.free_parameters(base, degree=1)
    doc = panel_doc(0.05, 0.05, "mix")
    z = np.array([0.1, 0.05, 0.05])

    def rf(zz):
        cat = cal._catalog_with(catalog, SP, cal.calibrated_entry(base, params, zz))
        return predict(recipe_from_doc(doc, catalog=cat), E2194_GEOMETRIES, 16, cat)

    p0 = rf(z)
    h = 1e-3
    lead = (rf(z + [h, 0.0, 0.0]).rf - p0.rf) / h
    fd = np.mean([(rf(z + [0.0, s, 0.0]).rf - p0.rf) / s for s in (1e-2, -1e-2)], axis=0)
    w = cal.band_chained_columns(params, base, z, [p0])[1][0]
    chained = w[None, :] * lead
    scale = np.abs(fd).max()
    assert np.abs(chained - fd).max() < 0.01 * scale, np.abs(chained - fd).max() / scale
    assert np.abs(lead - fd).max() > 0.5 * scale          # the weights matter


@pytest.mark.slow
def test_chained_jacobian_gives_the_same_fit_with_fewer_composes(catalog, tmp_path):
    """The same calibrate with the absorption columns chained (the default) and with a compose per column
    (``band_jacobian=False``, the path before): noise-free ladder made from a known truth (degree 2 and size,
    16 bands, n = 16); both recover the truth to within 1e-3 in every parameter, the chained one with fewer
    composes (2 + 2 per panel and Jacobian instead of 5)."""
    base = catalog["particles"][SP]
    params = cal.free_parameters(base, degree=2)
    z_true = np.array([0.3, -0.25, 0.1, np.log(1.2)])
    truth = cal._catalog_with(catalog, SP, cal.calibrated_entry(base, params, z_true))
    panels = []
    for vp, vw, name in ((0.1, 0.0, "masstone"), (0.02, 0.1, "letdown-1-5")):
        doc = panel_doc(vp, vw, name)
        pr = predict(recipe_from_doc(doc, catalog=truth), E2194_GEOMETRIES, catalog=truth)
        write_target(tmp_path / f"{name}.csv", pr.geometries, reflectance=pr.rf, wavelength_nm=pr.wavelength_nm)
        panels.append(cal.Panel(name, doc, cal.load_target(tmp_path / f"{name}.csv")))
    chained = cal.calibrate(SP, panels, catalog, degree=2)
    plain = cal.calibrate(SP, panels, catalog, degree=2, band_jacobian=False)
    np.testing.assert_allclose(chained.z, z_true, rtol=0, atol=1e-3)
    np.testing.assert_allclose(plain.z, z_true, rtol=0, atol=1e-3)
    assert chained.n_compose < plain.n_compose, (chained.n_compose, plain.n_compose)
