"""The preview renderer (flakedb.render.preview), its image writers (flakedb.render.imageio) and `flakedb render`.

Bugs these tests guard against:
- the wrong renderer mapping to the file (mu_i from the wrong vector, mu_o's sign, phi_d = φ_o - φ_i
  instead of π - (φ_o - φ_i), a mirrored azimuth): the furnace test compares every pixel's view
  angle with the file's own albedo, and a sun test on a table that depends on phi_d compares each
  pixel with the file evaluated at independently computed (mu_i, mu_o, phi_d);
- a biased estimator: BSDF-sample weights used wrongly, transmitted samples counted as
  reflection, MIS weights that do not sum to one (the sun counted twice or not at all), the disk
  light's pdf or irradiance wrong (closed form E cos θ albedo/π for a Lambertian table);
- the smooth coat's delta term missing, sampled instead of added exactly, with the wrong Fresnel
  angle or index, or blind to the sun in the mirror direction (exact per-pixel comparison);
- background pixels that are not the environment exactly; an image that depends on the number of
  threads;
- EXR files that do not round-trip float32, PNGs of the wrong size or encoding, temporary files left
  behind; `flakedb render` exiting 0 or writing files for an unreadable input.
"""

import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.bsdf import BSDFTable, open_bsdf, write_bsdf, write_h5
from flakedb.bsdf.convert import stack_to_table
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render import preview
from flakedb.render.imageio import read_exr, srgb_encode, to_srgb8, write_exr, write_png

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data" / "bsdf-files"   # CI: the shared folder beside the checkout
ENV_L = 0.5                                              # renderers.md's furnace radiance


def _data_file(name):
    p = DATA / name
    if not p.exists():
        pytest.skip(f"{p} is absent: the shared reference data sits beside the repository as ../shared")
    return p


def _pixel_centres(size, extent=preview.DEFAULT_EXTENT):
    """Independent geometry: (sphere mask, normals (size, size, 3)) at the pixel centres of an
    orthographic view of [-extent, extent]², row 0 at the top, camera on +z."""
    c = (np.arange(size) + 0.5) * (2.0 * extent / size)
    x, y = np.meshgrid(-extent + c, extent - c)
    r2 = x * x + y * y
    mask = r2 < 1.0
    n = np.stack([x, y, np.sqrt(np.maximum(1.0 - r2, 0.0))], axis=-1)
    return mask, n


def _nodes(h=32):
    x = np.linspace(0.0, 1.0, h + 1)[1:]
    return np.concatenate([-x[::-1], x])


def _reflection_table(value, h=32, orders=1, channels=3, **kw):
    """A table whose reflection entries (mu_i > 0, mu_o < 0) have coefficients value(|mu_o|) (C, L)."""
    mu = _nodes(h)
    coeffs = np.zeros((channels, 2 * h, 2 * h, orders))
    for i in range(h, 2 * h):
        for o in range(h):
            coeffs[:, i, o, :] = value(abs(mu[o]))
    return BSDFTable(mu=mu, coeffs=coeffs, **kw)


def _lambertian(path, albedo=(0.8, 0.5, 0.2)):
    """f·|mu_o| = albedo/π · |mu_o| (exact under the file's Catmull-Rom interpolation in mu_o)."""
    a = np.asarray(albedo)[:, None]
    write_bsdf(path, _reflection_table(lambda m: a / np.pi * m))
    return open_bsdf(path)


def _smooth_coated_h5(path):
    """A smooth-coated paint composed by flakedb's solver (delta term {"fresnel", 1.5})."""
    from flakedb.rt.scattering.media import PhaseMedium
    from flakedb.rt.adding.stack import Lambertian, Slab, Smooth, SolverSettings, solve_stack

    med = PhaseMedium(sigma_t_per_um=[0.3, 0.3, 0.3], albedo=[0.95, 0.45, 0.15], phase=("hg", 0.5))
    s = solve_stack(Smooth(1.5), [Slab(10.0, med)], Lambertian([0.8, 0.8, 0.8]), SolverSettings(n=32))
    write_h5(path, stack_to_table(s, metadata={"recipe": "test smooth red"}))
    return open_bsdf(path)


