"""Measured BRDFs (MERL format) read at instrument geometries (flakedb.match.merl, docs/validation.md).

Guards against: a wrong half/difference change of variables (the in-plane closed forms θ_h = |γ|/2,
θ_d = |θ_i − γ/2| are independent of the vector construction); a wrong bin (the square-root θ_h spacing,
the φ_d reciprocity fold) or plane order; a lost channel scale; a wrong RGB → CIELAB step (published
sRGB primaries' CIELAB); a file whose size disagrees with its header read as data; a target that does
not read back through flakedb.match.targets.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flakedb.match.merl import (
    MERL_DIMS,
    MERL_SCALE,
    MerlError,
    half_diff,
    in_plane_directions,
    merl_bins,
    merl_rgb_to_lab,
    merl_target,
    read_merl,
    write_merl,
)
from flakedb.match.targets import E2539_GEOMETRIES, read_target

G = np.asarray(E2539_GEOMETRIES, float)
ROOT = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


def _tool(*args):
    return subprocess.run([sys.executable, str(ROOT / "tools" / args[0]), *map(str, args[1:])],
                          capture_output=True, text=True, cwd=ROOT, env=ENV)
DIMS = (29, 31, 61)   # small synthetic tables (no geometry on a bin edge); the bin rules take the header's sizes


def test_in_plane_half_diff_closed_form():
    wi, wo = in_plane_directions(G)
    th, _, td, _ = half_diff(wi, wo)
    assert np.allclose(np.degrees(th), np.abs(G[:, 1]) / 2, atol=1e-9)
    assert np.allclose(np.degrees(td), np.abs(G[:, 0] - G[:, 1] / 2), atol=1e-9)
    # the detector is on the light's side exactly when θ_v = θ_i − γ < 0
    assert np.array_equal(wo[:, 0] > 0, G[:, 0] - G[:, 1] < 0)


def test_half_diff_inverts():
    # rotating d back (θ_h about y, φ_h about z) gives ω_i; the standard's reciprocity: swapping ω_i, ω_o
    # keeps θ_h, θ_d and moves φ_d by π
    rng = np.random.default_rng(3)
    t = rng.uniform(0, np.pi / 2 * 0.98, (200, 2))
    p = rng.uniform(-np.pi, np.pi, (200, 2))
    w = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)
    th, ph, td, pd = half_diff(w[:, 0], w[:, 1])
    d = np.stack([np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], axis=-1)
    x = np.cos(th) * d[:, 0] + np.sin(th) * d[:, 2]
    z = -np.sin(th) * d[:, 0] + np.cos(th) * d[:, 2]
    wi = np.stack([np.cos(ph) * x - np.sin(ph) * d[:, 1], np.sin(ph) * x + np.cos(ph) * d[:, 1], z], axis=-1)
    assert np.allclose(wi, w[:, 0], atol=1e-9)
    th2, _, td2, pd2 = half_diff(w[:, 1], w[:, 0])
    assert np.allclose(th2, th) and np.allclose(td2, td)
    assert np.allclose(np.mod(pd2 - pd, 2 * np.pi), np.pi, atol=1e-9)


def test_bins_match_the_reference_rules():
    # MERL's 90/90/180 table: θ_h = 7.5° (45as-15) is bin ⌊√(7.5/90)·90⌋ = 25; θ_d 52.5° bin 52; φ_d −π/4 folds
    # by reciprocity to 3π/4, bin 135 (not |φ_d|, bin 45)
    ih, idd, ip = merl_bins(np.radians(7.5), np.radians(52.5), -np.pi / 4, MERL_DIMS)
    assert (int(ih), int(idd), int(ip)) == (25, 52, 135)
    assert tuple(int(v) for v in merl_bins(np.pi, np.pi, np.pi - 1e-12, MERL_DIMS)) == (89, 89, 179)


def _table(f):
    """A synthetic table f(θ_h, θ_d, φ_d) (3, *DIMS) evaluated at each bin's lower edge."""
    nh, nd, nphi = DIMS
    th = (np.arange(nh) / nh) ** 2 * np.pi / 2
    td = np.arange(nd) / nd * np.pi / 2
    pd = np.arange(nphi) / nphi * np.pi
    T, D, P = np.meshgrid(th, td, pd, indexing="ij")
    return f(T, D, P), (th, td, pd)


