"""Glints in the preview (flakedb/render/sparkle.py, `flakedb render --sparkle`): deterministic for a
seed, independent of the sample count, and the image's mean over the sphere equals the smooth
render's within 2 % (the glints replace the part of the BSDF they carry).  Guards against glints
that move with --spp, bias the mean, or ignore the flake size."""

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.paint.recipe import load_recipe
from flakedb.paint.texture_inputs import texture_stack
from flakedb.render import preview
from flakedb.render.sparkle import sparkle_layer
from flakedb.resources import PACKAGE_DIR
from tests.render.test_preview import _lambertian
from tests.texture.cases import recipe

RECIPES = Path(PACKAGE_DIR) / "catalog" / "recipes"


@pytest.fixture(scope="module")
def stack():
    return texture_stack(load_recipe(RECIPES / "metallic-silver.yaml"))[0]


@pytest.mark.slow
def test_glints_are_deterministic_and_keep_the_mean(stack):
    sun = preview.studio_sun()
    a, ia = sparkle_layer(stack, sun, 96, preview.DEFAULT_EXTENT, sphere_diameter_mm=300.0, seed=3)
    b, _ = sparkle_layer(stack, sun, 96, preview.DEFAULT_EXTENT, sphere_diameter_mm=300.0, seed=3)
    c, _ = sparkle_layer(stack, sun, 96, preview.DEFAULT_EXTENT, sphere_diameter_mm=300.0, seed=4)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert ia["glints"] > 1000  # enough for the 2 % check below to be meaningful (Poisson ~ 1/√Σλ)
    # the glints' mean over the sphere equals the part of the BSDF they replace: Σ layer = 0 within
    # its Poisson error (√Σ L²/λ; the few glints near the highlight carry most of it)
    assert abs(a.sum()) < 3.0 * ia["sigma_layer_sum"]
    assert ia["sigma_layer_sum"] < 0.3 * ia["glint_radiance_sum"]


@pytest.mark.slow
def test_render_sparkle_independent_of_spp_and_mean_within_2_percent(tmp_path, stack):
    f = tmp_path / "grey.bsdf"
    _lambertian(f, albedo=(0.5, 0.5, 0.5))
    out = {}
    for spp in (2, 8):
        r = CliRunner().invoke(cli, ["render", str(f), "--out", str(tmp_path / f"o{spp}"), "--size", "64", "--spp",
                                     str(spp), "--sun", "--sparkle", str(RECIPES / "metallic-silver.yaml"),
                                     "--sphere-mm", "300", "--seed", "5"])
        assert r.exit_code == 0, r.output
        r0 = CliRunner().invoke(cli, ["render", str(f), "--out", str(tmp_path / f"s{spp}"), "--size", "64", "--spp",
                                      str(spp), "--sun", "--seed", "5"])
        assert r0.exit_code == 0, r0.output
        from flakedb.render.imageio import read_exr
        sp = read_exr(tmp_path / f"o{spp}" / "grey-metallic-silver.exr")
        sm = read_exr(tmp_path / f"s{spp}" / "grey.exr")
        out[spp] = (sp, sm)
    (a2, s2), (a8, s8) = out[2], out[8]
    # the glints (render with sparkle minus the smooth render of the same samples) do not change with spp
    g2, g8 = a2.astype(float) - s2, a8.astype(float) - s8
    big = np.abs(g8) > 1e-3 * np.abs(s8).max()
    assert big.sum() > 20
    assert np.allclose(g2[big], g8[big], rtol=0.02, atol=1e-3 * np.abs(s8).max())
    assert abs(a8.sum() / s8.sum() - 1.0) < 0.02


def test_bigger_flakes_sparkle_fewer_and_brighter():
    sun = preview.studio_sun()
    small = texture_stack(recipe(vf=0.05, D=10.0))[0]
    big = texture_stack(recipe(vf=0.05, D=40.0))[0]
    ls, i_s = sparkle_layer(small, sun, 48, preview.DEFAULT_EXTENT, sphere_diameter_mm=100.0, seed=1)
    lb, i_b = sparkle_layer(big, sun, 48, preview.DEFAULT_EXTENT, sphere_diameter_mm=100.0, seed=1)
    assert i_b["sum_lambda"] < 0.2 * i_s["sum_lambda"]
    assert lb.max() > 2.0 * ls.max()


def test_mitsuba_route_flake_map_and_parameters():
    """The flake normal map covers 1 − exp(−N_A⟨A⟩) of the texels (Boolean model) with unit normals of
    the recipe's tilt spread; the parameter set repeats the model's statistics and counts."""
    from flakedb.render.mitsuba_sparkle import flake_normal_map, shader_parameters
    from flakedb.texture.model import sparkle_indices
    from flakedb.texture.instruments import Observer

    st = texture_stack(recipe(vf=0.01, D=12.0, alpha=0.2))[0]
    f = st.flakes[0]
    m = flake_normal_map(st, 192, 3.0, seed=2)
    cov = m[..., 3].mean()
    expect = 1.0 - np.exp(-f.areal_density_per_um2 * f.mean_area_um2())
    assert cov == pytest.approx(expect, abs=0.03)
    n = m[m[..., 3] > 0][:, :3]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    slope2 = (n[:, 0] ** 2 + n[:, 1] ** 2) / n[:, 2] ** 2
    assert slope2.mean() == pytest.approx(f.alpha**2, rel=0.1)  # Beckmann: E[tan²θ] = α²
    p = shader_parameters(st, 50.0, 0.01, 1.0)
    assert p["species"][0]["flakes_per_mm2"] == pytest.approx(f.areal_density_per_um2 * 1e6)
    # a grid point: θ_h = 10°, θ_d = 10° in the binder is the in-plane pair l' = 20°, v' = 0°
    la = float(np.degrees(np.arcsin(np.sin(np.radians(20.0)) * st.eta)))
    r = sparkle_indices(st, Observer("o", 50.0, 0.01, 1.0, (la,), 0.0), la)
    i, j = 4, 2  # TILT_GRID 0..40 step 2.5 -> 10°; HALF_GRID 0..40 step 5 -> 10°
    assert p["glints_per_mm2"][i][j] == pytest.approx(r["glints_per_mm2"], rel=1e-9)
