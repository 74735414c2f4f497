"""The Mitsuba 3 sparkle route (flakedb/render/mitsuba_sparkle.py, `flakedb texture --mitsuba`,
docs/texture.md §7) rendered and checked against the texture model.

The files `flakedb texture --mitsuba` writes, loaded through its XML, on a flat 2.56 mm patch (512²
texels = pixels of 5 µm) under an orthographic camera along the normal, over a `measured` export of a
synthetic BSDF, with a directional light at 15°, 45°, 75° (the BYK-like geometries; 1 spp: each pixel
is its texel): (a) the glinting flakes per mm² (a flake whose pixels reach half the peak of an aligned
facet of its own α and gain: the model's β ≥ β_peak/2) match the model's glints_per_mm2 within 3σ
(Poisson) plus the model tolerance (the model's own hiding loss, which bounds the light path's
hiding that a normal map cannot have); (b) at the design light the patch's large-area mean equals
the `measured`-only render's within 3σ of the glints' per-flake spread + the hiding tolerance × β_ss;
(c) under a constant environment no flake reaches the glint threshold and the one-pixel luminance
spread is the model's graininess luminance_sd.  Guards: the same files with the refraction mapping
dropped (binder normals at the air surface, the route before issue #22) fail (a); a pigmented paint
keeps β_ss (the gain's extinction).  ~25 s in all.
"""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.bsdf import write_bsdf
from flakedb.cli.main import cli
from flakedb.render import mitsuba as fm
from flakedb.render.imageio import write_exr
from flakedb.render.mitsuba_sparkle import (
    FILES,
    apparent_normals,
    mapping_error_deg,
    material_xml,
    mitsuba_route,
)
from flakedb.texture.instruments import Observer
from flakedb.texture.model import graininess_indices, sparkle_indices
from tests.render.test_mitsuba import synthetic_table
from tests.texture.cases import RECIPE, stack_of

NAME = "mitsparkle"
KW = {"vf": 0.01, "alpha": 0.3, "D": 20.0, "gsd": 1.3, "d": 15.0}
SPOT_UM, TEXEL_UM, SIZE = 6.0, 5.0, 512   # the CLI: 512² texels of min(5 µm, spot); one texel per pixel
SOURCE_DEG, APERTURE_DEG = 12.0, 1e-3
LIGHTS = (15.0, 45.0, 75.0)
LUM = np.array([0.2126, 0.7152, 0.0722])   # linear sRGB → Y


def scene_xml(include, light_deg=None, size=SIZE, spp=1, material="flakedb_sparkle", crop=None):
    """Orthographic camera over the patch, along the normal; a directional light (irradiance 1 normal
    to the beam) at light_deg on the +x side, or a constant environment of radiance 1."""
    half = 0.5 * SIZE * TEXEL_UM * 1e-3
    if light_deg is None:
        emitter = '<emitter type="constant"><rgb name="radiance" value="1"/></emitter>'
        integ = ('<integrator type="direct"><integer name="emitter_samples" value="1"/>'
                 '<integer name="bsdf_samples" value="1"/></integrator>')
    else:
        t = np.radians(light_deg)
        emitter = (f'<emitter type="directional"><vector name="direction" x="{-np.sin(t):.12g}" y="0" '
                   f'z="{-np.cos(t):.12g}"/><rgb name="irradiance" value="1"/></emitter>')
        integ = ('<integrator type="direct"><integer name="emitter_samples" value="1"/>'
                 '<integer name="bsdf_samples" value="0"/></integrator>')
    return f"""<scene version="3.0.0">
    {include}
    {integ}
    <sensor type="orthographic">
        <transform name="to_world"><scale x="{half}" y="{half}"/><lookat origin="0,0,1" target="0,0,0" up="0,1,0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm"><integer name="width" value="{size}"/><integer name="height" value="{size}"/>
            <rfilter type="box"/><string name="pixel_format" value="rgb"/>{crop_xml(size, crop)}</film>
    </sensor>
    <shape type="rectangle"><transform name="to_world"><scale x="{half}" y="{half}"/></transform><ref id="{material}"/></shape>
    {emitter}
</scene>"""


def crop_xml(size, crop):
    """A central crop×crop window of the film (None: the whole film)."""
    if crop is None:
        return ""
    o = (size - crop) // 2
    return "".join(f'<integer name="{k}" value="{v}"/>' for k, v in
                   (("crop_offset_x", o), ("crop_offset_y", o), ("crop_width", crop), ("crop_height", crop)))


