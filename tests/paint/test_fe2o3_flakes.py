"""Iron-oxide-coated mica, the flakes gold and golden-pearl paints are made of (issue #35 items 4 and 6):
``mica-fe2o3-pearl`` (muscovite | 65 nm hematite, bronze) and ``mica-tio2-fe2o3-gold`` (muscovite | 52 nm
rutile | 8 nm hematite, a gold pearl).

Guards against: the species' stack reaching the optics other than as written (checked against a nested
Airy / Rouard recursion written here, independent of flakedb's characteristic matrices); the coating's
thickness spread averaged wrongly (checked against a brute-force Gauss-Hermite average); a coating that does
not absorb the blue (the flake must be warm: bronze / gold hue, absorptance in the blue several times that in
the red); a species that does not compose into a paint, or whose paint is not warmer than the white pearl's.
"""

import copy
import textwrap

import numpy as np
import pytest

from flakedb.colour.colorimetry import XYZ_to_Lab, reflectance_to_XYZ, white_XYZ
from flakedb.paint.catalog import get_species, load_catalog
from flakedb.paint.materials import refractive_index
from flakedb.paint.species import binder_index, film_stack, flake_reflectance_transmittance

FE = ("mica-fe2o3-pearl", "mica-tio2-fe2o3-gold")
WL = np.arange(380.0, 781.0, 25.0)
COS = np.array([1.0, 0.8, 0.5, 0.2])


@pytest.fixture(scope="module")
def catalog():
    return load_catalog()


def _without_spreads(entry):
    e = copy.deepcopy(entry)
    for f in e["coating"]:
        f.pop("thickness_rel_sd", None)
    e["substrate"].pop("thickness_rel_sd", None)
    return e


def _scaled_coating(entry, factor):
    """The entry, spreads dropped, every coating film's thickness times ``factor`` (the substrate kept)."""
    e = _without_spreads(entry)
    for f in e["coating"]:
        f["thickness_nm"]["value"] = float(f["thickness_nm"]["value"]) * factor
    return e


def _rouard(n_films, d_nm, wl, cos, n_b):
    """Unpolarised (R, T), each (W, A), of a film stack between two half-spaces of the binder by the nested
    Airy (Rouard) recursion: the stack below each interface replaced by its effective Fresnel coefficients,
    from the exit face up (Born & Wolf §1.6.5; Heavens, Optical Properties of Thin Solid Films, §4.5).
    ``n_films`` (W, F) complex (k >= 0), ``d_nm`` (F,), ``cos`` (A,) the cosine in the binder."""
    nb = np.asarray(n_b, float)[:, None] + 0j                     # (W, 1)
    kx2 = nb**2 * (1.0 - cos**2)[None, :]                          # (n sin θ)², invariant (Snell)
    media = [nb] + [n_films[:, j:j + 1] for j in range(n_films.shape[1])] + [nb]
    q = []
    for m in media:  # n cos θ in each medium, the decaying branch
        x = np.sqrt(m**2 - kx2)
        q.append(np.where(x.imag < 0, -x, x))
    out = []
    for pol in "sp":
        def rt(i, j):
            if pol == "s":
                den = q[i] + q[j]
                return (q[i] - q[j]) / den, 2 * q[i] / den
            ni2, nj2 = media[i]**2, media[j]**2
            den = nj2 * q[i] + ni2 * q[j]
            return (nj2 * q[i] - ni2 * q[j]) / den, 2 * media[i] * media[j] * q[i] / den
        last = len(media) - 1
        r, t = rt(last - 1, last)
        for m in range(last - 1, 0, -1):  # film m (media index) between m-1 above and the stack below
            e = np.exp(2j * np.pi * q[m] * d_nm[m - 1] / wl[:, None])
            r01, t01 = rt(m - 1, m)
            den = 1 + r01 * r * e * e
            r, t = (r01 + r * e * e) / den, t01 * t * e / den
        out.append((np.abs(r)**2, np.abs(t)**2))  # same real medium both sides: T = |t|² for s and p
    return 0.5 * (out[0][0] + out[1][0]), 0.5 * (out[0][1] + out[1][1])