def test_lambertian_file_reads_its_albedo(tmp_path):
    rho = np.array([0.8, 0.5, 0.2])
    table = np.broadcast_to(rho[:, None, None, None] / np.pi, (3, *DIMS)).copy()
    write_merl(tmp_path / "lambert.binary", table)
    raw = np.fromfile(tmp_path / "lambert.binary", dtype="<f8", offset=12).reshape(3, -1)
    assert np.allclose(raw[:, 0] * MERL_SCALE, rho / np.pi)       # stored unscaled, channel by channel
    R, lab = merl_target(read_merl(tmp_path / "lambert.binary"), G)
    assert np.allclose(R, rho, rtol=1e-12)
    assert np.allclose(lab, merl_rgb_to_lab(rho)[None], atol=1e-9)


def test_lobe_is_read_at_each_geometrys_bin(tmp_path):
    # channel-distinct functions of all three angles: each geometry must return the value of the bin its
    # closed-form angles fall in
    def f(T, D, P):
        return np.stack([np.exp(-(T / 0.15) ** 2) + 0.01 * np.cos(D),
                         0.3 * np.cos(T) + 0.1 * D,
                         0.05 + 0.02 * np.cos(P) + 0.01 * T])
    table, (th, td, pd) = _table(f)
    write_merl(tmp_path / "lobe.binary", table)
    R, _ = merl_target(read_merl(tmp_path / "lobe.binary"), G)
    t_h, t_d = np.radians(np.abs(G[:, 1]) / 2), np.radians(np.abs(G[:, 0] - G[:, 1] / 2))
    ih = np.minimum(np.floor(np.sqrt(t_h / (np.pi / 2)) * DIMS[0]), DIMS[0] - 1).astype(int)
    idd = np.minimum(np.floor(t_d / (np.pi / 2) * DIMS[1]), DIMS[1] - 1).astype(int)
    wi, wo = in_plane_directions(G)
    th_, _, td_, pd_ = half_diff(wi, wo)
    ip = merl_bins(th_, td_, pd_, DIMS)[2]             # in-plane φ_d is 0 or ±π: the fold puts it at an end
    assert set(ip.tolist()) <= {0, DIMS[2] - 1}
    expect = np.pi * f(th[ih], td[idd], pd[ip]).T
    assert np.allclose(R, expect, rtol=1e-12)


def test_unmeasured_bins_are_nan(tmp_path):
    table = np.full((3, *DIMS), 0.1)
    table[:, 0] = -1.0   # θ_h bin 0 (θ_h < 0.107°) not measured
    write_merl(tmp_path / "hole.binary", table)
    R, lab = merl_target(read_merl(tmp_path / "hole.binary"), np.array([[45.0, 0.1], [45.0, 45.0]]))
    assert np.isnan(R[0]).all() and np.isfinite(R[1]).all()


def test_srgb_reading_published_values():
    # IEC 61966-2-1 primaries in CIELAB (D65, 2°): red (53.24, 80.09, 67.20), green (87.73, −86.18, 83.18),
    # blue (32.30, 79.19, −107.86) (B. Lindbloom's sRGB table, to its 2 decimals)
    lab = merl_rgb_to_lab(np.eye(3))
    assert np.allclose(lab, [[53.24, 80.09, 67.20], [87.73, -86.18, 83.18], [32.30, 79.19, -107.86]], atol=0.01)
    grey = merl_rgb_to_lab(np.full(3, 0.2))
    assert abs(grey[1]) < 1e-3 and abs(grey[2]) < 1e-3
    assert abs(grey[0] - (116 * 0.2 ** (1 / 3) - 16)) < 1e-3


def test_truncated_file_refused(tmp_path):
    write_merl(tmp_path / "x.binary", np.full((3, *DIMS), 0.1))
    data = (tmp_path / "x.binary").read_bytes()
    (tmp_path / "y.binary").write_bytes(data[:-8])
    with pytest.raises(MerlError, match="truncated"):
        read_merl(tmp_path / "y.binary")
    (tmp_path / "z.binary").write_bytes(b"\x00" * 40)
    with pytest.raises(MerlError, match="not a MERL"):
        read_merl(tmp_path / "z.binary")


def test_tool_writes_a_target_that_reads_back(tmp_path):
    table, _ = _table(lambda T, D, P: np.stack([0.4 + 0 * T, 0.3 + 0.1 * np.cos(T), 0.2 + 0 * D]))
    write_merl(tmp_path / "paint.binary", table)
    r = _tool("merl_target.py", tmp_path / "out", tmp_path / "paint.binary")
    assert r.returncode == 0, r.stderr
    t = read_target(tmp_path / "out" / "paint.csv")
    assert t.name == "paint" and np.allclose(t.geometries, G)
    _, lab = merl_target(table, G)
    assert np.allclose(t.lab_under(observer="2", illuminant="D65"), lab, atol=1e-5)
    bad = _tool("merl_target.py", tmp_path / "out", tmp_path / "nothere")
    assert bad.returncode == 2 and "nothere" in bad.stderr and "Traceback" not in bad.stderr


