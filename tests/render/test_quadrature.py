"""The deterministic preview (flakedb.render.quadrature), the light grids and lat-long environments
(flakedb.render.envmap), and `flakedb render`'s --method / --environment / --write-environment.

Bugs these tests guard against:
- a wrong mapping from grid cells to the file's (mu_i, mu_o, phi_d) (the rotation about the view axis as
  an FFT correlation taken with the wrong sign or offset; phi_d mirrored): each is compared per pixel with
  the Monte Carlo renderer at 1024 samples, whose own mapping tests/render/test_preview.py checks against
  vectors-only quadratures, and with a table whose lobe depends on phi_d;
- lights whose power is lost or doubled on the grid (cell means, the sun's splatting, the lat-long file):
  the furnace (every pixel L · (albedo_R + F)) and a Lambertian under a sun (E cos θ albedo / π);
- noise: any random number in the default preview (same image for every seed; no pixel-scale grain);
- a lat-long environment in another layout than Mitsuba 3's envmap, or one that the renderer reads back
  differently from what --write-environment wrote.
"""

import math

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.bsdf import open_bsdf, write_bsdf
from flakedb.optics.fresnel import fresnel_dielectric
from flakedb.render import envmap, look, preview, quadrature
from flakedb.render.imageio import read_exr, write_exr
from tests.render.test_preview import _lambertian, _pixel_centres, _reflection_table, _smooth_coated_h5

ENV_L = 0.5
#: Angular size of one light-grid cell [rad] (1.41°).
H = math.pi / quadrature.N_THETA


def _furnace_expected(b, mu_i):
    e = ENV_L * b.albedo(mu_i)
    if b.delta is not None:
        e = e + ENV_L * fresnel_dielectric(mu_i, b.delta["eta"]).R[:, None]
    return e


# --------------------------------------------------------------------------------------------
# grids and lat-long images
# --------------------------------------------------------------------------------------------
def test_grid_solid_angles_and_cell_means():
    omega = envmap.cell_solid_angles(64, 128)
    assert abs(omega.sum() * 128 - 4 * np.pi) < 1e-12
    g = envmap.cell_average(lambda d: np.full(np.shape(d), 0.7), 16, 32, quadrature.VIEW_FRAME, 3)
    np.testing.assert_allclose(g, 0.7, rtol=1e-14)
    # ∫ max(d_z, 0) dω = π: the cell means keep an environment's integral (midpoint sub-cells, O(h²))
    g = envmap.cell_average(lambda d: np.repeat(np.maximum(d[..., 2:3], 0.0), 3, -1), 64, 128,
                            quadrature.VIEW_FRAME, 2)
    assert abs((g[..., 0] * omega[:, None]).sum() / np.pi - 1) < (H / 2) ** 2


def test_sun_power_is_kept_exactly():
    sun = preview.Sun((-0.3, 0.5, 0.8), radiance=(50.0, 40.0, 30.0), half_angle_deg=2.0)
    g = envmap.splat_sun(np.zeros((128, 256, 3)), sun, quadrature.VIEW_FRAME, 4096)
    power = (g * envmap.cell_solid_angles(128, 256)[:, None, None]).sum(axis=(0, 1))
    np.testing.assert_allclose(power, np.asarray(sun.radiance) * sun.solid_angle, rtol=1e-12)
    # every point lies in the disk: all of it sits within the cells around the sun's direction
    lit = np.argwhere(g[..., 0] > 0)
    theta, phi = envmap.grid_coordinates(np.asarray(sun.direction), quadrature.VIEW_FRAME)
    assert np.all(np.abs((lit[:, 0] + 0.5) * H - theta) < math.radians(2.0) + H)