@pytest.mark.parametrize("name", FE)
def test_flake_is_the_stack_by_nested_airy(catalog, name):
    # two exact methods in double precision: their difference is rounding of ~10 operations per film
    # (7 films, a few hundred flops), amplified by the recursion's denominators |1 + r r' e²| >= ~0.3 here:
    # ~1e-14; 1e-12 bounds it with margin and is far below any physics (the Fe2O3 films move R by > 0.1)
    # The catalogue's mica is incoherent (substrate.coherence; tests/optics/test_incoherent_substrate.py checks
    # that against the coherent flake averaged over the mica's thickness): this test is of the coherent stack.
    e = _without_spreads(get_species(name, catalog))
    e["substrate"].pop("coherence")
    nb = binder_index(catalog, WL)
    R, T = flake_reflectance_transmittance(e, WL, COS, nb)
    mats, d = film_stack(e)
    assert "Fe2O3-hematite-powder" in mats
    n = np.stack([refractive_index(m, WL) for m in mats], axis=1)
    Rr, Tr = _rouard(n, d, WL, COS, nb)
    np.testing.assert_allclose(R, Rr, rtol=0, atol=1e-12)
    np.testing.assert_allclose(T, Tr, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", FE)
def test_spread_average_is_gauss_hermite(catalog, name):
    # the catalogue's 8 % log-normal spread on the coating (both faces, all films together: film_spreads'
    # group 0): flakedb's trapezoid in z against an 80-node Gauss-Hermite rule over the same z ~ N(0, 1).
    # Quadrature, not rounding, sets the tolerance.  Measured (mica-fe2o3-pearl): at cos >= 0.5 they agree to
    # 5e-14; at cos 0.2 to 9e-9 (flakedb's default 31 nodes; 6.7e-11 with 61+, where Gauss-Hermite 40 vs 80
    # itself moves 2e-8: the integrand is least smooth there).  Bounds: 1e-12 and 1e-7, against the
    # spread's own effect on R of > 1e-3.
    e = get_species(name, catalog)
    nb = binder_index(catalog, WL)
    R, T = flake_reflectance_transmittance(e, WL, COS, nb)
    sd = float(e["coating"][0]["thickness_rel_sd"]["value"])
    assert all(float(f["thickness_rel_sd"]["value"]) == sd for f in e["coating"])
    s = np.sqrt(np.log1p(sd**2))
    x, w = np.polynomial.hermite.hermgauss(80)
    Rb = np.zeros_like(R)
    Tb = np.zeros_like(T)
    for xi, wi in zip(x, w / np.sqrt(np.pi)):
        Ri, Ti = flake_reflectance_transmittance(_scaled_coating(e, np.exp(s * np.sqrt(2) * xi - s * s / 2)),
                                                 WL, COS, nb)
        Rb += wi * Ri
        Tb += wi * Ti
    near = COS >= 0.5
    for got, ref in ((R, Rb), (T, Tb)):
        np.testing.assert_allclose(got[:, near], ref[:, near], rtol=0, atol=1e-12)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-7)
    Rflat, _ = flake_reflectance_transmittance(_without_spreads(e), WL, COS, nb)
    assert np.abs(Rflat - R).max() > 1e-3  # the spread matters, so the comparison sees it


def _lab(spectrum, wl):
    return XYZ_to_Lab(reflectance_to_XYZ(spectrum, wl), white=white_XYZ(wl))


def _normal_colours(entry, catalog, mica_rel_sd=0.0):
    """Lab of the flake's reflectance and transmittance at normal incidence in the binder (D65 / 2°), and its
    absorptance at 450 and 650 nm; ``mica_rel_sd`` > 0 averages over the mica's thickness (the catalogue
    leaves it 0 and treats the natural mica as incoherent instead, the limit of a broad spread: the spread then
    changes nothing, the mica being lossless)."""
    wl = np.arange(380.0, 781.0, 10.0)
    e = copy.deepcopy(entry)
    if mica_rel_sd:
        e["substrate"]["thickness_rel_sd"] = {"value": mica_rel_sd, "source": "test: a spread on the mica"}
    R, T = flake_reflectance_transmittance(e, wl, [1.0], binder_index(catalog, wl))
    A = 1.0 - R[:, 0] - T[:, 0]
    return _lab(R[:, 0], wl), _lab(T[:, 0], wl), A[wl == 450.0][0], A[wl == 650.0][0]


def _hue_deg(lab):
    return float(np.degrees(np.arctan2(lab[2], lab[1])))