@pytest.fixture(scope="module")
def mi():
    mi = pytest.importorskip("mitsuba")
    mi.set_variant("scalar_rgb")
    mi.set_log_level(mi.LogLevel.Warn)
    return mi


def render_y(mi, path, spp=1, seed=0, **params):
    """Luminance image in the texture's row order (Mitsuba shows the bitmap's rows bottom-up)."""
    img = np.array(mi.render(mi.load_file(str(path), **params), seed=seed, spp=spp))
    return np.flipud(img[..., :3] @ LUM)


@pytest.fixture(scope="module")
def route(tmp_path_factory, mi):
    d = tmp_path_factory.mktemp("mitsparkle")
    write_bsdf(d / "base.bsdf", synthetic_table(delta=False))
    measured = fm.export_measured(d / "base.bsdf", d / "base.measured.tensor", res=16, n_theta=6)["out"]
    base_inc = f'<bsdf type="measured" id="base"><string name="filename" value="{measured}"/></bsdf>'
    base = {}
    for la in LIGHTS:   # the measured-only route: uniform over the patch, one 8² render each
        p = d / f"base{la:g}.xml"
        p.write_text(scene_xml(base_inc, la, size=8, material="base"))
        base[la] = float(render_y(mi, p).mean())
    p = d / "base-env.xml"
    p.write_text(scene_xml(base_inc, None, size=8, spp=64, material="base"))
    base["env"] = float(render_y(mi, p, spp=64).mean())
    ground = np.pi * base[LIGHTS[0]] / np.cos(np.radians(LIGHTS[0]))   # luminance factor π L/(E cos θ_l)
    rec = d / f"{NAME}.yaml"
    rec.write_text(RECIPE.format(name=NAME, species="metallic", pigment="", **KW))
    res = CliRunner().invoke(cli, ["texture", str(rec), "--spot-um", str(SPOT_UM), "--aperture-deg", str(APERTURE_DEG),
                                   "--source-deg", str(SOURCE_DEG), "--light-deg", str(LIGHTS[0]), "--json",
                                   "--mitsuba", str(d), "--mitsuba-ground", repr(float(ground))])
    assert res.exit_code == 0, res.output
    for v in FILES.values():
        assert (d / v.format(name=NAME)).is_file()
    stack = stack_of(**KW)
    obs = Observer("mitsuba-test", SPOT_UM, float(np.radians(APERTURE_DEG)), SOURCE_DEG, LIGHTS, 0.0)
    r = mitsuba_route(stack, obs, SIZE, TEXEL_UM, ground_luminance_factor=ground, seed=0)   # what the CLI wrote
    inc = f'<include filename="{d / FILES["xml"].format(name=NAME)}"/>'
    assert np.allclose(read_exr(d / FILES["gain"].format(name=NAME)), r["gain"], rtol=1e-6, atol=1e-9)
    return {"dir": d, "base": base, "ground": ground, "stack": stack, "obs": obs, "r": r, "inc": inc, "measured": measured}


def read_exr(path):
    import OpenEXR  # lazy: only this check reads images
    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["RGB"].pixels, float)


def render_route(mi, route, light_deg, name="route", spp=1, crop=None):
    p = route["dir"] / f"{name}{'env' if light_deg is None else f'{light_deg:g}'}.xml"
    p.write_text(scene_xml(route["inc"], light_deg, spp=spp, crop=crop))
    return render_y(mi, p, spp=spp, measured=route["measured"])


def glint_count(y, base_y, r, light_deg):
    """Glinting flakes in a rendered patch: flakes with a pixel whose glint-layer radiance (the render
    minus (1 − s) × the measured-only render) reaches half the aligned-facet peak of an unattenuated
    flake of its kind, surface gain/(4π α² cos θ_a) (E = 1; Beckmann D(0) = 1/(πα²)).  Returns (count, ids of the glinting flakes)."""
    g = r["layer"]
    excess = y - (1.0 - r["weight"]) * base_y
    peak = g["surface_gain_y"] / (4.0 * np.pi * g["alpha"] ** 2 * g["normal"][..., 2])
    hit = g["exits"] & (excess >= 0.5 * peak)
    ids = np.unique(r["map"]["flake_id"][hit])
    return ids.size, ids


