"""Compose from the precomputed store (issues #5/#6; flakedb/rt/stored.py, flakedb/paint/mapping.py, flakedb compose
--store): guards against a store grid that is not the solver's inside node set below a smooth coat, a
stored kernel that is not kernel_Ergun / the pigment kernel (wrong factor, wrong node or channel
mapping), compressed factors whose kernel error exceeds the compression error, a store-backed compose
that differs from the direct one, a corrupted chunk that compose lets through or that leaves outputs,
and a store of another n or η used silently.

Tolerances are measured (n = 16, m = 17, 6 bands 500-600 nm, rank 8):
* stored raw kernel vs kernel_Ergun on the same R(c) table, at the stored φ_k: 8e-16 relative (asserted
  1e-10); between the φ_k the kernel is the trigonometric interpolant of the m samples (2.5e-4 at m = 17);
* store-backed compose (raw) vs direct compose, max |Δf| / max f of the reflection at the nodes:
  4.5e-5 (metallic), 6.2e-5 (cadmium-yellow) (asserted 3e-4): the store tabulates R(c) on 2049 nodes
  uniform in angle and interpolates in φ, the direct path on an adaptive c grid (1e-3 tolerance);
  CIEDE2000 of the report's colours ≤ 0.001;
* compressed (rank 8) vs raw compose: 1.5e-4 (metallic), 6.2e-4 (cadmium-yellow) (asserted 3e-3);
  ΔE00 ≤ 0.012.
"""

import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from flakedb.bsdf import open_bsdf
from flakedb.cli.main import cli
from flakedb.colour.colorimetry import delta_E_2000
from flakedb.compose.orchestrate import compose
from flakedb.paint import species as sp
from flakedb.paint.recipe import parse_recipe
from flakedb.pipelines.build import build, make_request
from flakedb.rt.microflake import FlakeOptics, _halfvector_terms, flake_ndf_Beckmann, kernel_Ergun, pigment_kernel_Ergun
from flakedb.rt.quadrature import default_tir_nodes, radau_hemisphere, snell_mapped_quadrature
from flakedb.rt.stored import StoredFlakeMedium, StoredGridMismatch, StoredPigmentMedium
from flakedb.store import compress as C
from flakedb.store import versions as st

N, M = 16, 17
WL = (500.0, 520.0, 540.0, 560.0, 580.0, 600.0)
ETA = 1.5
FLAKE, PIGMENT = "metallic", "cadmium-yellow"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    url = str(tmp_path_factory.mktemp("stored") / "store")
    req = make_request(species=[FLAKE, PIGMENT], n=N, m=M, rank=8, wavelength_nm=WL, store_raw=True, eta_top=ETA)
    res = build(req, url, scheduler="sync")
    assert res["status"] == "built"
    return url, req, st.open_version(url)


