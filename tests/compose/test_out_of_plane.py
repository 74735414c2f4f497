"""Out-of-plane geometries through compose, compare and match (issue 39 item 4).

Guards against: an out-of-plane colour taken from the wrong point of the BSDF (the in-plane φ_d 0/π, a wrong μ_o,
the azimuth's Fourier sum dropped or mis-signed) — checked against the written .h5 evaluated by the file reader
at directions built here from the instrument's published detector vectors, and against the solver's own Fourier
sum at node pairs; a table evaluation that is not reciprocal (swapping light and view must give the same
reflectance factor: exactly at the nodes, and off them to the interpolation's accuracy, which converges with n);
and an out-of-plane target (CSV azimuth_deg column, CxF3 Azimuth) that is refused, misread or written back
differently, which `compare` against the written file would show as a ΔE above 0.
"""

import csv
import json
import textwrap

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.bsdf import open_bsdf
from flakedb.cli.main import cli
from flakedb.colour.geometry import from_vectors, view_vector
from flakedb.colour.settings import OUT_OF_PLANE_GEOMETRIES, XRITE19_GEOMETRIES, resolve
from flakedb.compose.orchestrate import compose
from flakedb.match.cxf import read_cxf_target
from flakedb.match.fit import compose_solved, eval_geometries, predict
from flakedb.match.targets import read_target, write_target
from flakedb.paint.recipe import parse_recipe

LAYERS = [{"clearcoat": {"thickness_um": 40, "ior": 1.5}},
          {"basecoat": {"thickness_um": 10, "ior": 1.5, "particles": [
              {"species": "metallic", "volume_fraction": 0.03, "orientation_alpha": 0.35}]}},
          {"primer": {"color": "gray"}}]
#: The instrument's out-of-plane detectors (X-Rite, tests/colour/test_geometry.py) and the names they have under
#: the 45° and 15° illuminators.
DETECTORS = {"45as25az90": (45, (0.640856, 0.422618, 0.640856)), "45as25az-90": (45, (0.640856, -0.422618, 0.640856)),
             "45as60az125.3": (45, (0, 0.707, 0.707)), "45as60az-125.3": (45, (0, -0.707, 0.707)),
             "15as38.3az43": (15, (0.640856, 0.422618, 0.640856)), "15as38.3az-43": (15, (0.640856, -0.422618, 0.640856)),
             "15as46.9az104.5": (15, (0, 0.707, 0.707)), "15as46.9az-104.5": (15, (0, -0.707, 0.707))}


def _text(n=16, name="oop", bands="range_nm: [400, 700], step_nm: 20"):
    return (f"flakedb: 1\nname: {name}\nspectral: {{mode: spectral, {bands}}}\nresolution: {n}\nlayers:\n"
            + textwrap.indent(yaml.safe_dump(LAYERS, sort_keys=False, default_flow_style=None), "  "))


@pytest.fixture(scope="module")
def composed(tmp_path_factory):
    out = tmp_path_factory.mktemp("oop")
    res = compose(parse_recipe(_text()), out, raw=True, colour_settings=resolve(geometry_set="xrite19"))
    return res, open_bsdf(out / "oop.h5")


