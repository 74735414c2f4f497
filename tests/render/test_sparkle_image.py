"""Glints drawn on the deterministic preview (flakedb.render.sparkle.sparkle_image).

Guards against what issue #37 saw with 40 µm flakes: the old additive layer took the model's mean flake
radiance from every pixel without a glint, which went below zero where the render holds less than the
model's β_ss; clipping at 0 then added energy (a biased mean) and, clipping some channels more than
others, a colour cast.  Here: no pixel below zero, every region's mean kept within the Poisson error, the
colour of the highlight region kept, each glint drawn as a normalised spot, deterministic per seed.
"""

import numpy as np
import pytest

from flakedb.paint.recipe import load_recipe
from flakedb.paint.texture_inputs import texture_stack
from flakedb.render import look, preview, quadrature
from flakedb.render.sparkle import GLINT_KERNEL, sparkle_image, sparkle_layer
from flakedb.resources import RECIPES_DIR
from tests.render.test_preview import _lambertian
from tests.texture.cases import recipe

SIZE = 96


@pytest.fixture(scope="module")
def dark_smooth(tmp_path_factory):
    b = _lambertian(tmp_path_factory.mktemp("sp") / "g.bsdf", albedo=(0.1, 0.1, 0.1))
    return quadrature.render_sphere_quadrature(b, look.softbox_studio(), preview.studio_sun(), size=SIZE).image.astype(float)


@pytest.mark.slow
def test_big_flakes_make_no_hole_and_no_cast(dark_smooth):
    sun = preview.studio_sun()
    st = texture_stack(recipe(vf=0.05, D=40.0))[0]
    img, info = sparkle_image(dark_smooth, st, sun, preview.DEFAULT_EXTENT, seed=1)
    old, _ = sparkle_layer(st, sun, SIZE, preview.DEFAULT_EXTENT, seed=1)
    assert np.mean(dark_smooth + old < 0) > 0.01                 # the case that made the hole and the cast
    assert img.min() >= 0.0
    sigma = info["sigma_image_sum"]
    assert sigma < 0.05 * dark_smooth.sum()
    assert abs(img.sum() - dark_smooth.sum()) < 4 * sigma        # the mean is the render's
    # the region the glints live in keeps its colour: channel shares within the Poisson error
    g, _ = sparkle_image(dark_smooth, st, sun, preview.DEFAULT_EXTENT, seed=1, kernel=np.ones((1, 1)))
    lit = np.abs(g - dark_smooth).sum(-1) > 0
    share = img[lit].sum(0) / img[lit].sum()
    share0 = dark_smooth[lit].sum(0) / dark_smooth[lit].sum()
    np.testing.assert_allclose(share, share0, atol=3 * sigma / dark_smooth[lit].sum())
    # a glint is a spot of the kernel's shape: spreading moves energy, it neither adds nor removes any,
    # and a spot's peak is lower than the one-pixel glint's
    assert abs(GLINT_KERNEL.sum() - 1) < 1e-15 and GLINT_KERNEL[1, 1] == 0.25
    assert abs((img - g).sum()) < 1e-9 * np.abs(g - dark_smooth).sum()
    assert img.max() < 0.6 * g.max()
    # determinism for a seed
    again, _ = sparkle_image(dark_smooth, st, sun, preview.DEFAULT_EXTENT, seed=1)
    np.testing.assert_array_equal(again, img)


@pytest.mark.slow
def test_catalogue_silver_on_its_own_render_is_barely_capped(tmp_path):
    """metallic silver's glints on metallic silver's own preview: the model's mean flake radiance fits
    under the render almost everywhere (the cap takes < 5 % of it) and the image keeps the render's mean."""
    from flakedb.bsdf import open_bsdf

    st = texture_stack(load_recipe(RECIPES_DIR / "metallic-silver.yaml"))[0]
    from click.testing import CliRunner

    from flakedb.cli.main import cli

    r = CliRunner().invoke(cli, ["compose", str(RECIPES_DIR / "metallic-silver.yaml"), "--out", str(tmp_path), "--quiet"])
    assert r.exit_code == 0, r.output
    b = open_bsdf(tmp_path / "metallic-silver.bsdf")
    sun = preview.studio_sun()
    sm = quadrature.render_sphere_quadrature(b, look.softbox_studio(), sun, size=SIZE).image.astype(float)
    img, info = sparkle_image(sm, st, sun, preview.DEFAULT_EXTENT, seed=2)
    assert info["capped"] < 0.05, info["capped"]
    assert img.min() >= 0 and abs(img.sum() - sm.sum()) < 4 * info["sigma_image_sum"]