def _inside_nodes(n=N, eta=ETA):
    q = radau_hemisphere(n // 2)
    return snell_mapped_quadrature(q, eta, default_tir_nodes(q.h, eta))


def _recipe(species, ior=ETA, name=None, extra=""):
    return f"""flakedb: 1
name: {name or 't-' + species}
spectral: {{mode: spectral, range_nm: [{WL[0]:g}, {WL[-1]:g}], step_nm: 20}}
resolution: {N}
layers:
  - clearcoat: {{thickness_um: 40, ior: {ior}, roughness: 0}}
  - basecoat:
      thickness_um: 15
      ior: {ior}
      particles:
        - {{species: {species}, volume_fraction: 0.05{extra}}}
  - primer: {{color: gray}}
"""


def test_grid_is_the_solvers_inside_node_set(tiny):
    mu, _ = C.grid_nodes(N, M, ETA)
    assert np.array_equal(mu, _inside_nodes().full()[0]) and mu.size > N
    assert np.array_equal(C.grid_nodes(N, M)[0], radau_hemisphere(N // 2).full()[0])
    assert np.array_equal(C.grid_nodes(N, M, 1.0)[0], C.grid_nodes(N, M)[0])
    with pytest.raises(ValueError, match="eta_top"):
        C.grid_nodes(N, M, 0.8)
    url, req, v = tiny
    assert v.eta_top == ETA and np.array_equal(v.grid(N)[0], mu)
    assert v.raw(FLAKE, N).shape == (len(WL), mu.size, mu.size, M)
    # eta_top enters the content hash
    assert st.plan_build(req).version != st.plan_build(make_request(
        species=[FLAKE, PIGMENT], n=N, m=M, rank=8, wavelength_nm=WL, store_raw=True, eta_top=1.4)).version


def _same_table_optics(entry):
    """FlakeOptics on exactly the R(c) table the store interpolates (flakedb.store.compress)."""
    c = np.cos(np.linspace(0.5 * np.pi, 0.0, C.DEFAULT_N_TABLE))
    c[0] = 0.0
    R, T = sp.flake_reflectance_transmittance(entry, np.array(WL), c, np.full(len(WL), ETA))
    return FlakeOptics(c, R, T)


def test_stored_flake_kernel_is_kernel_Ergun(tiny):
    url, req, v = tiny
    x = _inside_nodes().x
    mu_o = np.concatenate([-x, x])
    _, phi = v.grid(N)
    alpha, a_rho = 0.2, 0.7
    args = (x[:, None, None], mu_o[None, :, None], phi[None, None, :])
    direct = kernel_Ergun(*args, alpha, _same_table_optics(req.species[FLAKE]), a_rho)
    raw = StoredFlakeMedium(alpha, a_rho, v.stored_reflectance(FLAKE, N, raw=True), None, None)
    k_raw = raw.kernel(*args)
    assert k_raw.shape == direct.shape
    assert np.abs(k_raw - direct).max() <= 1e-10 * np.abs(direct).max()
    # compressed: exactly (aρ/2) D (R̂ − R) away from the raw kernel, i.e. within the compression error
    comp = StoredFlakeMedium(alpha, a_rho, v.stored_reflectance(FLAKE, N), None, None)
    k_c = comp.kernel(*args)
    R, Rhat = v.raw(FLAKE, N), v.reflectance(FLAKE, N)
    h = x.size
    o_idx = np.concatenate([np.arange(h - 1, -1, -1), np.arange(h, 2 * h)])  # grid index of −x_1 … −x_h, x_1 … x_h
    sub = np.ix_(range(len(WL)), range(h, 2 * h), o_idx, range(M))
    dmu, _, two_f = _halfvector_terms(*args)
    d = flake_ndf_Beckmann(np.where(two_f > 0, dmu / np.sqrt(np.where(two_f > 0, two_f, 1.0)), 0.0), alpha)
    expect = 0.5 * a_rho * (Rhat[sub] - R[sub]) * d[None]
    assert np.abs((k_c - k_raw) - expect).max() <= 1e-10 * np.abs(k_raw).max()
    assert 0 < np.abs(k_c - k_raw).max() <= 0.5 * a_rho * np.abs(Rhat - R).max() * d.max() * (1 + 1e-9)


def test_stored_pigment_kernel_is_rho_csca_p(tiny):
    url, req, v = tiny
    entry = req.species[PIGMENT]
    ct = np.cos(np.linspace(np.pi, 0.0, C.DEFAULT_N_TABLE))
    ct[0], ct[-1] = -1.0, 1.0
    # per channel block, as the build's tasks do: the log-normal Mie quadrature depends on the set of
    # wavelengths evaluated together (measured: 9e-5 relative between blocks and one batch)
    cb = req.channel_block
    pos = [sp.pigment_optics(entry, np.array(WL[k:k + cb]), np.full(len(WL[k:k + cb]), ETA), mu=ct)
           for k in range(0, len(WL), cb)]
    po = type("PO", (), {a: np.concatenate([np.asarray(getattr(o, a)) for o in pos])
                         for a in ("c_ext_um2", "c_sca_um2", "phase_function")})
    rho = 3.0e-3
    ph = np.asarray(po.phase_function)
    phase = lambda c: np.stack([np.interp(c, ct, row) for row in ph])
    x = _inside_nodes().x
    mu_o = np.concatenate([-x, x])
    _, phi = v.grid(N)
    args = (x[:, None, None], mu_o[None, :, None], phi[None, None, :])
    direct = pigment_kernel_Ergun(*args, rho, po.c_sca_um2, phase)
    src = v.stored_reflectance(PIGMENT, N, raw=True, weights=rho * np.asarray(po.c_ext_um2))
    med = StoredPigmentMedium(src, rho * np.asarray(po.c_ext_um2), rho * np.asarray(po.c_sca_um2))
    assert np.abs(med.kernel(*args) - direct).max() <= 1e-10 * np.abs(direct).max()
    assert med.sigma_t(x).shape == (len(WL), x.size)


def test_nodes_off_the_grid_are_refused(tiny):
    url, req, v = tiny
    src = v.stored_reflectance(FLAKE, N)
    x = radau_hemisphere(N // 2).x  # the grid of a stack without a smooth coat
    with pytest.raises(StoredGridMismatch, match="not a node of the stored grid.*flakedb build"):
        src.evaluate(x[:, None, None], np.concatenate([-x, x])[None, :, None], np.zeros((1, 1, 3)))


def _f(res):
    return res.stack.eval_nodes(np.linspace(0.0, np.pi, 9))


def _lab(res):
    return np.array([[g["L"], g["a"], g["b"]] for g in res.report["geometries"]])


@pytest.mark.parametrize("species", [FLAKE, PIGMENT])
def test_store_backed_compose_matches_direct(tiny, tmp_path, species):
    url, req, v = tiny
    rec = parse_recipe(_recipe(species))
    direct = compose(rec, tmp_path / "d")
    raw = compose(rec, tmp_path / "r", store=url, raw=True)
    comp = compose(rec, tmp_path / "c", store=url)
    fd = _f(direct)
    scale = np.abs(fd).max()
    assert np.abs(_f(raw) - fd).max() <= 3e-4 * scale
    assert np.abs(_f(comp) - _f(raw)).max() <= 3e-3 * scale
    assert delta_E_2000(_lab(raw), _lab(direct)).max() < 0.01
    assert delta_E_2000(_lab(comp), _lab(direct)).max() < 0.05
    h5 = open_bsdf(Path(comp.paths["h5"]))
    assert h5.metadata["store_version"] == v.version and h5.metadata["raw"] is False
    assert v.version in comp.report["store"] and "compressed" in comp.report["store"]
    assert open_bsdf(Path(direct.paths["h5"])).metadata["store_version"] == "none: computed directly"


@pytest.fixture(scope="module")
def tiny_visible(tmp_path_factory):
    """The pigment over the recipes' full visible grid (380–780 nm, 20 nm): the RGB mode's blue
    channel phase function goes negative there (over 14 % of cos Θ), unlike on the 500–600 nm grid."""
    url = str(tmp_path_factory.mktemp("stored-vis") / "store")
    from flakedb.colour.colorimetry import spectral_grid

    req = make_request(species=[PIGMENT], n=N, m=M, rank=8, wavelength_nm=spectral_grid((380, 780), 20),
                       store_raw=True, eta_top=ETA)
    assert build(req, url, scheduler="sync")["status"] == "built"
    return url


def test_rgb_mode_pigment_store_compose_matches_direct(tiny_visible, tmp_path, monkeypatch):
    """RGB mode: the direct path (flakedb.paint.mapping.pigment_to_rgb) clips the pigment's RGB phase function
    at 0 (the sRGB map's negative lobes) and C_sca at C_ext; the store path maps the stored spectral
    series linearly and must apply the same constraints (flakedb.paint.mapping._stored_pigment_component,
    StoredPigmentMedium.nonnegative).  Measured (n = 16, 380–780 nm / 20 nm): ΔE00 raw vs direct
    1.2e-3 with the clip, 0.83 without it; compressed vs direct 0.021."""
    from flakedb.rt import stored as S

    url = tiny_visible
    rec = parse_recipe(_recipe(PIGMENT).replace("range_nm: [500, 600]", "range_nm: [380, 780]")
                       .replace("mode: spectral", "mode: rgb"))
    assert rec.wavelength_nm[0] == 380 and rec.mode == "rgb"
    direct = compose(rec, tmp_path / "d")
    raw = compose(rec, tmp_path / "r", store=url, raw=True)
    comp = compose(rec, tmp_path / "c", store=url)
    assert delta_E_2000(_lab(raw), _lab(direct)).max() < 0.01
    assert delta_E_2000(_lab(comp), _lab(direct)).max() < 0.06
    # without the phase clip the two paths differ visibly (what this test guards against)
    monkeypatch.setattr(S.StoredPigmentMedium, "kernel", lambda self, mi, mo, ph:
                        self.R_source.evaluate(mi, mo, ph) / (4.0 * np.pi))
    unclipped = compose(rec, tmp_path / "u", store=url, raw=True)
    assert delta_E_2000(_lab(unclipped), _lab(direct)).max() > 0.3


def test_cli_compose_store_raw_and_corrupted_chunk(tiny, tmp_path):
    url0, req, v = tiny
    rp = tmp_path / "r.yaml"
    rp.write_text(_recipe(FLAKE, name="cli"))
    out = tmp_path / "ok"
    r = CliRunner().invoke(cli, ["compose", str(rp), "--out", str(out), "--store", url0, "--raw"])
    assert r.exit_code == 0, r.output
    assert open_bsdf(out / "cli.h5").metadata["store_url"] == url0
    url = str(tmp_path / "copy")
    shutil.copytree(url0, url)
    key = f"species/{FLAKE}/n{N}_m{M}/U_pairs/c/0/0/0"
    p = Path(url) / "versions" / v.version / key
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0xFF
    p.write_bytes(bytes(data))
    bad = tmp_path / "bad"
    r = CliRunner(env={"FLAKEDB_STORE": url}).invoke(cli, ["compose", str(rp), "--out", str(bad)])
    assert r.exit_code != 0 and "failed verification" in r.output and key in r.output
    assert not bad.exists() or not any(bad.iterdir())


def test_store_of_another_n_or_eta_is_refused(tiny, tmp_path):
    url, req, v = tiny
    rp = tmp_path / "r.yaml"
    rp.write_text(_recipe(FLAKE, name="other"))
    r = CliRunner().invoke(cli, ["compose", str(rp), "--out", str(tmp_path / "o"), "--store", url, "--n", "12"])
    assert r.exit_code != 0 and "n = 12" in r.output and f"(n, m) [({N}, {M})]" in r.output
    assert "flakedb build" in r.output and "--n 12 --eta-top 1.5" in r.output and not (tmp_path / "o").exists()
    rp.write_text(_recipe(FLAKE, ior=1.3, name="other"))
    r = CliRunner().invoke(cli, ["compose", str(rp), "--out", str(tmp_path / "o"), "--store", url])
    assert r.exit_code != 0 and "η = 1.3" in r.output and "eta_top 1.5" in r.output
    assert "--eta-top 1.3" in r.output


def test_recipe_without_catalogue_species_needs_no_store(tmp_path):
    text = f"""flakedb: 1
name: custom
spectral: {{mode: spectral, range_nm: [{WL[0]:g}, {WL[-1]:g}], step_nm: 20}}
resolution: 8
layers:
  - clearcoat: {{thickness_um: 40, ior: 1.5, roughness: 0}}
  - basecoat:
      thickness_um: 10
      ior: 1.5
      particles:
        - {{custom: {{kind: medium, albedo: 0.9, phase: isotropic}}, optical_depth: 0.5}}
  - primer: {{color: gray}}
"""
    rp = tmp_path / "c.yaml"
    rp.write_text(text)
    r = CliRunner().invoke(cli, ["compose", str(rp), "--out", str(tmp_path / "o"), "--store",
                                 str(tmp_path / "no-such-store")])
    assert r.exit_code == 0, r.output
    assert "none needed" in r.output