def model_tolerance(stack, obs, light_deg):
    """The model's counts include hiding on both paths; the normal map hides on the view path only
    (the top-most flake): bounded by the model's whole hiding loss, 1 − N_g(φ)/(20 N_g(φ/20))."""
    thin = stack_of(**{**KW, "vf": KW["vf"] / 20})
    a, b = sparkle_indices(stack, obs, light_deg), sparkle_indices(thin, obs, light_deg)
    return a, 1.0 - a["glints_per_mm2"] / (20.0 * b["glints_per_mm2"])


def test_mapping_is_exact_for_a_normal_view_and_its_error_off_it():
    # along the normal (either side) the mapped normal is the air half-vector to rounding
    for la in LIGHTS:
        assert mapping_error_deg(1.5, la, 0.0) < 1e-5
        assert mapping_error_deg(1.5, 0.0, la) < 1e-5
    # off it the error grows (measured: light 45° view 15°: 1.04°; light 75° view 15°: 5.6°)
    assert 0.5 < mapping_error_deg(1.5, 45.0, 15.0) < 2.0 < mapping_error_deg(1.5, 75.0, 15.0) < 8.0
    # closed form: tilt ½ asin(η sin 2θ_b); TIR beyond η sin 2θ_b = 1
    th = np.radians(np.array([5.0, 15.0, 20.0, 21.0]))
    n = np.stack([np.sin(th), 0 * th, np.cos(th)], axis=-1)
    a, ok = apparent_normals(n, 1.5)
    assert np.allclose(np.arccos(a[:3, 2]), 0.5 * np.arcsin(1.5 * np.sin(2 * th[:3])), atol=1e-12)
    assert ok.tolist() == [True, True, True, False]