def _as_measured(tmp_path, doc, dims=MERL_DIMS):
    """A MERL file whose in-plane bins at the E2539 geometries hold ``doc``'s prediction as a camera calibrated
    to a white standard would record it: white-normalised linear sRGB (CIE 1931 / D65 on the recipe's grid,
    flakedb's RGB mode) over π; every other bin unmeasured (−1)."""
    from flakedb.colour.colorimetry import spectra_to_rgb_mode
    from flakedb.match.fit import predict, recipe_from_doc

    pred = predict(recipe_from_doc(doc), G, n=16)
    rgb = spectra_to_rgb_mode(pred.rf, pred.wavelength_nm)
    table = np.full((3, *dims), -1.0)
    wi, wo = in_plane_directions(G)
    th, _, td, pd = half_diff(wi, wo)
    ih, idd, ip = merl_bins(th, td, pd, dims)
    assert len(set(zip(ih, idd, ip))) == len(G)          # one bin per geometry
    table[:, ih, idd, ip] = rgb.T / np.pi
    write_merl(tmp_path / "silver-synthetic.binary", table)
    return tmp_path / "silver-synthetic.binary", pred.lab("2", "D65")


@pytest.mark.slow
def test_measured_file_to_match_round_trip(tmp_path):
    # the whole validation chain on a paint whose truth is known: recipe -> (sRGB) -> MERL file -> target ->
    # match from a loading 2x off.  The sRGB reading of the file gives the recipe's own CIELAB back (white-
    # normalising in RGB vs in XYZ: < 0.05 ΔE00 on this near-neutral paint), and the fit recovers the loading.
    import yaml
    from flakedb.colour.tolerance import delta_E_2000
    from flakedb.match.fit import match
    from flakedb.match.targets import write_target

    doc = yaml.safe_load(open(ROOT / "tools" / "validation" / "silver.yaml", encoding="utf-8"))
    p = doc["layers"][1]["basecoat"]["particles"][0]
    truth = dict(p, volume_fraction=0.06, orientation_alpha=0.12, orientation_shape=4.0)
    doc["layers"][1]["basecoat"]["particles"][0] = truth
    doc["layers"][2]["primer"] = {"albedo": 0.18}
    path, lab_true = _as_measured(tmp_path, doc)
    _, lab = merl_target(read_merl(path), G)
    assert np.max(delta_E_2000(lab_true, lab)) < 0.05
    base = yaml.safe_load(yaml.safe_dump(doc))
    base["layers"][1]["basecoat"]["particles"][0]["volume_fraction"] = {"fit": [0.02, 0.2], "start": 0.12}
    target = read_target(write_target(tmp_path / "t.csv", G, lab=lab, observer="2", illuminant="D65", name="s"))
    res = match(base, target, n=16)
    assert abs(res.values[0] / 0.06 - 1) < 0.02
    assert res.de_fit.max() < 0.1 < res.de_start.max()


def test_validation_tool_names_what_it_cannot_attempt(tmp_path):
    # a kind with no colourant in the catalogue is reported with its reason, not fitted with a stand-in
    write_merl(tmp_path / "red-metallic-paint.binary", np.full((3, *DIMS), 0.1))
    r = _tool("validate_measured.py", tmp_path / "o", tmp_path / "red-metallic-paint.binary")
    assert r.returncode == 0, r.stderr
    assert "not attempted: no red-metallic base" in r.stdout
    assert not (tmp_path / "o" / "red-metallic-paint.csv").exists()


def test_validate_measured_start_names_a_free_parameter(tmp_path):
    # --start sets a free parameter's start by the last part of its path; an unknown one is refused, naming the
    # base's free parameters, before anything is written (exit 2)
    r = _tool("validate_measured.py", tmp_path / "out",
              ROOT / "tools" / "validation" / "targets" / "cc_ibiza_sunset_rgb.csv", "--start", "spacer_nm=300")
    assert r.returncode == 2
    assert "--start spacer_nm: not a free parameter of colour-shift-fabry-perot.yaml" in r.stderr
    assert "coating_thickness_nm[1]" in r.stderr
    assert not (tmp_path / "out").exists()