def test_latlong_layout_is_mitsubas_envmap():
    """Mitsuba 3 envmap: u = atan2(d_x, -d_z) / 2π, v = acos(d_y) / π (row 0 up)."""
    h, w = 32, 64
    for d, (row, col) in {(0.0, 0.0, -1.0): (h // 2, 0), (1.0, 0.0, 0.0): (h // 2, w // 4),
                          (0.0, 0.0, 1.0): (h // 2, w // 2), (-1.0, 0.0, 0.0): (h // 2, 3 * w // 4)}.items():
        spot = preview.Sun(d, radiance=1.0, half_angle_deg=1.0)
        img = envmap.rasterise_latlong(lambda x: np.zeros(np.shape(x)), spot, width=w, sun_points=400)
        r, c = np.unravel_index(np.argmax(img[..., 0]), img.shape[:2])
        assert abs(r + 0.5 - h / 2) <= 1 and min(abs(c + 0.5 - col), w - abs(c + 0.5 - col)) <= 1, (d, r, c)
    sky = envmap.rasterise_latlong(preview.studio_environment(), None, width=w)
    assert sky[0].mean() > 3 * sky[-1].mean()                               # +y (up) on row 0
    # the reader interpolates what the writer wrote: a smooth environment comes back to 1e-3
    env = envmap.LatLongEnvironment(envmap.rasterise_latlong(preview.studio_environment(), None, width=512))
    d = envmap.cell_directions(20, 40, envmap.LATLONG).reshape(-1, 3)
    far = np.abs(d[:, 1]) > 0.1                                              # away from the sharp horizon
    np.testing.assert_allclose(env(d[far]), preview.studio_environment()(d[far]), rtol=2e-3)


# --------------------------------------------------------------------------------------------
# closed forms
# --------------------------------------------------------------------------------------------
@pytest.mark.parametrize("case", ["lambertian", "smooth_coated"])
def test_furnace_matches_the_files_albedo(case, tmp_path):
    """Constant L: each pixel is L · (albedo_R(mu_i) + F(mu_i)).  The midpoint rule over 1.41° cells cut
    by the horizon (where f·|mu_o| ∝ mu_o → 0) errs by O(h²); 4 h² = 2.4e-3 bounds it."""
    b = _lambertian(tmp_path / "l.bsdf") if case == "lambertian" else _smooth_coated_h5(tmp_path / "s.h5")
    size = 48
    r = quadrature.render_sphere_quadrature(b, preview.constant_environment(ENV_L), None, size=size, pixel_ss=1)
    mask, n = _pixel_centres(size)
    mu = n[..., 2][mask]
    want = _furnace_expected(b, mu)
    assert np.all(r.image[~mask] == np.float32(ENV_L))
    np.testing.assert_array_equal(r.coverage, mask.astype(np.float32))
    np.testing.assert_allclose(r.image[mask], want, rtol=4 * H * H, atol=1e-6)


def test_lambertian_under_a_sun_is_albedo_over_pi_E_cos(tmp_path):
    """A disk fully above the horizon gives E cos θ_c.  The sun's points are shared between the four
    nearest cell centres (≤ h/√2 away): relative error ≤ tan θ_c · h/√2 (first order; the bilinear share
    keeps the centroid, so it cancels to O(h²) on average) + the normal grid's bilinear interpolation of
    cos (≤ h_n²/8 / cos θ_c).  Splatting each point into its own cell only (no share) biased the mean by
    +0.35 %."""
    b = _lambertian(tmp_path / "l.bsdf")
    E = 2.0
    sun = preview.Sun.from_irradiance((0.3, 0.5, 0.8), E, half_angle_deg=0.5)
    size = 48
    r = quadrature.render_sphere_quadrature(b, preview.constant_environment(0.0), sun, size=size, pixel_ss=1)
    mask, n = _pixel_centres(size)
    c = n @ np.asarray(sun.direction)
    lit = mask & (c > 0.1)
    dark = mask & (c < -0.06)        # beyond the disk (0.009), a normal-grid step (0.025) and a cell (0.025)
    want = b.albedo(n[..., 2][lit]) / np.pi * E * c[lit][:, None]
    rel = r.image[lit] / want - 1
    tan = np.sqrt(1 - c[lit] ** 2) / c[lit]
    h_n = 0.5 * np.pi / (quadrature.N_NORMAL - 1)
    bound = tan * H / np.sqrt(2) + h_n ** 2 / 8 / c[lit] + 1e-6
    assert np.all(np.abs(rel) <= bound[:, None]), np.max(np.abs(rel) / bound[:, None])
    assert abs(rel.mean()) < 1e-3                                        # measured -8e-5 (max 3.7e-4)
    # unlit: zero up to the FFT's rounding (a sum of N_PHI terms of size max)
    assert np.all(np.abs(r.image[dark]) <= 1e-12 * r.image.max()) and np.all(r.image[~mask] == 0)


# --------------------------------------------------------------------------------------------
# against the Monte Carlo renderer (an independent estimate) and determinism
# --------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("lights", ["studio+sun", "softbox"])
def test_agrees_with_monte_carlo_at_many_samples(lights, tmp_path):
    """Both renderers at pixel centres; the Monte Carlo one at 2 × 512 samples per pixel (two seeds give
    its own noise σ).  4 × 4-pixel block means must agree within 5 σ + 1 % (the quadrature's bias,
    measured ≤ 1.7 % on the catalogue paints' soft-box edges at 1024 spp), and the sphere means within
    0.3 %.  A lobe that depends on phi_d (orders 0-2 towards the mirror direction) makes a mirrored
    azimuth visible.  No delta term here: its sun image is an area mean here and a pixel-centre sample
    there (test_mirrored_sun_keeps_its_power)."""
    write_bsdf(tmp_path / "lobe.bsdf",
               _reflection_table(lambda m: 0.15 * m * np.array([[1.5, 2.0, 0.5]] * 3), orders=3))
    b = open_bsdf(tmp_path / "lobe.bsdf")
    env, sun = ((preview.studio_environment(), preview.studio_sun()) if lights == "studio+sun"
                else (look.softbox_studio(), None))
    size = 32
    q = quadrature.render_sphere_quadrature(b, env, sun, size=size, pixel_ss=1).image.astype(float)
    mc = [preview.render_sphere(b, env, sun, size=size, spp=512, jitter=False, seed=s).image.astype(float)
          for s in (1, 2)]
    mask, _ = _pixel_centres(size)

    def blocks(img):
        return img.reshape(8, 4, 8, 4, 3).mean(axis=(1, 3))

    full = mask.reshape(8, 4, 8, 4).all(axis=(1, 3))
    bq, b1, b2 = (blocks(i)[full] for i in (q, *mc))
    sigma = np.abs(b1 - b2) / 2 + 1e-9                   # σ of the mean of the two
    m = 0.5 * (b1 + b2)
    assert np.all(np.abs(bq - m) <= 5 * sigma + 0.01 * m), np.max(np.abs(bq - m) / (5 * sigma + 0.01 * m))
    np.testing.assert_allclose(q[mask].mean(0), 0.5 * (mc[0] + mc[1])[mask].mean(0), rtol=3e-3)


def test_mirrored_sun_keeps_its_power(tmp_path):
    """A mirror-only coat (zero table, Fresnel delta) under a sun in a black world: the sun's image on
    the sphere has area Ω_sun / 4 (orthographic mirror ball), so Σ pixel · pixel area = ∫ F L dω / 4, and it
    sits at the half vector of the sun and the view."""
    write_bsdf(tmp_path / "m.bsdf", _reflection_table(lambda m: np.zeros((3, 1)), delta={"kind": "fresnel", "eta": 1.5}))
    b = open_bsdf(tmp_path / "m.bsdf")
    sun = preview.Sun((-0.3, 0.5, 0.8), radiance=(500.0, 400.0, 300.0), half_angle_deg=2.0)
    size = 64
    r = quadrature.render_sphere_quadrature(b, preview.constant_environment(0.0), sun, size=size)
    pix = 2 * preview.DEFAULT_EXTENT / size
    h = np.asarray(sun.direction) + [0.0, 0.0, 1.0]
    h /= np.linalg.norm(h)
    F = fresnel_dielectric(h[2], 1.5).R                          # F varies by < 1e-4 over the 2° disk
    energy = r.image.astype(float).sum(axis=(0, 1)) * pix * pix
    np.testing.assert_allclose(energy, F * np.asarray(sun.radiance) * sun.solid_angle / 4, rtol=1e-3)
    y, x = np.nonzero(r.image[..., 0])
    assert abs((x.mean() + 0.5) * pix - preview.DEFAULT_EXTENT - h[0]) < 1.5 * pix
    assert abs(preview.DEFAULT_EXTENT - (y.mean() + 0.5) * pix - h[1]) < 1.5 * pix


def test_identical_for_every_seed_and_free_of_grain(tmp_path):
    """The default preview has no random number: two renders are bit-identical, the CLI's --seed changes
    nothing, and the flake-free Lambertian sphere under the studio has no pixel-scale grain (the rms of
    its difference from the 3 × 3 box-smoothed image is < 0.1 % of its mean, where 32 spp Monte Carlo
    leaves ~10 %)."""
    from flakedb.cli.main import cli

    b = _lambertian(tmp_path / "l.bsdf")
    a = quadrature.render_sphere_quadrature(b, look.softbox_studio(), None, size=64)
    c = quadrature.render_sphere_quadrature(b, look.softbox_studio(), None, size=64)
    np.testing.assert_array_equal(a.image, c.image)

    def grain(img):
        y = img @ look.LUMA
        sm = sum(y[1 + i:63 + i, 1 + j:63 + j] for i in (-1, 0, 1) for j in (-1, 0, 1)) / 9
        inner = _pixel_centres(64, preview.DEFAULT_EXTENT)[0][1:63, 1:63]
        core = inner & (np.hypot(*np.meshgrid(np.arange(1, 63) - 31.5, np.arange(1, 63) - 31.5)) < 24)
        return np.sqrt(np.mean((y[1:63, 1:63] - sm)[core] ** 2)) / np.mean(y[1:63, 1:63][core])

    mc = preview.render_sphere(b, look.softbox_studio(), None, size=64, spp=32, seed=0)
    assert grain(a.image.astype(float)) < 1e-3 < 0.02 < grain(mc.image.astype(float))
    for seed in ("0", "7"):
        r = CliRunner().invoke(cli, ["render", str(tmp_path / "l.bsdf"), "--out", str(tmp_path / seed), "--size", "24",
                                     "--seed", seed])
        assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(read_exr(tmp_path / "0" / "l.exr"), read_exr(tmp_path / "7" / "l.exr"))


# --------------------------------------------------------------------------------------------
# the command: --environment, --write-environment, --method
# --------------------------------------------------------------------------------------------
def test_constant_environment_file_gives_the_furnace(tmp_path):
    """A constant lat-long EXR of radiance 0.5 lights the sphere as the constant environment: every pixel
    L · (albedo_R(mu_i) + F(mu_i)) (the tolerance of the furnace test, plus the sub-pixel mean)."""
    from flakedb.cli.main import cli

    write_exr(tmp_path / "grey.exr", np.full((64, 128, 3), ENV_L, np.float32))
    _smooth_coated_h5(tmp_path / "s.h5")
    size = 32
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "s.h5"), "--out", str(tmp_path / "o"), "--size", str(size),
                                 "--environment", str(tmp_path / "grey.exr")])
    assert r.exit_code == 0, r.output
    img = read_exr(tmp_path / "o" / "s.exr").astype(float)
    b = open_bsdf(tmp_path / "s.h5")
    # the mean over each pixel's 2 × 2 sub-pixel positions of the closed form
    ss = quadrature.PIXEL_SS
    x, y = quadrature._sub_pixel_points(size, preview.DEFAULT_EXTENT, ss)
    r2 = x * x + y * y
    inside = (r2 < 1).all(axis=-1)
    mu = np.sqrt(1 - r2[inside])
    want = _furnace_expected(b, mu.ravel()).reshape(mu.shape + (3,)).mean(axis=1)
    assert np.all(img[~(r2 < 1).any(axis=-1)] == np.float32(ENV_L))
    np.testing.assert_allclose(img[inside], want, rtol=4 * H * H, atol=1e-6)


