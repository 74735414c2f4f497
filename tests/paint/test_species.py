"""The particle catalogue (flakedb.paint.species, catalog/particles.yaml) and `flakedb species`.

Guards against: a catalogue that does not validate, or a schema that accepts unknown keys, values
without a source, unknown materials or a total thickness that disagrees with the film stack; a
wrong sweep expansion (names, thicknesses); a flake stack assembled wrongly (not symmetric, layers
out of order: a lossless stack must conserve energy, an aluminium flake must be opaque and bright);
physics of interference flakes (reflectance peaks must move to shorter wavelengths as the angle
grows, Born & Wolf §7.6); pigments fed the particle's own index instead of the relative one, or
the size parameter computed outside the binder (cross-check against miepython); the command printing
numbers other than the library's, not writing its plot, or failing silently on an unknown name.
"""

import copy
import re

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from flakedb.cli.main import cli
from flakedb.paint.catalog import (
    CatalogError,
    default_catalog_path,
    expand_sweeps,
    get_species,
    load_catalog,
    validate_catalog,
)
from flakedb.paint.species import (
    SHOW_ANGLES_DEG,
    SHOW_WAVELENGTHS_NM,
    binder_index,
    film_stack,
    flake_reflectance_transmittance,
    pigment_optics,
)

PAPER_SIX = {
    "metallic": "interference_flake",
    "pearlescent": "interference_flake",
    "gray-mirror": "mirror_flake",
    "cadmium-yellow": "pigment",
    "titanium-white": "pigment",
    "iron-black": "pigment",
}
#: species the catalogue adds to the paper's six (each with its reason in particles.yaml)
ADDED = {"pearl-white": "interference_flake", "carbon-black": "pigment", "iron-oxide-red": "pigment",
         "iron-oxide-red-transparent": "pigment", "titanium-white-r706": "pigment"}
#: issue #35 item 4, flakes as they are made (tests/paint/test_flakes_as_made.py)
ADDED = ADDED | {n: "interference_flake" for n in (
    "aluminium-cornflake", "aluminium-silver-dollar", "aluminium-vmp", "aluminium-silica", "mica-tio2-pearl",
    "synthetic-mica-tio2-interference", "alumina-tio2", "glass-flake-tio2", "aluminium-tio2")}
#: the Fabry-Perot colour-shift flake (tests/paint/test_colour_shift_flake.py)
ADDED = ADDED | {"colour-shift-cr-mgf2-al": "interference_flake"}
#: iron-oxide-coated mica, the species gold and golden-pearl paints are made of (tests/paint/test_fe2o3_flakes.py)
ADDED = ADDED | {"mica-fe2o3-pearl": "interference_flake", "mica-tio2-fe2o3-gold": "interference_flake"}
#: the diffractive (grating-embossed) aluminium flake, issue 35 (tests/paint/test_grating_recipe.py)
ADDED = ADDED | {"holographic-aluminium": "interference_flake"}
#: issue #35 item 1, organic colourants from published KM data (tests/paint/test_palette.py)
ADDED = ADDED | {n: "tinter" for n in (
    "phthalo-blue", "phthalo-blue-red-shade", "phthalo-green", "phthalo-green-yellow-shade", "quinacridone-red",
    "quinacridone-magenta", "pyrrole-red", "hansa-yellow-opaque")}


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


@pytest.fixture
def raw():
    with open(default_catalog_path(), encoding="utf-8") as f:
        return yaml.safe_load(f)


