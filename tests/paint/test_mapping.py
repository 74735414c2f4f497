"""resolution: auto meets its accuracy targets (issue 12; docs/resolution.md).

Guards against: an auto n that misses the stated albedo accuracy of a rough coat over a scattering
slab; a rough coat whose auto n breaks the white furnace.  Only order 0 is solved (the albedo is
order 0 exactly: the adding method does not mix Fourier orders), which keeps the tests fast.
"""

import numpy as np
import pytest
import yaml
from scipy.interpolate import CubicSpline

from flakedb.paint.mapping import auto_resolution, build_paint, solve_paint
from flakedb.paint.recipe import parse_recipe


def _recipe(alpha, slab=True, primer=0.5):
    layers = [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": alpha}}]
    if slab:
        layers.append({"basecoat": {"thickness_um": 10, "ior": 1.5, "particles": [
            {"custom": {"kind": "medium", "name": "hg", "albedo": 0.9, "phase": {"hg": 0.7}}, "optical_depth": 1.0}]}})
    layers.append({"primer": {"albedo": primer}})
    return parse_recipe(yaml.safe_dump({"flakedb": 1, "name": "t", "spectral": {"mode": "mono"},
                                        "resolution": "auto", "layers": layers}))


def _albedo(paint, n, mu):
    st = solve_paint(paint, n, max_orders=1)
    return CubicSpline(st.x, st.albedo()[0])(mu)


def test_auto_rough_coat_hg_slab_diffuse_albedo_within_one_percent():
    r = _recipe(0.02)
    n, why = auto_resolution(r)
    assert n <= 512 and "rough coat" in why
    paint = build_paint(r)
    mu = np.cos(np.radians(np.linspace(0.0, 80.0, 17)))
    a, ref = _albedo(paint, n, mu), _albedo(paint, 384 if n < 384 else 512, mu)
    assert np.abs(a / ref - 1.0).max() <= 0.01


@pytest.mark.parametrize("alpha", [0.01, 0.02, 0.05, 0.1, 0.3])
def test_auto_rough_coat_white_furnace(alpha):
    r = _recipe(alpha, slab=False, primer=1.0)
    n, _ = auto_resolution(r)
    st = solve_paint(build_paint(r), n, max_orders=1)
    sel = st.x >= np.cos(np.radians(80.0))
    assert np.abs(st.albedo()[0][sel] - 1.0).max() <= 1e-3


def _medium_recipe(albedo, phase, mode="spectral", resolution="auto"):
    spectral = {"spectral": {"mode": "spectral", "range_nm": [400, 700], "step_nm": 20},
                "rgb": {"mode": "rgb", "range_nm": [380, 780], "step_nm": 10}, "mono": {"mode": "mono"}}[mode]
    layers = [{"clearcoat": {"thickness_um": 40, "ior": 1.5}},
              {"basecoat": {"thickness_um": 10, "ior": 1.5, "particles": [
                  {"custom": {"kind": "medium", "albedo": albedo, "phase": phase}, "optical_depth": 2.0}]}},
              {"primer": {"albedo": 0.5}}]
    return parse_recipe(yaml.safe_dump({"flakedb": 1, "name": "t", "spectral": spectral,
                                        "resolution": resolution, "layers": layers}))


def test_custom_medium_albedo_spectrum_per_band_and_vmf_phase():
    spec = {"wavelength_nm": [380, 550, 780], "value": [0.9, 0.3, 0.6]}
    paint = build_paint(_medium_recipe(spec, {"vmf": {"kappa": 20}}))
    med = paint.slabs[0].medium
    wl = paint.wavelength_nm
    np.testing.assert_allclose(med.albedo, np.interp(wl, spec["wavelength_nm"], spec["value"]), rtol=1e-15)
    np.testing.assert_allclose(med.sigma_t_per_um, 0.2)
    assert med.phase == ("vmf", 20.0)
    rec = paint.components[0]
    assert rec["albedo"] == [med.albedo.min(), med.albedo.max()] and med.albedo.max() == pytest.approx(0.9 - 0.6 * 20 / 170)
    assert rec["phase"]["vmf"]["kappa"] == 20.0 and rec["phase"]["vmf"]["g"] == pytest.approx(0.95, abs=1e-15)


def test_custom_medium_albedo_in_rgb_mode_is_the_linear_map_clipped():
    from flakedb.colour.colorimetry import spectra_to_rgb_mode

    flat = build_paint(_medium_recipe({"wavelength_nm": [380, 780], "value": [0.5, 0.5]}, "isotropic", "rgb"))
    np.testing.assert_allclose(flat.slabs[0].medium.albedo, 0.5, atol=1e-12)  # white-normalised: grey stays grey
    assert flat.info["rgb_clip"]["layers[1].basecoat.particles[0]"] < 1e-12
    # a narrow blue band: sRGB's negative lobes push red below 0, which is clipped and reported
    wl = np.arange(380.0, 781.0, 10.0)
    vals = np.where(np.abs(wl - 450) <= 10, 1.0, 0.0)
    p = build_paint(_medium_recipe({"wavelength_nm": wl.tolist(), "value": vals.tolist()}, "isotropic", "rgb"))
    raw = spectra_to_rgb_mode(vals, wl)
    np.testing.assert_allclose(p.slabs[0].medium.albedo, np.clip(raw, 0, 1), rtol=1e-12)
    assert raw.min() < 0 and p.info["rgb_clip"]["layers[1].basecoat.particles[0]"] == pytest.approx(-raw.min())


def test_auto_resolution_resolves_the_vmf_lobe():
    n, why = auto_resolution(_medium_recipe(0.9, {"vmf": {"kappa": 400}}))
    assert "vMF lobe κ = 400" in why and n >= 2 * 1.7 * np.sqrt(400)
    n0, why0 = auto_resolution(_medium_recipe(0.9, {"vmf": {"kappa": 1}}))
    assert n0 == 32 and "vMF" not in why0