# --------------------------------------------------------------------------------------------
# (1) the furnace: constant environment 0.5, no sun
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", ["coated_diffuse_mono_n200", "carpaint_rgb_n100", "lambertian", "smooth_coated"])
def test_furnace_matches_the_files_albedo(case, tmp_path):
    if case == "lambertian":
        b, exact = _lambertian(tmp_path / "lambert.bsdf"), True
    elif case == "smooth_coated":
        b, exact = _smooth_coated_h5(tmp_path / "smooth.h5"), False
        assert b.delta == {"kind": "fresnel", "eta": 1.5}
    else:
        b, exact = open_bsdf(_data_file(case + ".bsdf")), case.endswith("mono_n200")
    size = 64
    r = preview.render_sphere(b, preview.constant_environment(ENV_L), None, size=size, spp=8,
                              jitter=False, seed=3)
    mask, n = _pixel_centres(size)
    mu_i = n[..., 2][mask]
    expected = ENV_L * b.albedo(mu_i)
    if b.delta is not None:
        expected = expected + ENV_L * fresnel_dielectric(mu_i, b.delta["eta"]).R[:, None]
    img = r.image.astype(np.float64)
    assert np.all(r.image[~mask] == np.float32(ENV_L)), "background must be the environment exactly"
    np.testing.assert_array_equal(r.coverage, mask.astype(np.float32))
    got, want = img[mask].mean(axis=0), expected.mean(axis=0)
    np.testing.assert_allclose(got, want, rtol=0.01)
    if exact:  # one sampled channel: every sample's weight is the albedo, so each pixel is exact
        np.testing.assert_allclose(img[mask], expected, rtol=1e-4, atol=1e-6)


def test_jittered_furnace_is_bounded_and_antialiased(tmp_path):
    """With jittered pixel positions the edge pixels blend sphere and background (coverage strictly
    between 0 and 1), and no pixel leaves [0, L · max albedo] (a white Lambertian table)."""
    b = _lambertian(tmp_path / "lambert.bsdf", albedo=(1.0, 1.0, 1.0))
    top = ENV_L * b.albedo(np.linspace(0.0, 1.0, 20001)).max()   # Catmull-Rom overshoot near mu = 0
    r = preview.render_sphere(b, preview.constant_environment(ENV_L), None, size=32, spp=4, seed=1)
    assert np.all(r.image <= top * (1 + 1e-6)) and np.all(r.image >= 0)
    edge = (r.coverage > 0) & (r.coverage < 1)
    assert edge.sum() > 20
    mask, n = _pixel_centres(32)
    centre = mask & (n[..., 2] > 0.5)      # far from the edge and from grazing: the albedo is 1
    np.testing.assert_allclose(r.image[centre], ENV_L, rtol=1e-5)


# --------------------------------------------------------------------------------------------
# (2) a sun only: closed form, and the phi_d convention
# --------------------------------------------------------------------------------------------
def _sun_only(b, sun, size, spp):
    return preview.render_sphere(b, preview.constant_environment(0.0), sun, size=size, spp=spp,
                                 jitter=False, seed=5)


def test_lambertian_under_a_sun_is_albedo_over_pi_E_cos(tmp_path):
    """A disk fully above the local horizon gives irradiance E cos θ_c exactly (projected solid
    angle of a cap: π sin²α cos θ_c), so the pixel is albedo(mu_i)/π · E · cos θ_c.  Each sample
    lies within cos θ_c ± sin θ_c sin α (the disk's extent), which bounds every pixel; the mean
    relative error over all lit pixels must vanish (no bias)."""
    b = _lambertian(tmp_path / "lambert.bsdf")
    E = 2.0
    sun = preview.Sun.from_irradiance((0.3, 0.5, 0.8), E, half_angle_deg=0.5)
    np.testing.assert_allclose(sun.irradiance, E, rtol=1e-12)
    size = 48
    r = _sun_only(b, sun, size, spp=16)
    mask, n = _pixel_centres(size)
    cos_sun = n @ np.asarray(sun.direction)
    sin_a = np.sin(np.radians(sun.half_angle_deg))
    lit = mask & (cos_sun > sin_a + 1e-3)            # the whole disk above the local horizon
    dark = mask & (cos_sun < -sin_a - 1e-3)
    assert lit.sum() > 300 and dark.sum() > 100
    c = cos_sun[lit]
    expected = b.albedo(n[..., 2][lit]) / np.pi * E * c[:, None]
    rel = r.image[lit] / expected - 1.0
    bound = 1.1 * np.sqrt(1 - c * c) / c * sin_a + 1e-5
    assert np.all(np.abs(rel) <= bound[:, None]), np.max(np.abs(rel) / bound[:, None])
    assert abs(rel.mean()) < 1e-4
    assert np.all(r.image[dark] == 0)
    assert np.all(r.image[~mask] == 0)