class TestCatalogue:
    def test_paper_particles_present(self, catalog):
        assert {n: e["kind"] for n, e in catalog["particles"].items()} == PAPER_SIX | ADDED

    def test_every_number_has_a_source(self, catalog):
        def walk(node, path):
            if isinstance(node, dict):
                if "value" in node:
                    assert isinstance(node.get("source"), str) and len(node["source"]) > 10, path
                for k, v in node.items():
                    walk(v, f"{path}.{k}")
            elif isinstance(node, list):
                for i, v in enumerate(node):
                    walk(v, f"{path}[{i}]")

        walk(catalog["particles"], "particles")

    def test_sweep_expansion(self, catalog):
        allsp = expand_sweeps(catalog)
        sweep = [n for n in allsp if n.startswith("pearlescent-tio2-")]
        assert sweep == [f"pearlescent-tio2-{t:03d}nm" for t in range(70, 141, 10)]
        e = allsp["pearlescent-tio2-070nm"]
        mats, d = film_stack(e)
        assert mats == ["TiO2-rutile-o", "SiO2", "TiO2-rutile-o"]
        np.testing.assert_allclose(d, [70.0, 300.0, 70.0])
        assert abs(e["thickness_um"]["value"] - 0.44) < 1e-12
        assert catalog["particles"]["pearlescent"]["coating"][0]["thickness_nm"]["value"] == 120  # not mutated

    def test_species_are_copies_made_on_lookup(self, catalog):
        """expand_sweeps' view: each entry a deep copy equal to the catalogue's, the same object on every lookup
        (a recipe's check sees one entry per species), made only when looked up; changing it leaves the
        catalogue and a second view as they were."""
        allsp = expand_sweeps(catalog)
        assert list(allsp)[: len(catalog["particles"])] == list(catalog["particles"]) and "metallic" in allsp
        assert not allsp._made                                   # nothing copied before a lookup
        e = allsp["metallic"]
        assert e == catalog["particles"]["metallic"] and e is not catalog["particles"]["metallic"]
        assert allsp["metallic"] is e and set(allsp._made) == {"metallic"}
        e["orientation_alpha"]["value"] = 9.0
        assert catalog["particles"]["metallic"]["orientation_alpha"]["value"] != 9.0
        assert expand_sweeps(catalog)["metallic"]["orientation_alpha"]["value"] != 9.0
        with pytest.raises(KeyError):
            allsp["chrome"]

    def test_film_stack_symmetric(self, catalog):
        for name, e in expand_sweeps(catalog).items():
            if e["kind"] == "interference_flake":
                mats, d = film_stack(e)
                assert mats == mats[::-1] and np.array_equal(d, d[::-1]), name

    def test_unknown_species_lists_known(self, catalog):
        with pytest.raises(ValueError, match=r"unknown species 'chrome'.*metallic.*pearlescent-tio2-140nm"):
            get_species("chrome", catalog)


class TestSchema:
    @pytest.mark.parametrize(
        "mutate, where",
        [
            (lambda d: d.update(extra=1), r"\(top level\): Additional properties"),
            (lambda d: d["particles"]["metallic"].update(colour="silver"), r"particles\.metallic: Additional properties.*'colour'"),
            (lambda d: d["particles"]["metallic"]["coating"][0].update(rough=1), r"particles\.metallic\.coating\[0\]: Additional"),
            (lambda d: d["particles"]["iron-black"]["gsd"].update(unit="-"), r"particles\.iron-black\.gsd: Additional"),
            (lambda d: d["sweeps"]["pearlescent-tio2"].update(step=5), r"sweeps\.pearlescent-tio2: Additional"),
        ],
    )
    def test_rejects_unknown_keys(self, raw, mutate, where):
        mutate(raw)
        problems = validate_catalog(raw)
        assert any(re.search(where, p) for p in problems), problems

    def test_rejects_value_without_source(self, raw):
        del raw["particles"]["titanium-white"]["median_diameter_um"]["source"]
        assert any("titanium-white.median_diameter_um" in p and "'source'" in p for p in validate_catalog(raw))

    def test_rejects_bad_values(self, raw):
        bad = copy.deepcopy(raw)
        bad["particles"]["gray-mirror"]["albedo"]["value"] = 1.5
        bad["particles"]["cadmium-yellow"]["gsd"]["value"] = 0.9
        problems = "\n".join(validate_catalog(bad))
        assert "gray-mirror.albedo" in problems and "cadmium-yellow.gsd" in problems

    def test_semantic_checks(self, raw):
        raw["particles"]["metallic"]["substrate"]["material"] = "Unobtainium"
        raw["particles"]["pearlescent"]["thickness_um"]["value"] = 1.0
        raw["sweeps"]["pearlescent-tio2"]["base"] = "iron-black"
        problems = "\n".join(validate_catalog(raw))
        assert "particles.metallic.substrate.material: unknown material 'Unobtainium'" in problems
        assert "particles.pearlescent.thickness_um" in problems and "0.54" in problems
        assert "sweeps.pearlescent-tio2.base" in problems

    def test_load_catalog_error_names_entry_and_field(self, raw, tmp_path):
        raw["particles"]["metallic"]["diameter_um"]["value"] = -3
        p = tmp_path / "bad.yaml"
        p.write_text(yaml.safe_dump(raw), encoding="utf-8")
        with pytest.raises(CatalogError, match=r"particles\.metallic\.diameter_um\.value"):
            load_catalog(p)


