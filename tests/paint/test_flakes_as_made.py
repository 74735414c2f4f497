"""Issue #35 item 4: aluminium grades with a settable oxide, interference pigments on real substrates with
thickness distributions, recipe overrides of the films, and a composed paint with them."""

import textwrap

import numpy as np
import pytest

from flakedb.paint.catalog import get_species, load_catalog
from flakedb.paint.materials import refractive_index
from flakedb.paint.recipe import RecipeError, parse_recipe
from flakedb.paint.recipe_checks import flake_entry_with_films
from flakedb.paint.species import binder_index, film_spreads, film_stack, flake_reflectance_transmittance
from tests.cases import basecoat_recipe

NEW = ("aluminium-cornflake", "aluminium-silver-dollar", "aluminium-vmp", "aluminium-silica", "mica-tio2-pearl",
       "alumina-tio2", "aluminium-tio2", "mica-fe2o3-pearl", "mica-tio2-fe2o3-gold")
WL = np.arange(380.0, 781.0, 20.0)


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


@pytest.mark.parametrize("name", NEW)
def test_species_optics_physical(catalog, name):
    e = get_species(name, catalog)
    c = np.linspace(0.0, 1.0, 9)
    R, T = flake_reflectance_transmittance(e, WL, c, binder_index(catalog, WL))
    assert np.all(R >= 0) and np.all(T >= 0) and np.all(R + T <= 1 + 1e-12)
    mats, _ = film_stack(e)
    k = np.stack([refractive_index(m, WL).imag for m in mats])
    if not np.any(k > 0):  # lossless substrates and coatings (k = 0 in these tables): R + T = 1
        np.testing.assert_allclose(R + T, 1.0, atol=1e-9)
    else:  # an absorbing film (Al, Fe2O3) takes some light at every angle but grazing (cos 0: R = 1)
        assert np.all((R + T)[:, c > 0] < 1.0)


def test_film_spreads_pair_the_two_faces(catalog):
    groups, sd = film_spreads(get_species("synthetic-mica-tio2-interference", catalog))
    assert groups.tolist() == [0, 0, 0, 1, 0, 0, 0]
    assert sd.tolist() == [0.08, 0.08, 0.08, 0.0, 0.08, 0.08, 0.08]


def test_oxide_thickness_is_the_stack_the_transfer_matrix_sees(catalog):
    # the recipe's oxide thickness reaches the optics: the species path equals Al2O3 | Al | Al2O3 written out,
    # and it moves R by more than 0.01 over 5-100 nm (measured: in a 1.5 binder a 5-200 nm Al2O3 or SiO2 film
    # keeps R(450) >= R(650): a low-index oxide does not warm an aluminium flake; docs/flakes.md)
    from flakedb.optics.thinfilm import thin_film_transfer_matrix
    from flakedb.paint.materials import refractive_index
    e = get_species("aluminium-cornflake", catalog)
    wl = np.array([450.0, 550.0, 650.0])
    nb = binder_index(catalog, wl)
    Rs = []
    for t in (5.0, 60.0, 100.0):
        R, _ = flake_reflectance_transmittance(flake_entry_with_films(e, {"coating_thickness_nm": [t]}), wl, [1.0, 0.5], nb)
        n = np.stack([refractive_index(m, wl) for m in ("Al2O3", "Al", "Al2O3")], axis=1)
        direct = thin_film_transfer_matrix(n, [t, 300.0, t], wl, [1.0, 0.5], nb).R
        np.testing.assert_allclose(R, direct, rtol=0, atol=1e-14)
        Rs.append(R)
    assert np.abs(Rs[1] - Rs[0]).max() > 0.01


def test_tio2_on_aluminium_is_the_warm_silver(catalog):
    # the specular colour of the flake itself (normal incidence in the binder, D65 / 2°): the MgF2 flake and the
    # native-oxide cornflake are slightly blue, 15 nm of TiO2 warm (b* +2.0 measured), 25 nm warmer
    from flakedb.colour.colorimetry import XYZ_to_Lab, reflectance_to_XYZ, white_XYZ
    wl = np.arange(380.0, 781.0, 10.0)
    nb = binder_index(catalog, wl)
    def b_star(e):
        R, _ = flake_reflectance_transmittance(e, wl, [1.0], nb)
        return XYZ_to_Lab(reflectance_to_XYZ(R[:, 0], wl), white=white_XYZ(wl))[2]
    warm = get_species("aluminium-tio2", catalog)
    assert b_star(get_species("metallic", catalog)) < 0 and b_star(get_species("aluminium-cornflake", catalog)) < 0
    assert 1.0 < b_star(warm) < 3.0
    assert b_star(flake_entry_with_films(warm, {"coating_thickness_nm": [25.0]})) > b_star(warm) + 1.0


def _recipe(particle, mode="rgb"):
    return textwrap.dedent(f"""\
        flakedb: 1
        name: flakes-as-made
        spectral: {{mode: {mode}}}
        resolution: 16
        layers:
          - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}
          - basecoat: {{thickness_um: 15, ior: 1.5, particles: [{particle}]}}
          - primer: {{color: gray}}
        """)