def test_phi_convention_under_a_sun(tmp_path):
    """f·|mu_o| = A |mu_o| (1 + cos phi_d): bright towards the mirror direction (phi_d = 0), dark
    towards retro-reflection.  Each pixel must equal ∫ f·|mu_o| L dω over the disk, computed here
    by a fixed quadrature with (mu_i, mu_o, phi_d) built from vectors only (no frames)."""
    A = 0.25
    write_bsdf(tmp_path / "fwd.bsdf", _reflection_table(lambda m: np.full((3, 2), A * m), orders=2))
    b = open_bsdf(tmp_path / "fwd.bsdf")
    L = 100.0
    sun = preview.Sun((-0.2, 0.4, 0.9), radiance=L, half_angle_deg=0.25)
    size = 40
    r = _sun_only(b, sun, size, spp=16)
    mask, n = _pixel_centres(size)
    v = np.array([0.0, 0.0, 1.0])
    mu_i = n[..., 2]
    v_t = v - mu_i[..., None] * n
    l_t = np.asarray(sun.direction) - (n @ np.asarray(sun.direction))[..., None] * n
    # away from where phi_d is undefined (normal along the view or the sun): there it turns fast
    # across the disk and the sampled value is noisy
    ok = (mask & (n @ np.asarray(sun.direction) > 0.05) & (np.linalg.norm(v_t, axis=-1) > 0.1)
          & (np.linalg.norm(l_t, axis=-1) > 0.1))
    # equal-solid-angle quadrature of the disk: 8 rings x 16 azimuths
    k, j = np.meshgrid(np.arange(8) + 0.5, np.arange(16) + 0.5, indexing="ij")
    cos_c = 1.0 - k.ravel() / 8 * sun.one_minus_cos
    sin_c = np.sqrt(1.0 - cos_c**2)
    az = 2 * np.pi * j.ravel() / 16
    s_, t_ = preview.orthonormal_basis(np.asarray(sun.direction))
    d = np.asarray(sun.direction)
    wo = (sin_c * np.cos(az))[:, None] * s_ + (sin_c * np.sin(az))[:, None] * t_ + cos_c[:, None] * d
    nn, vt = n[ok][:, None, :], v_t[ok][:, None, :]
    cos_o = np.einsum("pqk,pqk->pq", np.broadcast_to(wo, (nn.shape[0],) + wo.shape), nn)
    w_t = wo[None] - cos_o[..., None] * nn
    cos_phi = -np.einsum("pqk,pqk->pq", vt, w_t) / (np.linalg.norm(vt, axis=-1) * np.linalg.norm(w_t, axis=-1))
    phi_d = np.arccos(np.clip(cos_phi, -1.0, 1.0))
    f = b.eval(np.broadcast_to(mu_i[ok][:, None], cos_o.shape), -cos_o, phi_d)      # (P, Q, 3)
    expected = f.mean(axis=1) * L * sun.solid_angle
    assert expected[:, 0].max() > 5 * expected[:, 0].min()          # the lobe is really there
    np.testing.assert_allclose(r.image[ok], expected, rtol=2e-3, atol=1e-3 * expected.max())
    # the flipped convention (phi_d -> π - phi_d) would be far off
    flipped = b.eval(mu_i[ok], -(n[ok] @ np.asarray(sun.direction)), np.pi - phi_d[:, 0])
    assert np.max(np.abs(flipped * L * sun.solid_angle - r.image[ok])) > 0.3 * expected.max()


def _phi_d(v, n, wo):
    """phi_d of the file from vectors only: cos phi_d = -(v_t · wo_t) / (|v_t| |wo_t|) with the
    tangential parts v_t, wo_t of the view and light directions (conventions: 0 = mirror)."""
    v_t = v - np.sum(v * n, axis=-1, keepdims=True) * n
    w_t = wo - np.sum(wo * n, axis=-1, keepdims=True) * n
    c = -np.sum(v_t * w_t, axis=-1) / (np.linalg.norm(v_t, axis=-1) * np.linalg.norm(w_t, axis=-1))
    return np.arccos(np.clip(c, -1.0, 1.0))