@pytest.mark.slow
def test_written_environment_renders_as_the_studio(tmp_path):
    """--write-environment then --environment: the same light.  The sphere's mean under the exported
    studio (with its sun) is within 0.2 % of the analytic studio's (measured 0.03 %)."""
    from flakedb.cli.main import cli

    _smooth_coated_h5(tmp_path / "s.h5")
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "s.h5"), "--out", str(tmp_path / "a"), "--size", "48",
                                 "--env", "studio", "--write-environment"])
    assert r.exit_code == 0, r.output
    env_file = tmp_path / "a" / "environment-studio.exr"
    lat = read_exr(env_file)
    assert lat.shape == (512, 1024, 3)
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "s.h5"), "--out", str(tmp_path / "b"), "--size", "48",
                                 "--environment", str(env_file)])
    assert r.exit_code == 0, r.output
    a, e = read_exr(tmp_path / "a" / "s-studio.exr" if (tmp_path / "a" / "s-studio.exr").exists()
                    else tmp_path / "a" / "s.exr"), read_exr(tmp_path / "b" / "s.exr")
    mask, n = _pixel_centres(48)
    # away from the sun's mirror image (0.7 pixel across at 48 px: the analytic disk's image is exact by
    # area, the file's blurred sun is sampled at 2 × 2 points per pixel)
    h = np.asarray(preview.studio_sun().direction) + [0.0, 0.0, 1.0]
    h /= np.linalg.norm(h)
    keep = mask & (np.linalg.norm(n - h, axis=-1) > 0.15)
    np.testing.assert_allclose(e[keep].mean(0), a[keep].mean(0), rtol=2e-3)
    # the lights alone, no FILES
    r = CliRunner().invoke(cli, ["render", "--out", str(tmp_path / "c"), "--env", "softbox", "--write-environment"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["environment-softbox.exr"]


@pytest.mark.parametrize("args, words", [
    (["--method", "quadrature", "--spp", "4"], ["--spp 4", "montecarlo"]),
    (["--environment", "ENV", "--env", "studio"], ["--environment", "--env", "give one"]),
    (["--environment", "BAD"], ["not a readable", "lat-long"]),
    (["--environment", "NAN"], ["--environment", "finite radiance"]),
    (["--environment", "ENV", "--sparkle", "SILVER"], ["--sparkle", "--sun", "--environment"]),
])
def test_cli_refusals(args, words, tmp_path):
    from flakedb.cli.main import cli

    _lambertian(tmp_path / "l.bsdf")
    write_exr(tmp_path / "env.exr", np.full((4, 8, 3), 1.0, np.float32))
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    nan = np.full((4, 8, 3), 1.0, np.float32)
    nan[1, 2, 0] = np.nan
    write_exr(tmp_path / "nan.exr", nan)
    from flakedb.resources import RECIPES_DIR

    names = {"ENV": tmp_path / "env.exr", "BAD": tmp_path / "bad.exr", "NAN": tmp_path / "nan.exr",
             "SILVER": RECIPES_DIR / "metallic-silver.yaml"}
    args = [str(names.get(a, a)) for a in args]
    r = CliRunner().invoke(cli, ["render", str(tmp_path / "l.bsdf"), "--out", str(tmp_path / "o")] + args)
    assert r.exit_code != 0 and "Traceback" not in r.output
    for w in words:
        assert w in r.output, r.output
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_mono_file_and_transmission(tmp_path):
    """A mono HDF5 table (one output channel) lights in RGB: the furnace in every channel; a table that only
    transmits (mu_o > 0 entries) leaves the sphere black under any light."""
    from flakedb.bsdf import BSDFTable, write_h5

    from tests.render.test_preview import _nodes

    write_h5(tmp_path / "m.h5", _reflection_table(lambda m: np.full((1, 1), 0.3 / np.pi) * m, channels=1,
                                                  delta={"kind": "fresnel", "eta": 1.5}))
    b = open_bsdf(tmp_path / "m.h5")
    assert b.kernel_arrays().mix.shape == (1, 1)
    r = quadrature.render_sphere_quadrature(b, preview.constant_environment(ENV_L), None, size=32, pixel_ss=1)
    mask, n = _pixel_centres(32)
    want = _furnace_expected(b, n[..., 2][mask])
    assert r.image.shape == (32, 32, 3)
    np.testing.assert_allclose(r.image[mask], np.repeat(want, 3, axis=1), rtol=4 * H * H)
    mu = _nodes(16)
    c = np.zeros((3, 32, 32, 1))
    c[:, 16:, 16:, 0] = 0.9 / np.pi * mu[16:]
    write_bsdf(tmp_path / "t.bsdf", BSDFTable(mu=mu, coeffs=c))
    r = quadrature.render_sphere_quadrature(open_bsdf(tmp_path / "t.bsdf"), preview.constant_environment(ENV_L),
                                            preview.studio_sun(), size=16)
    assert np.all(r.image[r.coverage >= 1] == 0) and np.all(r.image[r.coverage == 0] == np.float32(ENV_L))