def test_recipe_sets_the_oxide_and_the_flake_thickness_follows(catalog):
    r = parse_recipe(_recipe("{species: aluminium-cornflake, volume_fraction: 0.05, coating_thickness_nm: [40], "
                             "coating_thickness_rel_sd: 0.1}"), catalog=catalog)
    p = next(q for L in r.basecoats for q in L.particles)
    assert p.entry["coating"][0]["thickness_nm"]["value"] == 40.0
    assert p.entry["coating"][0]["thickness_rel_sd"]["value"] == 0.1
    assert p.entry["thickness_um"]["value"] == pytest.approx(0.38)
    assert get_species("aluminium-cornflake", catalog)["coating"][0]["thickness_nm"]["value"] == 5  # catalogue untouched
    r = parse_recipe(_recipe("{species: aluminium-cornflake, volume_fraction: 0.05, coating_thickness_nm: 40}"),
                     catalog=catalog)  # one number for a one-film coating
    assert next(q for L in r.basecoats for q in L.particles).entry["coating"][0]["thickness_nm"]["value"] == 40.0


@pytest.mark.parametrize("particle, needle", [
    ("{species: aluminium-cornflake, volume_fraction: 0.05, coating_thickness_nm: [40, 5]}", "coating_thickness_nm: 2 value"),
    ("{species: gray-mirror, volume_fraction: 0.05, coating_thickness_nm: [40]}", "interference flakes only"),
    ("{species: synthetic-mica-tio2-interference, volume_fraction: 0.05, coating_thickness_nm: 40}", "1 value"),
    ("{species: aluminium-cornflake, volume_fraction: 0.05, coating_thickness_rel_sd: 0.9}", "coating_thickness_rel_sd"),
])
def test_recipe_film_errors_name_the_field(catalog, particle, needle):
    with pytest.raises(RecipeError, match=needle):
        parse_recipe(_recipe(particle), catalog=catalog)


def test_composed_paint_with_new_species_is_physical_and_sees_the_oxide(catalog):
    from flakedb.solve.pipeline import solve_recipe
    out = []
    for t in (5, 55):
        r = parse_recipe(_recipe(f"{{species: aluminium-cornflake, volume_fraction: 0.05, coating_thickness_nm: [{t}]}}, "
                                 f"{{species: mica-tio2-pearl, volume_fraction: 0.02}}"), catalog=catalog)
        s = solve_recipe(r, catalog=catalog)  # check_physical: energy, reciprocity, positivity (raises)
        out.append(np.asarray(s.table.stored))
    m = min(out[0].shape[-1], out[1].shape[-1])  # Fourier orders kept may differ; order 0 carries the albedo
    assert np.all(np.isfinite(out[0])) and np.abs(out[1][..., :m] - out[0][..., :m]).max() > 1e-3


def test_match_recovers_the_tio2_thickness_on_aluminium(tmp_path):
    """`match` varies a coating thickness (coating_thickness_nm: {fit: [min, max]}, a one-film coating): a target
    made by flakedb from 20 nm of TiO2 on the aluminium flake, the fit started at 12 nm."""
    import yaml
    from click.testing import CliRunner

    from flakedb.cli.main import cli
    text = basecoat_recipe("warm-silver", ["{species: aluminium-tio2, volume_fraction: 0.05, coating_thickness_nm: [THICK]}"])
    (tmp_path / "true.yaml").write_text(text.replace("THICK", "20"))
    target = tmp_path / "target.csv"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "true.yaml"), "--write-csv", str(target),
                                 "--geometries", "e2194"])
    assert r.exit_code == 0, r.output
    (tmp_path / "base.yaml").write_text(text.replace("[THICK]", "{fit: [5, 30], start: 12}"))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(target), "--out", str(out)])
    assert r.exit_code == 0, r.output
    fitted = yaml.safe_load((out / "warm-silver-fitted.yaml").read_text())
    assert fitted["layers"][1]["basecoat"]["particles"][0]["coating_thickness_nm"] == pytest.approx(20.0, rel=0.02)


def test_store_serves_a_spread_flake_and_recipe_films_after_a_recipe_build(tmp_path):
    """A catalogue flake with a thickness spread is built into a store and composed from it; a recipe that
    sets its films is refused by name until `flakedb build --recipe` adds the flake with those films (its own
    species of the store, flakedb.paint.components.store_key), not as a changed catalogue; then it composes."""
    from click.testing import CliRunner

    from flakedb.cli.main import cli
    store = tmp_path / "S"
    r = CliRunner().invoke(cli, ["build", "--store", str(store), "--species", "aluminium-tio2", "--n", "16",
                                 "--step-nm", "20", "--workers", "1"])
    assert r.exit_code == 0, r.output
    plain = _recipe("{species: aluminium-tio2, volume_fraction: 0.05}", mode="spectral").replace(
        "{mode: spectral}", "{mode: spectral, range_nm: [380, 780], step_nm: 20}")
    (tmp_path / "a.yaml").write_text(plain)
    r = CliRunner().invoke(cli, ["compose", str(tmp_path / "a.yaml"), "--store", str(store), "--out", str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    (tmp_path / "b.yaml").write_text(plain.replace("volume_fraction: 0.05}", "volume_fraction: 0.05, coating_thickness_nm: [20]}"))
    r = CliRunner().invoke(cli, ["compose", str(tmp_path / "b.yaml"), "--store", str(store), "--out", str(tmp_path / "o2")])
    assert r.exit_code != 0
    assert "with the recipe's coating_thickness_nm" in r.output and "catalogue changed" not in r.output
    assert "flakedb build --recipe" in r.output
    r = CliRunner().invoke(cli, ["build", "--recipe", str(tmp_path / "b.yaml"), "--store", str(store), "--workers", "1"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["compose", str(tmp_path / "b.yaml"), "--store", str(store), "--out", str(tmp_path / "o2")])
    assert r.exit_code == 0, r.output