def test_out_of_plane_report_rows_are_the_written_bsdf_at_the_detector_directions(composed):
    """The report's out-of-plane reflectance factors are π f of the .h5 as the file reader evaluates it, at
    (μ_i, μ_o, φ_d) computed here from the published detector vectors by plain vector algebra (no flakedb
    geometry code): μ_i = cos θ_i, μ_o = −d_z, φ_d = the angle between the light's and the detector's
    horizontal directions."""
    res, b5 = composed
    rows = {r["illumination_deg"]: None for r in res.report["geometries"]}
    assert len(res.report["geometries"]) == 19 and set(rows) == {45.0, 15.0}
    by_name = {}
    for r in res.report["geometries"]:
        if r["azimuth_deg"]:
            by_name[f"{r['illumination_deg']:g}as{r['aspecular_deg']:g}az{r['azimuth_deg']:g}"] = r
    assert set(by_name) == set(DETECTORS)
    for name, (th, d) in DETECTORS.items():
        d = np.asarray(d, float) / np.linalg.norm(d)
        mu_i, mu_o = np.cos(np.radians(th)), -d[2]
        phi_d = np.arccos(d[0] / np.hypot(d[0], d[1]))     # the light travels along +x
        direct = np.pi * b5.eval(mu_i, mu_o, phi_d, clamp="none") / abs(mu_o)
        # the named angles are the detector's rounded to 0.1°: the report is evaluated there, so compare at
        # the report's own directions too (exactly), and at the detector's within the rounding's effect
        r = by_name[name]
        exact = np.pi * b5.eval(r["mu_i"], r["mu_o"], r["phi_d"], clamp="none") / abs(r["mu_o"])
        np.testing.assert_allclose(r["reflectance_factor"], exact, rtol=1e-10, atol=1e-14)
        assert abs(r["mu_o"] - mu_o) < 2e-3 and abs(r["phi_d"] - phi_d) < 3e-3, name
        np.testing.assert_allclose(r["reflectance_factor"], direct, rtol=5e-3)
    # the azimuth matters: out of plane at aspecular 25° is not the in-plane 45as25 (φ_d and μ_o differ)
    in_plane = next(r for r in res.report["geometries"] if (r["illumination_deg"], r["aspecular_deg"],
                                                            r["azimuth_deg"]) == (45.0, 25.0, 0.0))
    assert abs(by_name["45as25az90"]["L"] - in_plane["L"]) > 0.5
    # an isotropic paint: ± azimuth give the same colour
    assert by_name["45as25az90"]["reflectance_factor"] == by_name["45as25az-90"]["reflectance_factor"]


def test_out_of_plane_at_node_pairs_is_the_solvers_fourier_sum(composed):
    """Directions on the solver's nodes with an out-of-plane azimuth: the table evaluation through the geometry
    (θ_i, γ, az) is the solver's own f(μ_i, μ_o, φ_d) (:meth:`eval_nodes`, its Fourier sum), to the rounding of
    the angles' round trip through trigonometry (a few ulps of μ, times |d ln f/dμ| ≲ 10²)."""
    res, _ = composed
    s = res.stack
    x = s.x
    phis = np.array([0.3, 1.2, 2.5])
    f = s.eval_nodes(phis)                                     # (C, h_o, h_i, P) in 1/sr
    for ki, ko in ((4, 5), (5, 3), (6, 4)):
        for p, ph in enumerate(phis):
            light = (np.sqrt(1 - x[ki] ** 2), 0.0, -x[ki])
            det = (np.sqrt(1 - x[ko] ** 2) * np.cos(ph), np.sqrt(1 - x[ko] ** 2) * np.sin(ph), x[ko])
            g = from_vectors(light, det)
            assert g[2] != 0.0
            rf = eval_geometries(res.table, [g])[0]
            np.testing.assert_allclose(rf, np.pi * f[:, ko, ki, p], rtol=1e-12)


def _swapped(geometries):
    """The geometries with light and view exchanged: the light travels against the old view direction, the view
    looks back along the old light."""
    out = []
    for th, asp, az in np.asarray(geometries, float):
        t = np.radians(th)
        light = np.array([np.sin(t), 0.0, -np.cos(t)])
        out.append(from_vectors(-view_vector(th, asp, az), -light))
    return out


def test_reciprocity_exact_at_nodes(composed):
    res, _ = composed
    x = res.stack.x
    g = [from_vectors((np.sqrt(1 - x[ki] ** 2), 0, -x[ki]),
                      (np.sqrt(1 - x[ko] ** 2) * np.cos(ph), np.sqrt(1 - x[ko] ** 2) * np.sin(ph), x[ko]))
         for ki, ko, ph in ((4, 5, 0.7), (6, 3, 2.0), (5, 5, 1.4))]
    rf, rf_swapped = eval_geometries(res.table, g), eval_geometries(res.table, _swapped(g))
    # the solver is reciprocal at its nodes to rounding (measured 1e-14 of the table's largest value)
    np.testing.assert_allclose(rf_swapped, rf, rtol=1e-12)