def test_iron_oxide_pearl_is_bronze(catalog):
    """Hematite absorbs below ~550 nm: the flake takes the blue (absorptance at 450 nm > 3x that at 650 nm),
    and what it reflects and transmits at normal incidence is warm.  Measured (docs/flakes.md): the catalogue
    flake (incoherent mica) reflects hue 47° (a* +19, b* +20), bronze, as the coherent flake over a 0.3 spread
    of its mica does (46°; 82° with one coherent 400 nm mica); transmits hue 68°.  Gold / bronze sector taken as hue 30-100° (orange to yellow) with chroma > 15."""
    e = get_species("mica-fe2o3-pearl", catalog)
    for sd in (0.0, 0.3):
        Rlab, Tlab, a450, a650 = _normal_colours(e, catalog, sd)
        assert 30.0 < _hue_deg(Rlab) < 100.0 and np.hypot(Rlab[1], Rlab[2]) > 15.0, (sd, Rlab)
        assert 30.0 < _hue_deg(Tlab) < 100.0 and Tlab[2] > 30.0, (sd, Tlab)
        assert a450 > 3.0 * a650 > 0.0, (a450, a650)


def test_iron_oxide_top_turns_the_white_pearl_gold(catalog):
    """8 nm of hematite on the silver-white pearl: b* of its reflectance rises by > 8 (measured +14 for the
    catalogue flake, incoherent mica, as over a 0.3 spread of a coherent mica; +17 with one coherent 400 nm
    mica), the ensemble's hue becomes yellow (measured 93°; the white pearl's is achromatic, measured C* 3.6); the white pearl absorbs nothing, the gold one > 0.3 of the blue."""
    gold, white = get_species("mica-tio2-fe2o3-gold", catalog), get_species("mica-tio2-pearl", catalog)
    for sd in (0.0, 0.3):
        g, _, g450, g650 = _normal_colours(gold, catalog, sd)
        w, _, w450, _ = _normal_colours(white, catalog, sd)
        assert g[2] > w[2] + 8.0, (sd, g, w)
        assert g450 > 0.3 and g450 > 5.0 * g650 and abs(w450) < 1e-12
    g, _, _, _ = _normal_colours(gold, catalog, 0.3)
    w, _, _, _ = _normal_colours(white, catalog, 0.3)
    assert np.hypot(w[1], w[2]) < 5.0 and 70.0 < _hue_deg(g) < 110.0 and g[2] > 8.0, (g, w)


def _recipe(particles):
    return textwrap.dedent(f"""\
        flakedb: 1
        name: gold-pearl
        spectral: {{mode: spectral, range_nm: [400, 700], step_nm: 20}}
        resolution: 16
        layers:
          - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}
          - basecoat: {{thickness_um: 15, ior: 1.5, particles: [{particles}]}}
          - primer: {{color: gray}}
        """)


def test_gold_paint_composes_and_is_warmer_than_the_white_pearl(catalog):
    """A basecoat of each new species (n = 16, 16 bands) solves through the one path (check_physical: energy,
    reciprocity, positivity raise); its albedo at normal incidence, blue (400-480 nm) over red (600-700 nm),
    is below the white pearl's: the hematite takes the blue on the way in and out."""
    from flakedb.paint.recipe import parse_recipe
    from flakedb.solve.pipeline import solve_recipe
    ratio = {}
    for name in ("mica-tio2-pearl",) + FE:
        r = parse_recipe(_recipe(f"{{species: {name}, volume_fraction: 0.04}}"), catalog=catalog)
        table = solve_recipe(r, catalog=catalog).table
        a = table.albedo()[:, int(np.argmax(table.mu))]  # (16 bands,) at the node nearest normal incidence
        assert a.shape == (16,) and np.all((a > 0) & (a < 1)), (name, a)
        ratio[name] = a[:5].mean() / a[-6:].mean()
    # measured (incoherent mica): white pearl 1.03, bronze 0.24, gold 0.51; with the hematite swapped for as
    # much rutile (the interference alone) 0.65 and 0.80, which these bounds refuse (with one coherent 400 nm
    # mica, before: 1.28, 0.34, 0.66; swapped 0.84, 1.04)
    assert ratio["mica-fe2o3-pearl"] < 0.5 * ratio["mica-tio2-pearl"], ratio
    assert ratio["mica-tio2-fe2o3-gold"] < 0.65 * ratio["mica-tio2-pearl"], ratio


