"""RGL measured BRDFs (tensor_file, powitacq parameterisation) read at instrument geometries (flakedb.match.rgl).

Guards against: a tensor_file field read at the wrong offset, shape or dtype; a truncated file (or a Git LFS
pointer) read as data; a wrong VNDF inversion (marginal/conditional order, the within-cell quadratic, the
trapezoidal CDFs) or a swapped unit-square axis; a wrong factor in f_r cos θ_o = R D / (4 σ) or a missing
1/cos θ_o; interpolation between θ_i slices that is not linear; a target that does not read back.  The
synthetic files have closed forms independent of the code: a bilinear VNDF density p ∝ (1 + x)(1 + 2y) inverts
to s_x = (u_x + u_x²/2)/1.5, s_y = (u_y + u_y²)/2, and linear tables interpolate exactly.

With the RGL database's files at hand (FLAKEDB_RGL_DIR, e.g. the car paints ``ilm_l3_37_metallic_rgb.bsdf``),
the reader is also checked against values of the reference implementation (rgl-epfl/brdf-loader
``powitacq_rgb::BRDF::eval``, compiled and run on the same file), against reciprocity (the table is sliced by
θ_i only, so f_r(a, b) = f_r(b, a) is a property of the data, not of the code) and against the file's own
luminance field (the sRGB Y of its rgb field).
"""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flakedb.match.measured import MeasuredError, measured_target
from flakedb.match.merl import in_plane_directions
from flakedb.match.rgl import (
    RglError,
    read_rgl,
    read_tensor_file,
    rgl_brdf,
    rgl_target,
    write_tensor_file,
)
from flakedb.match.targets import E2539_GEOMETRIES, read_target

G = np.asarray(E2539_GEOMETRIES, float)
ROOT = Path(__file__).resolve().parents[2]
THETA_I = np.radians([0.0, 30.0, 55.0, 90.0]).astype(np.float32)
RGB_COEF = np.array([[0.2, 0.3, -0.1], [0.5, -0.2, 0.1], [0.1, 0.05, 0.3]])   # R_c = a + b s_x + c s_y


def _synthetic(path, rows=9, cols=11, nm=33, wavelengths_nm=None):
    """An isotropic RGL-layout file with closed-form tables: ndf D = 1 + u_θ + 0.5 u_φ, σ = 2 + u_θ, VNDF density
    (1 + x)(1 + 2y) in every slice, R_c(s; θ_i) = (a_c + b_c s_x + c_c s_y)(1 + θ_i)."""
    ut, up = np.meshgrid(np.linspace(0, 1, nm), np.linspace(0, 1, 2))
    x, y = np.meshgrid(np.linspace(0, 1, cols), np.linspace(0, 1, rows))
    vndf = np.broadcast_to((1 + x) * (1 + 2 * y), (1, THETA_I.size, rows, cols))
    sx, sy = np.meshgrid(np.linspace(0, 1, 32), np.linspace(0, 1, 32))
    R = np.stack([a + b * sx + c * sy for a, b, c in RGB_COEF])
    rgb = R[None, None] * (1 + THETA_I.astype(float))[None, :, None, None, None]
    f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)
    chan = {"rgb": f32(rgb)}
    if wavelengths_nm is not None:   # spectra: channel 0's pattern times a spectrum linear in λ
        spec = 0.2 + 0.0005 * (np.asarray(wavelengths_nm) - 360.0)
        chan = {"wavelengths": f32(wavelengths_nm), "spectra": f32(rgb[:, :, :1] * spec[None, None, :, None, None])}
    write_tensor_file(path, {
        "version": np.array([1, 0], np.uint8), "description": np.frombuffer(b"synthetic", np.uint8),
        "phi_i": np.zeros(1, np.float32), "theta_i": THETA_I,
        "sigma": f32(2 + ut), "ndf": f32(1 + ut + 0.5 * up), "vndf": f32(vndf),
        "luminance": f32(np.einsum("c,ptcij->ptij", [0.2126729, 0.7151522, 0.0721750], rgb)),
        **chan, "jacobian": np.ones(1, np.uint8)})
    return path


def _dirs(rng, n, tmax=80.0):
    t = rng.uniform(0, np.radians(tmax), n)
    p = rng.uniform(-np.pi, np.pi, n)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def test_tensor_file_round_trip(tmp_path):
    fields = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array([7], np.uint8),
              "c": np.linspace(0, 1, 5), "d": np.arange(4, dtype=np.int64).reshape(2, 2, 1)}
    write_tensor_file(tmp_path / "t.bsdf", fields)
    raw = (tmp_path / "t.bsdf").read_bytes()
    assert raw[:12] == b"tensor_file\0" and raw[12:14] == b"\x01\x00"
    back = read_tensor_file(tmp_path / "t.bsdf")
    assert list(back) == list(fields)
    for k, v in fields.items():
        assert back[k].dtype == v.dtype and back[k].shape == v.shape and np.array_equal(back[k], v)