def test_reciprocity_off_nodes_converges_with_n():
    """Off the nodes the readers interpolate f·|μ_o| (docs/bsdf-format.md), so the swapped geometry interpolates
    the other cosine: light ↔ view differs by the interpolation error, which falls at least 4× per doubling of n
    (measured relative asymmetry at the xrite19 geometries: 3.8e-3, 2.4e-4, 3.6e-5 at n = 16, 32, 64)."""
    asym = []
    for n in (16, 32, 64):
        table = compose_solved(parse_recipe(_text(n, bands="range_nm: [500, 540], step_nm: 20")), n, raw=True).table
        rf, rf_s = eval_geometries(table, XRITE19_GEOMETRIES), eval_geometries(table, _swapped(XRITE19_GEOMETRIES))
        asym.append(float(np.max(np.abs(rf_s / rf - 1))))
    assert asym[0] < 1e-2 and asym[1] < asym[0] / 4 and asym[2] < asym[1] / 4, asym


def test_out_of_plane_targets_read_compare_and_write_back(tmp_path):
    """A target CSV with an azimuth_deg column and the CxF3 file `compare --write-cxf` writes both read back with
    the out-of-plane geometries, and compare against either is ΔE 0 at all 19 geometries."""
    (tmp_path / "r.yaml").write_text(_text(name="oop-t", bands="range_nm: [400, 700], step_nm: 20"))
    cxf = tmp_path / "p.cxf"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--write-cxf", str(cxf), "--geometries",
                                 "xrite19"])
    assert r.exit_code == 0, r.output
    assert "az90°" in r.output and "az-125.3°" in r.output
    t = read_cxf_target(cxf)
    np.testing.assert_array_equal(t.geometries, np.asarray(XRITE19_GEOMETRIES))
    pred = predict(parse_recipe(_text(name="oop-t")), XRITE19_GEOMETRIES)
    np.testing.assert_array_equal(t.reflectance, pred.rf)
    write_target(tmp_path / "t.csv", t.geometries, reflectance=t.reflectance, wavelength_nm=t.wavelength_nm,
                 name="oop-csv")
    assert "illumination_deg,aspecular_deg,azimuth_deg," in (tmp_path / "t.csv").read_text()
    tc = read_target(tmp_path / "t.csv")
    np.testing.assert_array_equal(tc.geometries, t.geometries)
    # the CxF3 spectra are written with 17 digits (ΔE exactly 0), the CSV's with 9 (relative 5e-10: ΔE00 < 1e-6)
    for target, limit in ((cxf, 0.0), (tmp_path / "t.csv", 1e-6)):
        table = tmp_path / f"{target.stem}-table.csv"
        r = CliRunner().invoke(cli, ["compare", str(tmp_path / "r.yaml"), "--target", str(target), "--max-de",
                                     f"{limit:g}", "--table", str(table)])
        assert r.exit_code == 0, r.output
        rows = list(csv.DictReader(table.open()))
        assert len(rows) == 19 and all(float(x["dE00"]) <= limit for x in rows)
        assert sorted({float(x["azimuth_deg"]) for x in rows}) == sorted({0.0} | {g[2] for g in OUT_OF_PLANE_GEOMETRIES})


def test_match_recovers_a_loading_from_out_of_plane_geometries_only(tmp_path):
    """`match` against a target measured at the eight out-of-plane geometries alone (made from a known metallic
    loading) recovers the loading from a start 3× off; its report names the azimuths."""
    pred = predict(parse_recipe(_text(name="oop-m")), OUT_OF_PLANE_GEOMETRIES)
    write_target(tmp_path / "t.csv", OUT_OF_PLANE_GEOMETRIES, reflectance=pred.rf, wavelength_nm=pred.wavelength_nm,
                 name="oop-only")
    base = _text(name="oop-m").replace("volume_fraction: 0.03", "volume_fraction: {fit: [0.005, 0.2], start: 0.09}")
    assert "fit:" in base
    (tmp_path / "base.yaml").write_text(base)
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(tmp_path / "t.csv"),
                                 "--out", str(out), "--limit", "45/25/90=0.5"])
    assert r.exit_code == 0, r.output
    assert "az90°" in r.output and "az-104.5°" in r.output
    fitted = yaml.safe_load((out / "oop-m-fitted.yaml").read_text())
    assert fitted["layers"][1]["basecoat"]["particles"][0]["volume_fraction"] == pytest.approx(0.03, rel=0.01)
    rep = json.loads((out / "oop-m-match.json").read_text())
    assert [g["azimuth_deg"] for g in rep["geometries"]] == [g[2] for g in OUT_OF_PLANE_GEOMETRIES]
    assert max(g["dE00_start"] for g in rep["geometries"]) > 1.0 and max(g["dE00_fit"] for g in rep["geometries"]) < 0.05