def test_glint_layer_area_ratio_matches_the_mapping():
    """α² = J d½²/(4c ln 2) uses the area ratio J = c η² μ_l'/(μ_l cos θ_a) of the binder-normal →
    air-half-vector map; check J against the numerical Jacobian of apparent_normals."""
    eta, tb, h = 1.5, np.radians(12.0), 1e-6
    def tilt(t):
        return np.arccos(apparent_normals(np.array([np.sin(t), 0.0, np.cos(t)]), eta)[0][2])
    ta = tilt(tb)
    J_num = (np.sin(ta) / np.sin(tb)) * (tilt(tb + h) - tilt(tb - h)) / (2 * h)
    J = np.cos(tb) * eta**2 * np.cos(2 * tb) / (np.cos(2 * ta) * np.cos(ta))
    assert J_num == pytest.approx(J, rel=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("light_deg", LIGHTS)
def test_glints_per_mm2_match_the_model(mi, route, light_deg):
    r = route["r"]
    y = render_route(mi, route, light_deg)
    n, ids = glint_count(y, route["base"][light_deg], r, light_deg)
    m, hide = model_tolerance(route["stack"], route["obs"], light_deg)
    area_mm2 = (SIZE * TEXEL_UM * 1e-3) ** 2
    expect = m["glints_per_mm2"] * area_mm2
    print(f"light {light_deg}: {n} glints vs model {expect:.1f} (hiding tolerance {hide:.3f})")
    assert expect > 15
    assert abs(n - expect) <= 3.0 * np.sqrt(expect) + hide * expect
    # the glinting flakes lean toward the light (+x): the map's orientation in Mitsuba is right
    nb = r["map"]["normal"][np.isin(r["map"]["flake_id"], ids)]
    assert np.all(nb[..., 0] > 0)


@pytest.mark.slow
def test_without_the_refraction_mapping_the_counts_fail(mi, route, tmp_path):
    """The route before issue #22 (binder normals at the air surface) fails the count check of (a)."""
    d, r = route["dir"], route["r"]
    broken = d / "broken"
    broken.mkdir(exist_ok=True)
    for k in ("alpha", "gain"):
        (broken / FILES[k].format(name=NAME)).write_bytes((d / FILES[k].format(name=NAME)).read_bytes())
    write_exr(broken / FILES["normals"].format(name=NAME), 0.5 * (r["map"]["normal"] + 1.0))
    (broken / FILES["xml"].format(name=NAME)).write_text((d / FILES["xml"].format(name=NAME)).read_text())
    rb = dict(route, dir=broken, inc=f'<include filename="{broken / FILES["xml"].format(name=NAME)}"/>')
    light = 15.0
    y = render_route(mi, rb, light)
    layer = dict(r["layer"], normal=r["map"]["normal"])
    n, _ = glint_count(y, route["base"][light], dict(r, layer=layer), light)
    m, hide = model_tolerance(route["stack"], route["obs"], light)
    expect = m["glints_per_mm2"] * (SIZE * TEXEL_UM * 1e-3) ** 2
    print(f"broken route, light {light}: {n} glints vs model {expect:.1f}")
    assert abs(n - expect) > 3.0 * np.sqrt(expect) + hide * expect


ENV_SPP, ENV_CROP = 64, 160


def mean_sigma(y, r):
    """Large-area mean of y and its standard error from the per-flake spread (the glints carry the
    variance: Var = Σ_k (Σ_pixels of flake k y)² / N²)."""
    ids = r["map"]["flake_id"]
    base = np.median(y[ids < 0])
    ex = y - base
    per = np.bincount(ids[ids >= 0], weights=ex[ids >= 0])
    return float(y.mean()), float(np.sqrt(np.sum(per**2)) / y.size)


@pytest.mark.slow
def test_large_area_mean_keeps_the_measured_route(mi, route):
    """(b) At the design light the blend's mean equals the measured-only render within 3σ of the
    glints' spread + the hiding tolerance × β_ss (the glint layer carries β_ss, the weight removes it)."""
    la = LIGHTS[0]
    y = render_route(mi, route, la)
    mean, sig = mean_sigma(y, route["r"])
    m, hide = model_tolerance(route["stack"], route["obs"], la)
    k = np.pi / np.cos(np.radians(la))   # radiance → luminance factor
    rel = k * (mean - route["base"][la]) / route["ground"]
    bound = (3.0 * k * sig + hide * m["flake_luminance_factor"]) / route["ground"]
    print(f"mean bias {rel:+.4f} of M = {route['ground']:.4f} (bound {bound:.4f}; β_ss {m['flake_luminance_factor']:.4f})")
    assert abs(rel) <= bound


@pytest.mark.slow
def test_glints_vanish_under_a_constant_environment(mi, route):
    """(c) Under a uniform sky (radiance 1) each flake adds its gain × the conductor's albedo (≤ 1) to
    the luminance factor: graininess only (its spread the model's), nowhere near the model's glint threshold β_peak/2 (β_peak ≥ 1
    for sparkle, docs/texture.md §3.3).  Per-flake means over its pixels: the blend picks the glint layer
    with probability s, so one pixel at 64 spp has σ ≈ (gain/s) √(s(1 − s)/64) ≈ 0.3."""
    r = route["r"]
    y = render_route(mi, route, None, spp=ENV_SPP, crop=ENV_CROP)
    o = (SIZE - ENV_CROP) // 2
    win = np.s_[o:o + ENV_CROP, o:o + ENV_CROP]   # a central crop: the same rows after the flip
    g = {k: v[win] for k, v in r["layer"].items()}
    ids = r["map"]["flake_id"][win]
    excess = y - (1.0 - r["weight"]) * route["base"]["env"]   # luminance factor (sky radiance 1)
    sel = g["exits"]
    npx = np.bincount(ids[sel])
    keep = npx >= 4
    mean_ex = np.bincount(ids[sel], weights=excess[sel])[keep] / npx[keep]
    mean_gain = np.bincount(ids[sel], weights=g["gain_y"][sel])[keep] / npx[keep]
    assert keep.sum() > 100
    peak = sparkle_indices(route["stack"], route["obs"], LIGHTS[0])["peak_luminance_factor"]
    assert peak >= 1.0 and np.all(mean_ex < 0.5 * peak)
    # what is left is the flakes' own mirror albedo: the layer's excess over its gain, on average
    ratio = mean_ex.sum() / mean_gain.sum()
    print(f"env: excess/gain {ratio:.4f}, max flake excess {mean_ex.max():.3f}, model peak {peak:.3g}")
    assert 0.8 < ratio < 1.0 + 3.0 / np.sqrt(keep.sum())
    # graininess: the luminance-factor spread of one-pixel spots over the whole patch (the render's
    # expectation: (1 − s) × the measured-only sky render + gain × the measured albedo) against the
    # model's luminance_sd for a spot of one texel (docs/texture.md §4); allowed: 3/√(visible flakes)
    # (the spread's sampling error, one flake ≈ one independent draw) + the model's hiding loss
    full = (1.0 - r["weight"]) * route["base"]["env"] + ratio * r["layer"]["gain_y"]
    spot = Observer("pixel", TEXEL_UM, float(np.radians(APERTURE_DEG)), SOURCE_DEG, LIGHTS, 0.0)
    model = graininess_indices(route["stack"], spot, ground_luminance_factor=float(full.mean()))
    n_vis = np.unique(r["map"]["flake_id"][r["layer"]["exits"]]).size
    _, hide = model_tolerance(route["stack"], route["obs"], LIGHTS[0])
    print(f"graininess: render luminance sd {full.std():.4f} vs model {model['luminance_sd']:.4f} ({n_vis} flakes)")
    assert full.std() == pytest.approx(model["luminance_sd"], rel=3.0 / np.sqrt(n_vis) + hide)


def test_cli_mitsuba_ground_is_checked_and_the_fallback_weight_says_so(tmp_path):
    rec = tmp_path / f"{NAME}.yaml"
    rec.write_text(RECIPE.format(name=NAME, species="metallic", pigment="", **KW))
    res = CliRunner().invoke(cli, ["texture", str(rec), "--observer", "byk-mac-like", "--mitsuba", str(tmp_path / "m"),
                                   "--mitsuba-ground", "-1"])
    assert res.exit_code != 0 and "--mitsuba-ground -1" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "m").exists()
    # --flakes-only: no composed BSDF, so no ground: the fallback weight (without it the BSDF grounds the blend)
    res = CliRunner().invoke(cli, ["texture", str(rec), "--observer", "byk-mac-like", "--mitsuba", str(tmp_path / "m"),
                                   "--flakes-only"])
    assert res.exit_code == 0, res.output
    p = json.loads((tmp_path / "m" / FILES["params"].format(name=NAME)).read_text())["mitsuba"]
    assert p["weight_basis"].startswith("covered fraction") and 0 < p["blend_weight"] < 1
    assert p["design_light_deg"] == 15.0 and p["texel_um"] == 5.0
    assert sorted(x.name for x in (tmp_path / "m").iterdir()) == sorted(v.format(name=NAME) for v in FILES.values())