def test_store_builds_the_new_species_and_composes_from_them(tmp_path, catalog):
    """Both species build into a store (n = 16, 20 nm steps); a recipe with them composes from it (the CLI),
    and the solve from the store agrees with the solve from the catalogue (the store holds the same stack)."""
    from click.testing import CliRunner

    from flakedb.cli.main import cli
    from flakedb.paint.recipe import parse_recipe
    from flakedb.solve.pipeline import solve_recipe
    store = tmp_path / "S"
    r = CliRunner().invoke(cli, ["build", "--store", str(store), "--species", FE[0], "--species", FE[1],
                                 "--n", "16", "--step-nm", "20", "--workers", "1"])
    assert r.exit_code == 0, r.output
    text = _recipe(", ".join(f"{{species: {n}, volume_fraction: 0.02}}" for n in FE))
    (tmp_path / "a.yaml").write_text(text)
    out = tmp_path / "o"
    r = CliRunner().invoke(cli, ["compose", str(tmp_path / "a.yaml"), "--store", str(store), "--out", str(out)])
    assert r.exit_code == 0, r.output
    rec = parse_recipe(text, catalog=catalog)
    a_store = solve_recipe(rec, catalog=catalog, store=str(store)).table.albedo()
    a_direct = solve_recipe(rec, catalog=catalog).table.albedo()
    # the stored kernel is the direct one to 1e-5 of its scale (tests/store/test_stored.py); measured here 2.2e-7
    assert a_store.shape == a_direct.shape and np.abs(a_store - a_direct).max() <= 1e-5


@pytest.mark.slow
def test_gold_base_recovers_the_hematite_thickness(tmp_path):
    """`match` from tools/validation/gold-fe2o3.yaml: a target made by flakedb from that base with 50 nm of
    hematite (the other fields at the base's start values), fitted from 65 nm with the pearl's loading free too,
    recovers the thickness to 2 % (n = 16, E2194 geometries)."""
    import yaml
    from click.testing import CliRunner

    from flakedb.cli.main import cli
    root = __import__("pathlib").Path(__file__).resolve().parents[2]
    doc = yaml.safe_load((root / "tools" / "validation" / "gold-fe2o3.yaml").read_text(encoding="utf-8"))
    ps = doc["layers"][1]["basecoat"]["particles"]
    assert [p["species"] for p in ps] == ["metallic", "iron-oxide-red-transparent", "mica-fe2o3-pearl"]

    def fixed(node):  # every {fit: ..., start: s} at its start value
        if isinstance(node, dict):
            return node["start"] if "fit" in node else {k: fixed(v) for k, v in node.items()}
        return [fixed(v) for v in node] if isinstance(node, list) else node
    truth = fixed(doc)
    truth["layers"][1]["basecoat"]["particles"][2]["coating_thickness_nm"] = 50.0
    (tmp_path / "true.yaml").write_text(yaml.safe_dump(truth))
    target = tmp_path / "target.csv"
    r = CliRunner().invoke(cli, ["compare", str(tmp_path / "true.yaml"), "--n", "16", "--write-csv", str(target),
                                 "--geometries", "e2194"])
    assert r.exit_code == 0, r.output
    base = fixed(doc)
    base["layers"][1]["basecoat"]["particles"][2].update(
        coating_thickness_nm={"fit": [27, 108], "start": 65}, volume_fraction={"fit": [0.002, 0.1], "start": 0.03})
    (tmp_path / "base.yaml").write_text(yaml.safe_dump(base))
    out = tmp_path / "out"
    r = CliRunner().invoke(cli, ["match", str(tmp_path / "base.yaml"), "--target", str(target), "--n", "16",
                                 "--out", str(out)])
    assert r.exit_code == 0, r.output
    fitted = yaml.safe_load((out / "validation-gold-fe2o3-fitted.yaml").read_text())
    p = fitted["layers"][1]["basecoat"]["particles"][2]
    assert p["coating_thickness_nm"] == pytest.approx(50.0, rel=0.02)
    assert p["volume_fraction"] == pytest.approx(0.02, rel=0.05)


@pytest.mark.parametrize("base", ["gold-fe2o3.yaml", "pearl-gold.yaml"])
def test_validation_bases_are_valid_at_start_and_bounds(catalog, base):
    """The new match bases name the new species and parse at their start values and at every bound together
    (all low, all high): `match` would refuse them before any computation otherwise."""
    import yaml

    from flakedb.paint.recipe import parse_recipe
    root = __import__("pathlib").Path(__file__).resolve().parents[2]
    doc = yaml.safe_load((root / "tools" / "validation" / base).read_text(encoding="utf-8"))
    assert {p["species"] for p in doc["layers"][1]["basecoat"]["particles"]} & set(FE)

    def at(node, pick):
        if isinstance(node, dict):
            return pick(node) if "fit" in node else {k: at(v, pick) for k, v in node.items()}
        return [at(v, pick) for v in node] if isinstance(node, list) else node
    for pick in (lambda f: f["start"], lambda f: f["fit"][0], lambda f: f["fit"][1]):
        parse_recipe(yaml.safe_dump(at(doc, pick)), catalog=catalog)