WL = np.arange(380.0, 781.0, 2.0)


class TestFlakeOptics:
    def test_metallic_opaque_and_bright(self, catalog):
        e = get_species("metallic", catalog)
        cos = np.cos(np.radians([0.0, 20.0, 40.0, 60.0, 80.0]))
        R, T = flake_reflectance_transmittance(e, WL, cos, binder_index(catalog, WL))
        assert R.shape == T.shape == (WL.size, cos.size)
        assert np.all(T < 1e-12)
        # Al under MgF2 in a dielectric: 0.83-0.90 at normal incidence; lowest (0.73) at 780 nm and
        # 80°, where Al's interband absorption near 800 nm (1.5 eV) sets in.
        assert np.all(R > 0.7) and np.all(R < 1.0) and R.mean() > 0.8

    def test_pearl_white_is_the_quarter_wave_reflector(self, catalog):
        # particles.yaml: pearl-white's TiO2 and SiO2 are each a quarter wave at 550 nm.  With exact
        # λ/(4n) thicknesses every interface reflection adds in phase there and the stack in the binder
        # (n0 on both sides) has the closed form of a quarter-wave H L H stack: each quarter-wave layer
        # maps the admittance y -> n_layer²/y, so Y = nH⁴ / (nL² n0) and R = ((n0 - Y)/(n0 + Y))²
        # (Macleod, Thin-Film Optical Filters, quarter-wave stacks).  The catalogue's rounded 52/94 nm
        # must stay within 0.3 % of that value; its first-order band must be broad (R >= half its
        # maximum over 440-700 nm, R(550) within 1 % of the maximum, measured 427-766 nm and 0.995)
        # with no second maximum in 380-780 nm (a coloured higher order would be a coloured pearl).
        from flakedb.paint.materials import refractive_index

        e = copy.deepcopy(get_species("pearl-white", catalog))
        wl0 = np.array([550.0])
        n0 = float(binder_index(catalog, wl0)[0])
        nH = float(refractive_index(e["coating"][0]["material"], wl0)[0].real)
        nL = float(refractive_index(e["substrate"]["material"], wl0)[0].real)
        Y = nH**4 / (nL**2 * n0)
        R_closed = ((n0 - Y) / (n0 + Y)) ** 2
        exact = copy.deepcopy(e)
        exact["coating"][0]["thickness_nm"]["value"] = 550.0 / (4 * nH)
        exact["substrate"]["thickness_nm"]["value"] = 550.0 / (4 * nL)
        R, _ = flake_reflectance_transmittance(exact, wl0, np.array([1.0]), np.array([n0]))
        assert abs(R[0, 0] - R_closed) < 1e-9
        R_cat, _ = flake_reflectance_transmittance(e, wl0, np.array([1.0]), np.array([n0]))
        assert abs(R_cat[0, 0] / R_closed - 1) < 3e-3
        wl = np.arange(380.0, 781.0, 1.0)
        Rs = flake_reflectance_transmittance(e, wl, np.array([1.0]), binder_index(catalog, wl))[0][:, 0]
        assert Rs[wl == 550.0][0] >= 0.99 * Rs.max()
        assert np.all(Rs[(wl >= 440) & (wl <= 700)] >= 0.5 * Rs.max())
        inner = (Rs[1:-1] > Rs[:-2]) & (Rs[1:-1] > Rs[2:])
        assert inner.sum() == 1

    def test_lossless_pearlescent_conserves_energy(self, catalog):
        wl = np.arange(430.0, 781.0, 5.0)  # k = 0 for TiO2 (Devore) and SiO2 (Malitson) here
        for name, e in expand_sweeps(catalog).items():
            if name.startswith("pearlescent"):
                R, T = flake_reflectance_transmittance(e, wl, np.linspace(0.05, 1.0, 7), binder_index(catalog, wl))
                np.testing.assert_allclose(R + T, 1.0, atol=1e-12)

    def test_pearlescent_peaks_blue_shift_with_angle(self, catalog):
        # Interference maxima satisfy n d cos(theta_film) ∝ lambda: tilting the flake moves each
        # reflectance peak to shorter wavelengths.  Track every prominent peak of the 0° spectrum in
        # 5° steps (in the binder) while it stays visible: each step it must move to the blue, by
        # less than 40 nm.  A peak that fades or leaves the band ends its track (>= 3 steps needed).
        from scipy.signal import find_peaks

        wl = np.arange(380.0, 781.0, 0.5)
        angles = np.arange(0.0, 41.0, 5.0)
        nb = binder_index(catalog, wl)
        checked = 0
        for name, e in expand_sweeps(catalog).items():
            if not name.startswith("pearlescent"):
                continue
            R, _ = flake_reflectance_transmittance(e, wl, np.cos(np.radians(angles)), nb)
            peaks = [wl[find_peaks(R[:, j], prominence=0.05)[0]] for j in range(angles.size)]
            for start in peaks[0]:
                if not 420.0 <= start <= 760.0:
                    continue
                pos, steps = start, 0
                for j in range(1, angles.size):
                    near = peaks[j][np.abs(peaks[j] - pos) < 40.0]
                    if near.size == 0:
                        break
                    nxt = near[np.argmin(np.abs(near - pos))]
                    assert nxt < pos, (name, angles[j], pos, nxt)
                    pos, steps = nxt, steps + 1
                checked += steps >= 3
        assert checked >= 9

    def test_mirror_flake(self, catalog):
        e = get_species("gray-mirror", catalog)
        R, T = flake_reflectance_transmittance(e, WL, np.array([1.0, 0.5, 0.1]), 1.5)
        assert np.all(R == 0.5) and np.all(T == 0.0)
        spec = copy.deepcopy(e)
        spec["albedo"] = {"wavelength_nm": [380, 780], "value": [0.2, 0.6], "source": "test spectrum"}
        R, _ = flake_reflectance_transmittance(spec, np.array([380.0, 580.0, 780.0]), np.array([1.0]), 1.5)
        np.testing.assert_allclose(R[:, 0], [0.2, 0.4, 0.6])