def test_truncated_or_foreign_files_refused(tmp_path):
    path = _synthetic(tmp_path / "s.bsdf")
    raw = path.read_bytes()
    (tmp_path / "cut.bsdf").write_bytes(raw[:-100])
    with pytest.raises(RglError, match="runs past"):
        read_tensor_file(tmp_path / "cut.bsdf")
    (tmp_path / "lfs.bsdf").write_text("version https://git-lfs.github.com/spec/v1\noid sha256:00\nsize 658952\n")
    with pytest.raises(RglError, match="not a tensor_file"):
        read_rgl(tmp_path / "lfs.bsdf")
    with pytest.raises(MeasuredError, match="unknown measured-BRDF suffix '.brdf'"):
        measured_target(tmp_path / "x.brdf", G)


def test_synthetic_file_closed_form(tmp_path):
    b = read_rgl(_synthetic(tmp_path / "s.bsdf"))
    rng = np.random.default_rng(5)
    wi, wo = _dirs(rng, 400), _dirs(rng, 400)
    f = rgl_brdf(b, wi, wo, clip=False)
    # independent construction of the unit-square coordinates and of the VNDF inverse
    wm = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    th_i, ph_i = np.arccos(wi[:, 2]), np.arctan2(wi[:, 1], wi[:, 0])
    th_m, ph_m = np.arccos(wm[:, 2]), np.arctan2(wm[:, 1], wm[:, 0])
    ux, uy = np.sqrt(2 * th_m / np.pi), np.mod((ph_m - ph_i + np.pi) / (2 * np.pi), 1.0)
    sx, sy = (ux + ux ** 2 / 2) / 1.5, (uy + uy ** 2) / 2
    R = (RGB_COEF[:, 0] + np.outer(sx, RGB_COEF[:, 1]) + np.outer(sy, RGB_COEF[:, 2])) * (1 + th_i)[:, None]
    # θ_i interpolation is linear between slices, and R is linear in θ_i: exact
    D, sig = 1 + ux + 0.5 * uy, 2 + np.sqrt(2 * th_i / np.pi)
    expect = R * (D / (4 * sig * wo[:, 2]))[:, None]
    assert np.allclose(f, expect, rtol=2e-6, atol=1e-7)   # float32 tables
    below = wo.copy()
    below[:, 2] *= -1
    assert np.all(rgl_brdf(b, wi, below) == 0)


def test_spectral_file_gives_a_spectral_target(tmp_path):
    # the database's 195-bin grid; a spectrum linear in λ is resampled exactly onto 380-780 nm; the geometry
    # factor is the RGB test's channel 0 (closed form there), so R(λ) / R(λ0) is the spectrum's ratio
    wl = np.linspace(358.63, 1001.89, 195)
    path = _synthetic(tmp_path / "s_spec.bsdf", wavelengths_nm=wl)
    m = measured_target(path, G)
    assert m.lab is None and np.allclose(m.wavelength_nm, np.arange(380, 781, 5))
    rgb_like = rgl_brdf(read_rgl(_synthetic(tmp_path / "s_rgb.bsdf")), *in_plane_directions(G), clip=False)[:, 0]
    spec = 0.2 + 0.0005 * (m.wavelength_nm - 360.0)
    assert np.allclose(m.reflectance, np.pi * rgb_like[:, None] * spec[None], rtol=1e-5)
    with pytest.raises(RglError, match="spectral file"):
        rgl_target(read_rgl(path), G)


def test_tool_writes_rgl_target_that_reads_back(tmp_path):
    path = _synthetic(tmp_path / "paint_rgb.bsdf")
    r = subprocess.run([sys.executable, str(ROOT / "tools" / "merl_target.py"), str(tmp_path / "out"), str(path)],
                       capture_output=True, text=True, cwd=ROOT,
                       env=dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])))
    assert r.returncode == 0, r.stderr
    t = read_target(tmp_path / "out" / "paint_rgb.csv")
    _, lab = rgl_target(read_rgl(path), G)
    assert np.allclose(t.lab_under(observer="2", illuminant="D65"), lab, atol=1e-5)
    assert "CC0" in t.notes.get("licence", "")