def test_bsdf_sampled_directions_under_the_studio_env(tmp_path):
    """BSDF sampling alone (no sun) under the non-uniform studio environment, for a lobe towards
    the mirror direction, f·|mu_o| = A |mu_o| (1 + cos phi_d)²: each pixel must match a brute-force
    quadrature of ∫ f·|mu_o| L_env dω over the hemisphere (phi_d from vectors), while the
    quadrature with the azimuth mirrored (phi_d -> π - phi_d) must not."""
    A = 0.15
    write_bsdf(tmp_path / "lobe.bsdf", _reflection_table(lambda m: A * m * np.array([[1.5, 2.0, 0.5]] * 3), orders=3))
    b = open_bsdf(tmp_path / "lobe.bsdf")
    env = preview.Environment(kind="studio", horizon_blur=0.6)    # smooth: quadrature-friendly
    size = 16
    r = preview.render_sphere(b, env, None, size=size, spp=256, jitter=False, seed=2)
    mask, n = _pixel_centres(size)
    sel = mask & (n[..., 2] > 0.2) & (np.hypot(n[..., 0], n[..., 1]) > 0.15)
    nn = n[sel]                                                              # (P, 3)
    # midpoint quadrature in (cos θ, φ) about each normal: dω = dcosθ dφ
    c = (np.arange(40) + 0.5) / 40
    ph = 2 * np.pi * (np.arange(80) + 0.5) / 80
    cc, pp = (a.ravel() for a in np.meshgrid(c, ph, indexing="ij"))
    s_, t_ = preview.orthonormal_basis(nn)
    sin = np.sqrt(1 - cc**2)
    wo = ((sin * np.cos(pp))[None, :, None] * s_[:, None] + (sin * np.sin(pp))[None, :, None] * t_[:, None]
          + cc[None, :, None] * nn[:, None])                                 # (P, Q, 3)
    v = np.array([0.0, 0.0, 1.0])
    phi = _phi_d(v, nn[:, None], wo)
    mu_i = np.broadcast_to(nn[:, 2:3], phi.shape)
    mu_o = -np.broadcast_to(cc, phi.shape)
    dw = 2 * np.pi / cc.size
    L = env(wo)
    expected = np.sum(b.eval(mu_i, mu_o, phi) * L, axis=1) * dw
    mirrored = np.sum(b.eval(mu_i, mu_o, np.pi - phi) * L, axis=1) * dw
    assert np.mean(np.abs(mirrored / expected - 1)) > 0.3                    # the test can tell them apart
    # per-pixel noise at 256 spp is about 1.7 % (measured seed to seed): 6 sigma per pixel, and
    # about 4 sigma for the mean over the ~170 pixels
    np.testing.assert_allclose(r.image[sel], expected, rtol=0.1)
    assert abs(np.mean(r.image[sel] / expected - 1)) < 0.005