class TestPigmentOptics:
    def test_monodisperse_matches_miepython(self, catalog):
        # gsd = 1: one sphere; miepython 3's efficiencies_mx(m, x) with m = N/n_binder,
        # x = π d n_binder / λ (conventions).  miepython writes m = n - ik: pass the conjugate.
        import miepython

        e = copy.deepcopy(get_species("cadmium-yellow", catalog))
        e["gsd"]["value"] = 1.0
        wl = np.array([450.0, 550.0, 650.0])
        nb = binder_index(catalog, wl)
        p = pigment_optics(e, wl, nb)
        d = e["median_diameter_um"]["value"]
        from flakedb.paint.materials import refractive_index

        for i, w in enumerate(wl):
            m = refractive_index("CdS", w) / nb[i]
            x = np.pi * d * nb[i] / (w * 1e-3)
            qext, qsca, _, g = miepython.efficiencies_mx(np.conj(m), x)
            area = np.pi * d**2 / 4
            assert abs(p.c_ext_um2[i] - qext * area) < 1e-9 * qext * area
            assert abs(p.c_sca_um2[i] - qsca * area) < 1e-9 * qsca * area
            assert abs(p.g[i] - g) < 1e-9

    def test_pigment_physics(self, catalog):
        wl = np.array([450.0, 550.0, 650.0])
        nb = binder_index(catalog, wl)
        white = pigment_optics(get_species("titanium-white", catalog), wl, nb)
        np.testing.assert_allclose(white.c_sca_um2, white.c_ext_um2, rtol=1e-12)  # k = 0: no absorption
        yellow = pigment_optics(get_species("cadmium-yellow", catalog), wl, nb)
        albedo = yellow.c_sca_um2 / yellow.c_ext_um2
        assert albedo[0] < 0.7 and albedo[2] > 0.999  # CdS absorbs blue (band gap ~2.4 eV), not red
        black = pigment_optics(get_species("iron-black", catalog), wl, nb)
        assert np.all(black.c_sca_um2 < black.c_ext_um2)

    def test_kind_mismatch(self, catalog):
        with pytest.raises(ValueError, match="not a pigment"):
            pigment_optics(get_species("metallic", catalog), WL, 1.5)
        with pytest.raises(ValueError, match="not a flake"):
            flake_reflectance_transmittance(get_species("iron-black", catalog), WL, np.array([1.0]), 1.5)