# --------------------------------------------------------------------------------------------------------
# The database's own files (not in the repository: give FLAKEDB_RGL_DIR)
# --------------------------------------------------------------------------------------------------------
RGL_DIR = Path(os.environ.get("FLAKEDB_RGL_DIR", ROOT / "no-rgl-dir"))
SILVER = RGL_DIR / "ilm_l3_37_metallic_rgb.bsdf"
SILVER_SHA256 = "5a6a5ed609d718f4fd752038fa091644c13d23816994a0bfbd6fad505e7c2fa6"
needs_silver = pytest.mark.skipif(not SILVER.exists(), reason="FLAKEDB_RGL_DIR has no ilm_l3_37_metallic_rgb.bsdf")
#: powitacq_rgb::BRDF::eval (f_r cos θ_o, float32) on the silver file at the E2539 geometries (in order) and at
#: five random direction pairs (below), from the reference code built from rgl-epfl/brdf-loader (BSD-3)
REF_SILVER = np.array([
    [4.4326529e-01, 4.4525376e-01, 4.2920968e-01], [6.2068945e-01, 6.2146241e-01, 5.9861070e-01],
    [2.5216571e-01, 2.5844109e-01, 2.5259408e-01], [4.3121997e-02, 4.4665597e-02, 4.4838551e-02],
    [5.0672544e-03, 5.2407454e-03, 5.2365917e-03], [2.5916594e-04, 2.6800326e-04, 2.6767253e-04],
    [3.0145079e-02, 3.0956522e-02, 3.0578902e-02], [4.7710419e-01, 4.8000193e-01, 4.6502179e-01],
    [5.3958517e-01, 5.3963041e-01, 5.1947975e-01], [2.7523775e-02, 2.8560907e-02, 2.8697262e-02],
    [1.9959579e-03, 2.0693741e-03, 2.0774675e-03], [1.3136837e-04, 1.3575306e-04, 1.3524406e-04],
    [1.2578270e-02, 1.2983317e-02, 1.2803923e-02], [1.0014877e-03, 1.0374918e-03, 1.0406961e-03],
    [4.8501752e-03, 5.0182124e-03, 5.0110593e-03], [5.6879278e-02, 5.8708869e-02, 5.7713777e-02]])
REF_WI = [[0.25058627128601074, -0.723990261554718, 0.6426854729652405],
          [0.0270246472209692, -0.8829832077026367, 0.4686260223388672],
          [0.4067825675010681, 0.011628016829490662, 0.9134510159492493],
          [-0.0073487479239702225, 0.0002078232355415821, 0.9999729990959167],
          [0.6454108953475952, 0.6229292154312134, 0.4420451819896698]]
REF_WO = [[0.16874542832374573, -0.9347377419471741, 0.31271451711654663],
          [0.29105719923973083, -0.10462943464517593, 0.9509670734405518],
          [0.8864505887031555, 0.309719443321228, 0.3439173996448517],
          [-0.24138572812080383, 0.8788437247276306, 0.41154181957244873],
          [-0.6063963770866394, 0.042130544781684875, 0.794045627117157]]


@needs_silver
def test_silver_against_reference_implementation():
    assert hashlib.sha256(SILVER.read_bytes()).hexdigest() == SILVER_SHA256
    wi, wo = in_plane_directions(G)
    a = np.vstack([wi.astype(np.float32).astype(float), REF_WI])
    c = np.vstack([wo.astype(np.float32).astype(float), REF_WO])
    f_cos = rgl_brdf(read_rgl(SILVER), a, c) * c[:, 2:3]
    # float32 reference against float64 here: relative 1e-4 covers its rounding through ~30 operations
    assert np.allclose(f_cos, REF_SILVER, rtol=1e-4, atol=0)


@needs_silver
def test_silver_is_reciprocal_and_its_luminance_is_srgb_y():
    b = read_rgl(SILVER)
    rng = np.random.default_rng(11)
    x, y = _dirs(rng, 2000, 75.0), _dirs(rng, 2000, 75.0)
    f1, f2 = rgl_brdf(b, x, y).sum(1), rgl_brdf(b, y, x).sum(1)
    # measured data, sliced by θ_i only: reciprocal to ~15 % (median |ln ratio| 0.137 measured on this file), while
    # the other reading of eval (f_r cos θ_i, so f_r = eval / cos θ_i) breaks it by (cos θ_o / cos θ_i)² (0.634)
    rec = np.median(np.abs(np.log(f1 / f2)))
    alt = np.median(np.abs(np.log(f1 * y[:, 2] ** 2 / (f2 * x[:, 2] ** 2))))
    assert rec < 0.2 and alt > 3 * rec
    f = read_tensor_file(SILVER)
    lum = np.einsum("c,ptcij->ptij", [0.2126729, 0.7151522, 0.0721750], f["rgb"].astype(float))
    assert np.allclose(lum, f["luminance"], rtol=1e-5, atol=1e-6 * f["luminance"].max())


TARGETS = sorted((ROOT / "tools" / "validation" / "targets").glob("*.csv"))


@pytest.mark.parametrize("csv", TARGETS, ids=[p.stem for p in TARGETS])
def test_shipped_targets_are_the_files_read(csv):
    # every shipped target names its source and CC0 licence; with the database's file at hand it is that file
    # read by this code (to the CSV's 6 decimals)
    t = read_target(csv)
    assert np.allclose(t.geometries, G) and "RGL material database" in t.notes["source"]
    assert "CC0" in t.notes["licence"]
    f = RGL_DIR / f"{csv.stem}.bsdf"
    if f.exists():
        assert np.allclose(t.lab_under(observer="2", illuminant="D65"), measured_target(f, G).lab, atol=2e-6)