@pytest.mark.slow
def test_pigment_extinction_is_in_the_glint_gain(mi, route, tmp_path):
    """With an absorbing pigment (iron black, 0.004) the glint layer's mean is still the model's β_ss
    (e^{−τ} along both paths from each flake's depth, eq. S1), within 3σ of the per-flake spread + the
    hiding tolerance; without the extinction it would be 0.18 against 0.10."""
    kw = {**KW, "pigment": "iron-black", "pv": 0.004}
    stack = stack_of(**kw)
    assert stack.absorbers
    la = LIGHTS[0]
    r = mitsuba_route(stack, route["obs"], SIZE, TEXEL_UM, ground_luminance_factor=route["ground"], seed=0)
    for k in ("normals", "alpha", "gain"):
        write_exr(tmp_path / FILES[k].format(name="pig"), r[k])
    (tmp_path / FILES["xml"].format(name="pig")).write_text(material_xml("pig", TEXEL_UM, SIZE, r["weight"]))
    rp = dict(route, dir=tmp_path, inc=f'<include filename="{tmp_path / FILES["xml"].format(name="pig")}"/>')
    y = render_route(mi, rp, la)
    mean, sig = mean_sigma(y, r)
    k = np.pi / np.cos(np.radians(la))
    layer = k * (mean - (1.0 - r["weight"]) * route["base"][la])
    thin = stack_of(**{**kw, "vf": KW["vf"] / 20})
    m, m_thin = sparkle_indices(stack, route["obs"], la), sparkle_indices(thin, route["obs"], la)
    hide = 1.0 - m["flake_luminance_factor"] / (20.0 * m_thin["flake_luminance_factor"])
    print(f"pigment: layer β_ss {layer:.4f} ± {k * sig:.4f} vs model {m['flake_luminance_factor']:.4f}")
    assert abs(layer - m["flake_luminance_factor"]) <= 3.0 * k * sig + hide * m["flake_luminance_factor"]