def _table_rows(output, label):
    lines = output.splitlines()
    i = next(k for k, s in enumerate(lines) if s.startswith(label))
    return np.array([[float(v) for v in lines[i + 2 + r].split()] for r in range(len(SHOW_WAVELENGTHS_NM))])


class TestCommand:
    def test_show_flake_prints_library_numbers_and_writes_plot(self, tmp_path, catalog):
        r = CliRunner().invoke(cli, ["species", "show", "metallic", "--out", str(tmp_path)])
        assert r.exit_code == 0, r.output
        png = tmp_path / "metallic-optics.png"
        assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp file left
        wl = np.array(SHOW_WAVELENGTHS_NM)
        R, T = flake_reflectance_transmittance(
            get_species("metallic", catalog), wl, np.cos(np.radians(SHOW_ANGLES_DEG)), binder_index(catalog, wl)
        )
        for label, ref in (("R ", R), ("T ", T)):
            rows = _table_rows(r.output, label)
            np.testing.assert_allclose(rows[:, 0], wl)
            np.testing.assert_allclose(rows[:, 1:], ref, atol=6e-7)

    def test_show_pigment(self, tmp_path, catalog):
        r = CliRunner().invoke(cli, ["species", "show", "titanium-white", "--out", str(tmp_path)])
        assert r.exit_code == 0, r.output
        assert (tmp_path / "titanium-white-optics.png").exists()
        wl = np.array(SHOW_WAVELENGTHS_NM)
        p = pigment_optics(get_species("titanium-white", catalog), wl, binder_index(catalog, wl))
        rows = _table_rows(r.output, "per particle")
        np.testing.assert_allclose(rows[:, 1], p.c_ext_um2, atol=6e-7)
        np.testing.assert_allclose(rows[:, 2], p.c_sca_um2, atol=6e-7)
        np.testing.assert_allclose(rows[:, 4], p.g, atol=6e-7)

    def test_unknown_name_fails_and_lists_known(self, tmp_path):
        r = CliRunner().invoke(cli, ["species", "show", "chrome", "--out", str(tmp_path)])
        assert r.exit_code != 0
        assert "unknown species 'chrome'" in r.output and "pearlescent-tio2-070nm" in r.output
        assert not list(tmp_path.iterdir())

    def test_list(self, catalog):
        r = CliRunner().invoke(cli, ["species", "list"])
        assert r.exit_code == 0
        for name in expand_sweeps(catalog):
            assert name in r.output