# --------------------------------------------------------------------------------------------
# (3) the delta term alone
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fmt", ["bsdf", "h5"])
@pytest.mark.parametrize("lights", ["constant", "studio+sun"])
def test_delta_term_is_exact(fmt, lights, tmp_path):
    table = _reflection_table(lambda m: np.zeros((3, 1)), delta={"kind": "fresnel", "eta": 1.5})
    path = tmp_path / f"mirror.{fmt}"
    (write_bsdf if fmt == "bsdf" else write_h5)(path, table)
    b = open_bsdf(path)
    assert b.delta == {"kind": "fresnel", "eta": 1.5}
    size = 48
    mask, n = _pixel_centres(size)
    mu_i = n[..., 2][mask]
    F = fresnel_dielectric(mu_i, 1.5).R
    if lights == "constant":
        env, sun = preview.constant_environment(ENV_L), None
        expected = ENV_L * np.repeat(F[:, None], 3, axis=1)
    else:
        env = preview.studio_environment()
        sun = preview.Sun((-0.3, 0.5, 0.8), radiance=50.0, half_angle_deg=6.0)
        rdir = 2.0 * mu_i[:, None] * n[mask] - np.array([0.0, 0.0, 1.0])   # mirror of the view ray
        in_sun = rdir @ np.asarray(sun.direction) >= np.cos(np.radians(6.0))
        assert in_sun.sum() >= 3
        expected = F[:, None] * (env(rdir) + 50.0 * in_sun[:, None])
    r = preview.render_sphere(b, env, sun, size=size, spp=2, jitter=False)
    np.testing.assert_allclose(r.image[mask], expected, rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(fresnel_dielectric(1.0, 1.5).R, 0.04, rtol=1e-12)  # (0.5/2.5)²


def test_transmission_is_not_reflected(tmp_path):
    """A table that only transmits (mu_i > 0, mu_o > 0 entries): the sphere must be black."""
    mu = _nodes(16)
    coeffs = np.zeros((3, 32, 32, 1))
    coeffs[:, 16:, 16:, 0] = 0.9 / np.pi * mu[16:]
    write_bsdf(tmp_path / "t.bsdf", BSDFTable(mu=mu, coeffs=coeffs))
    b = open_bsdf(tmp_path / "t.bsdf")
    assert b.albedo(0.7)[0] > 0.8
    r = preview.render_sphere(b, preview.constant_environment(ENV_L), preview.studio_sun(), size=16,
                              spp=4, jitter=False)
    mask, _ = _pixel_centres(16)
    assert np.all(r.image[mask] == 0) and np.all(r.image[~mask] == np.float32(ENV_L))


def test_image_does_not_depend_on_threads(tmp_path):
    b = open_bsdf(_data_file("carpaint_rgb_n100.bsdf"))
    kw = dict(size=24, spp=3, seed=11, tile_rows=5)
    a = preview.render_sphere(b, preview.studio_environment(), preview.studio_sun(), threads=1, **kw)
    c = preview.render_sphere(b, preview.studio_environment(), preview.studio_sun(), threads=2, **kw)
    np.testing.assert_array_equal(a.image, c.image)
    d = preview.render_sphere(b, preview.studio_environment(), preview.studio_sun(), threads=2,
                              **{**kw, "seed": 12})
    assert not np.array_equal(a.image, d.image)


def test_unknown_delta_kind_is_refused(tmp_path):
    table = _reflection_table(lambda m: np.zeros((3, 1)), delta={"kind": "conductor", "eta": 1.5})
    write_h5(tmp_path / "x.h5", table)
    with pytest.raises(ValueError, match="unknown delta term"):
        preview.render_sphere(open_bsdf(tmp_path / "x.h5"), size=8, spp=1)


# --------------------------------------------------------------------------------------------
# (4) image files
# --------------------------------------------------------------------------------------------
def test_exr_round_trip_and_png(tmp_path):
    rng = np.random.default_rng(0)
    img = (rng.standard_normal((17, 23, 3)) * 10.0 ** rng.uniform(-6, 4, (17, 23, 3))).astype(np.float32)
    img[0, 0] = [0.0, 1e30, -1e-30]
    write_exr(tmp_path / "a.exr", img)
    back = read_exr(tmp_path / "a.exr")
    assert back.dtype == np.float32 and back.shape == img.shape
    np.testing.assert_array_equal(back, img)

    from PIL import Image

    lin = np.zeros((5, 7, 3))
    lin[..., 0] = 0.5          # sRGB 0.5 -> 0.7354 -> 188
    lin[..., 1] = 2.0          # clipped
    lin[..., 2] = 0.001        # linear segment: 12.92e-3 -> 3
    write_png(tmp_path / "a.png", lin)
    with Image.open(tmp_path / "a.png") as im:
        assert im.format == "PNG" and im.mode == "RGB" and im.size == (7, 5)
        px = np.asarray(im)
    assert tuple(px[2, 3]) == (188, 255, 3)
    assert tuple(to_srgb8(np.full((1, 1, 3), 0.25), exposure=1.0)[0, 0]) == (188, 188, 188)
    # the two branches of the transfer function meet at 0.0031308
    np.testing.assert_allclose(srgb_encode([0.0, 0.0031308, 1.0]), [0.0, 12.92 * 0.0031308, 1.0], rtol=1e-6)
    assert sorted(os.listdir(tmp_path)) == ["a.exr", "a.png"]        # no temporary files left
    with pytest.raises(ValueError):
        write_exr(tmp_path / "b.exr", np.zeros((4, 4)))
    assert not (tmp_path / "b.exr").exists()


# --------------------------------------------------------------------------------------------
# (5) the command
# --------------------------------------------------------------------------------------------
def test_cli_render_writes_both_images(tmp_path):
    from flakedb.cli.main import cli

    b = tmp_path / "lambert.bsdf"
    _lambertian(b)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["render", str(b), "--out", str(out), "--size", "16", "--spp", "2",
                                   "--env", "constant"])
    assert res.exit_code == 0, res.output
    img = read_exr(out / "lambert.exr")
    assert img.shape == (16, 16, 3) and img.dtype == np.float32
    assert img[0, 0, 0] == np.float32(0.5)                       # --env constant: the furnace
    from PIL import Image

    with Image.open(out / "lambert.png") as im:
        assert im.size == (16, 16)
    assert sorted(os.listdir(out)) == ["lambert.exr", "lambert.png"]


@pytest.mark.parametrize("content", [b"not a bsdf file at all", b"SCATFUN\x01" + b"\x00" * 20, None])
def test_cli_bad_file_fails_and_writes_nothing(content, tmp_path):
    from flakedb.cli.main import cli

    f = tmp_path / "bad.bsdf"
    if content is not None:
        f.write_bytes(content)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["render", str(f), "--out", str(out), "--size", "16", "--spp", "1"])
    assert res.exit_code != 0
    assert "bad.bsdf" in res.output
    assert not out.exists() or not any(out.iterdir())
