"""The Fourier `.bsdf` / HDF5 BSDF files (flakedb.bsdf) and `flakedb info`.

Bugs these tests guard against:
- a reader that disagrees with layerlab's (wrong Catmull-Rom weights or tangent scaling, the zero
  nodes mishandled, Y/R/B mixed up, the wrong clamping, pdf normalised by the wrong cdf entry):
  every array of the layerlab reference npz files and the README's values are reproduced;
- a writer whose file layerlab/pbrt would refuse or misread (header fields, offsets not
  contiguous in e = o + i·N, the size formula, K_e != 0 on zero-node entries, a cdf that is not the
  spec's Catmull-Rom integral, truncation not the spec's rule), checked by re-reading, by
  re-writing layerlab's files byte for byte, and by an independent slow implementation of the
  spec's formulas written here;
- importance sampling that does not draw with density `pdf` (chi-square test with a negative
  control that must be rejected), weights that do not average to the albedo, an analytic
  Lambertian case (pdf = |mu_o|/pi, weight = rho exactly);
- HDF5 files that lose precision, channels, metadata or the delta term; non-atomic writes;
  corrupt files accepted silently; `flakedb info` crashing or exiting 0 on a bad file.
"""

import json
import os
import struct

import numpy as np
import pytest
from click.testing import CliRunner
from scipy import stats

from flakedb.bsdf import (
    BSDFFileError,
    BSDFTable,
    bsdf_file_size,
    catmull_rom_cdf,
    catmull_rom_weights,
    format_metadata,
    insert_zero_nodes,
    open_bsdf,
    parse_metadata,
    read_bsdf,
    read_h5,
    write_bsdf,
    write_h5,
)
from flakedb.bsdf.h5file import h5_filters

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "..", "shared", "data", "bsdf-files")
if not os.path.isdir(DATA):  # the shared data folder sits beside the checkout
    DATA = "/work/shared/data/bsdf-files"
FILES = ["carpaint_rgb_n100", "coated_diffuse_mono_n200"]


@pytest.fixture(scope="module", params=FILES)
def ref(request):
    name = request.param
    path = os.path.join(DATA, name + ".bsdf")
    if not os.path.exists(path):
        pytest.skip(f"reference file {path} not available")
    return name, read_bsdf(path), np.load(os.path.join(DATA, name + "_reader_reference.npz"))


@pytest.fixture(scope="module")
def carpaint():
    path = os.path.join(DATA, "carpaint_rgb_n100.bsdf")
    if not os.path.exists(path):
        pytest.skip("reference file not available")
    return read_bsdf(path)


# ------------------------------------------------------------------------------------------------
# Slow, obviously-correct scalar implementations of the spec's formulas (independent of the module)
# ------------------------------------------------------------------------------------------------
def slow_weights(nodes, x):
    """pbrt-v3 CatmullRomWeights, transcribed literally (scalar)."""
    n = len(nodes)
    if not (nodes[0] <= x <= nodes[-1]):
        return 0, [0.0] * 4
    idx = max(i for i in range(n) if nodes[i] <= x)
    idx = min(max(idx, 0), n - 2)
    x0, x1 = nodes[idx], nodes[idx + 1]
    t = (x - x0) / (x1 - x0)
    t2, t3 = t * t, t * t * t
    w = [0.0, 2 * t3 - 3 * t2 + 1, -2 * t3 + 3 * t2, 0.0]
    if idx > 0:
        w0 = (t3 - 2 * t2 + t) * (x1 - x0) / (x1 - nodes[idx - 1])
        w[0] = -w0
        w[2] += w0
    else:
        w0 = t3 - 2 * t2 + t
        w[0] = 0
        w[1] -= w0
        w[2] += w0
    if idx + 2 < n:
        w3 = (t3 - t2) * (x1 - x0) / (nodes[idx + 2] - x0)
        w[1] -= w3
        w[3] = w3
    else:
        w3 = t3 - t2
        w[1] -= w3
        w[2] += w3
        w[3] = 0
    return idx - 1, w


def slow_cdf(x, v):
    """The spec's cdf recursion, one segment at a time."""
    n = len(x)
    out = [0.0]
    for k in range(n - 1):
        w = x[k + 1] - x[k]
        d0 = w * (v[k + 1] - v[k - 1]) / (x[k + 1] - x[k - 1]) if k > 0 else v[k + 1] - v[k]
        d1 = w * (v[k + 2] - v[k]) / (x[k + 2] - x[k]) if k + 2 < n else v[k + 1] - v[k]
        out.append(out[-1] + w * ((v[k] + v[k + 1]) / 2 + (d0 - d1) / 12))
    return np.array(out)


def gauss_nodes(h):
    """h nodes per hemisphere in (0, 1] with a node at 1 (like the solver's Gauss-Radau rule)."""
    x = np.append((np.polynomial.legendre.leggauss(h - 1)[0] + 1) / 2 * 0.98, 1.0)
    return np.concatenate([-x[::-1], x])


def synthetic_table(h=8, L=14, channels=3, seed=0):
    """A smooth analytic f·|mu_o| with orders that vary per entry (many near the mirror direction)."""
    mu = gauss_nodes(h)
    mi, mo = np.meshgrid(mu, mu, indexing="ij")
    near = np.exp(-(mi + mo) ** 2 / 0.05)                      # mirror: mu_o = -mu_i
    r = 0.15 + 0.6 * near                                      # decay ratio of the orders
    base = np.abs(mo) * (0.3 + 0.2 * mi ** 2 + 2.0 * near) * np.where(mi * mo < 0, 1.0, 0.3)
    ell = np.arange(L)
    a = base[..., None] * r[..., None] ** ell * np.cos(0.3 * ell)       # some negative orders
    tint = np.array([1.0, 0.7, 0.4, 0.9, 0.2])[:channels]
    coeffs = tint[:, None, None, None] * a[None]
    coeffs[..., 1:] *= (1 + 0.1 * np.arange(channels))[:, None, None, None]
    return BSDFTable(mu=mu, coeffs=coeffs, eta=1.5, alpha=(0.1, 0.25),
                     delta={"kind": "fresnel", "eta": 1.5} if channels == 3 else None,
                     metadata={"recipe": "synthetic test paint", "flakedb_version": "0.1.0", "n": h},
                     channels=None)


def table_rgb_values(table, i, o, phi):
    """What eval must return at nodes (i, o): the table's series summed, R, G, B (or mono x3)."""
    v = np.einsum("cl,pl->pc", table.coeffs[:, i, o], np.cos(np.outer(phi, np.arange(table.coeffs.shape[-1]))))
    return np.repeat(v, 3, axis=1) if v.shape[1] == 1 else v


# ------------------------------------------------------------------------------------------------
# The layerlab reference files
# ------------------------------------------------------------------------------------------------
class TestLayerlabReference:
    def test_nodes_cdf_albedo(self, ref):
        _, b, r = ref
        np.testing.assert_array_equal(b.nodes, r["nodes"])
        np.testing.assert_array_equal(b.cdf[:, -1], r["cdf_last"])
        np.testing.assert_allclose(b.albedo_nodes(), r["albedo_from_cdf"], rtol=1e-7, atol=1e-9)

    def test_eval_random(self, ref):
        _, b, r = ref
        p, want = r["random_points"], r["eval_random_rgb"]
        got = b.eval(p[:, 0], p[:, 1], p[:, 2])
        assert got.shape == want.shape
        assert np.max(np.abs(got - want)) <= 1e-6 * np.max(np.abs(want))

    def test_eval_and_pdf_grid(self, ref):
        _, b, r = ref
        g, ph = r["mu_grid"], r["phi_grid"]
        args = (g[:, None, None], -g[None, :, None], ph[None, None, :])   # reflection: mu_o = -mu_grid
        want = r["eval_grid_rgb"]
        got = b.eval(*args)
        assert got.shape == want.shape
        assert np.max(np.abs(got - want)) <= 1e-6 * np.max(np.abs(want))
        want = r["pdf_grid"]
        assert np.max(np.abs(b.pdf(*args) - want)) <= 1e-6 * np.max(want)

    def test_pdf_random(self, ref):
        _, b, r = ref
        p, want = r["random_points"], r["pdf_random"]
        assert np.max(np.abs(b.pdf(p[:, 0], p[:, 1], p[:, 2]) - want)) <= 1e-6 * np.max(want)

    def test_series(self, ref):
        _, b, r = ref
        sp, want = r["series_points"], r["series_channel0"]
        got = b.series(sp[:, 0], sp[:, 1])[:, 0, :]
        assert got.shape == want.shape
        assert np.max(np.abs(got - want)) <= 1e-6 * np.max(np.abs(want))
        np.testing.assert_allclose(b.series(sp[:, 0], sp[:, 1], "sampling"), got, rtol=0, atol=0)

    def test_numpy_reference_path_equals_numba(self, ref):
        _, b, r = ref
        rng = np.random.default_rng(5)
        mi, mo, ph = rng.uniform(-1, 1, 600), rng.uniform(-1, 1, 600), rng.uniform(0, 2 * np.pi, 600)
        mo[:300] = -mi[:300] + rng.normal(0, 0.02, 300)                     # near the mirror peak
        for fn in (b.eval, b.pdf):
            a, c = fn(mi, mo, ph, method="numba"), fn(mi, mo, ph, method="numpy")
            assert np.max(np.abs(a - c)) <= 1e-12 * max(np.max(np.abs(a)), 1)


README_VALUES = {
    "coated_diffuse_mono_n200": [
        ((0.5, -0.5, 0), (1.460501,) * 3), ((1, -1, 0), (0.4107609,) * 3), ((0, -0.5, 0.1), (0,) * 3),
        ((0.005, -0.02, 0.3), (0,) * 3), ((0.9, -0.9, 3), (0.08303276,) * 3),
        ((-0.6, 0.4, 1), (0.06366197,) * 3)],
    "carpaint_rgb_n100": [
        ((0.5, -0.5, 0), (1.575329, 1.525992, 1.520869)), ((1, -1, 0), (0.5785176, 0.5077715, 0.5006349)),
        ((0, -0.5, 0.1), (0, 0, 0)), ((0.005, -0.02, 0.3), (-0.002230856, -0.002395813, -0.002412934)),
        ((0.9, -0.9, 3), (0.1203179, 0.0559797, 0.04984428)),
        ((-0.6, 0.4, 1), (-1.150335e-05, -1.219324e-05, -1.261841e-05))],
}


def test_readme_values(ref):
    name, b, _ = ref
    for (mi, mo, ph), want in README_VALUES[name]:
        # 7 printed digits; near grazing layerlab's float32 blend loses ~4e-8 absolute (1e-8 of the peak)
        np.testing.assert_allclose(b.eval(mi, mo, ph), want, rtol=2e-6, atol=1e-7)


def test_clamp_modes(carpaint):
    raw = carpaint.eval(0.005, -0.02, 0.3, clamp="none")
    assert np.all(raw < 0)                                    # layerlab keeps RGB ringing ...
    np.testing.assert_array_equal(carpaint.eval(0.005, -0.02, 0.3), raw)
    np.testing.assert_array_equal(carpaint.eval(0.005, -0.02, 0.3, clamp="all"), 0.0)   # ... pbrt does not


def test_broadcasting_and_out_of_range(carpaint):
    out = carpaint.eval(np.array([0.3, 0.6])[:, None, None], np.array([-0.2, -0.5, -0.9])[None, :, None],
                        np.zeros((1, 1, 4)))
    assert out.shape == (2, 3, 4, 3)
    np.testing.assert_allclose(out[1, 1, 0], carpaint.eval(0.6, -0.5, 0.0))
    bad = carpaint.eval([np.nan, 1.2, 0.5, 0.5], [-0.5, -0.5, -1.5, np.nan], 0.0)
    np.testing.assert_array_equal(bad, 0.0)
    np.testing.assert_array_equal(carpaint.pdf([np.nan, 1.2], [-0.5, -0.5], 0.0), 0.0)


# ------------------------------------------------------------------------------------------------
# Catmull-Rom machinery against literal transcriptions of the spec
# ------------------------------------------------------------------------------------------------
def test_catmull_rom_weights_match_spec():
    nodes = insert_zero_nodes(gauss_nodes(5))
    xs = np.concatenate([np.linspace(-1, 1, 57), nodes, [0.0, -1e-9, 1e-9]])
    off, w = catmull_rom_weights(nodes, xs)
    for x, o, ww in zip(xs, off, w):
        so, sw = slow_weights(list(nodes), float(x))
        np.testing.assert_allclose(ww, sw, rtol=1e-13, atol=1e-15)
        if np.any(ww != 0):
            assert o == so
    inside = (xs >= nodes[0]) & (xs <= nodes[-1])
    np.testing.assert_allclose(w[inside].sum(-1), 1.0, rtol=1e-13)       # partition of unity


def test_catmull_rom_cdf_matches_spec_and_is_exact_for_linear():
    rng = np.random.default_rng(1)
    x = insert_zero_nodes(gauss_nodes(6))
    v = rng.normal(size=(3, x.size))
    got = catmull_rom_cdf(x, v)
    for row, g in zip(v, got):
        np.testing.assert_allclose(g, slow_cdf(x, row), rtol=1e-13, atol=1e-15)
    # a linear function is integrated exactly at every node: ∫_{x_0}^{x} (2 + 3t) dt
    exact = (2 * x + 1.5 * x ** 2) - (2 * x[0] + 1.5 * x[0] ** 2)
    np.testing.assert_allclose(catmull_rom_cdf(x, 2 + 3 * x), exact, rtol=1e-13, atol=1e-14)


# ------------------------------------------------------------------------------------------------
# Writer: round trips and the spec's constraints
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("channels", [3, 1])
def test_round_trip_synthetic(tmp_path, channels):
    table = synthetic_table(channels=channels)
    path = tmp_path / "t.bsdf"
    info = write_bsdf(path, table, truncation=0)
    raw = path.read_bytes()
    n = table.n
    N = n + 2
    # header fields (spec table) and the size formula
    ident, ver, flags, nn, ncoef, nmax, nch, nbases, nmeta, npar, npv, eta, a0, a1 = struct.unpack_from(
        "<7sBIIIIIIIIIfff", raw)
    assert (ident, ver, flags, nn, nch, nbases, npar, npv) == (b"SCATFUN", 1, 1, N, channels, 1, 0, 0)
    assert raw[56:64] == bytes(8)
    assert (eta, a0, a1) == (np.float32(1.5), np.float32(0.1), np.float32(0.25))
    assert len(raw) == bsdf_file_size(N, ncoef, nmeta) == info["size"]
    assert len(raw) == 64 + 4 * (N + N * N + 2 * N * N + ncoef) + nmeta
    b = read_bsdf(path)
    # offsets contiguous in e = o + i*N, zero-node entries empty, nMaxOrder = max K
    K = b.offsets[:, 1].astype(np.int64)
    np.testing.assert_array_equal(b.offsets[:, 0], np.concatenate([[0], np.cumsum(K * channels)[:-1]]))
    assert K.sum() * channels == ncoef and K.max() == nmax
    h = n // 2
    Kq = K.reshape(N, N)
    assert not (Kq[h:h + 2].any() or Kq[:, h:h + 2].any())
    np.testing.assert_array_equal(b.nodes, insert_zero_nodes(table.mu).astype(np.float32))
    # evaluation at the quadrature nodes returns the table to float32 precision
    phi = np.linspace(0, np.pi, 7)
    peak = np.max(np.abs(table.coeffs).sum(-1))
    for i in range(n):
        for o in range(n):
            got = b.eval(table.mu[i], table.mu[o], phi, clamp="none")
            want = table_rgb_values(table, i, o, phi)
            assert np.max(np.abs(got - want)) <= 3e-6 * peak, (i, o)
    # 2π·cdf[i][N-1] is the table's albedo by the spec's integral (slow version here, channel Y)
    y = table.coeffs[:, :, :, 0]
    y = y[0] if channels == 1 else 0.212671 * y[0] + 0.715160 * y[1] + 0.072169 * y[2]
    x = insert_zero_nodes(table.mu)
    for i in range(n):
        v = np.concatenate([y[i, :h], [0, 0], y[i, h:]])
        fi = i if i < h else i + 2
        np.testing.assert_allclose(b.albedo_nodes()[fi], 2 * np.pi * slow_cdf(x, v)[-1], rtol=2e-6)
    want = table.albedo().T                                       # (n, C) in the table's channels
    np.testing.assert_allclose(b.albedo(table.mu), want if channels == 3 else np.repeat(want, 3, 1), rtol=5e-6)
    # metadata and delta come back; to_table reproduces the table to float32
    assert b.metadata == table.metadata and b.delta == table.delta
    t2 = b.to_table()
    np.testing.assert_allclose(t2.coeffs, table.coeffs, rtol=2e-6, atol=1e-7 * peak)
    np.testing.assert_allclose(t2.mu, table.mu, rtol=1e-7)


def test_default_truncation_is_the_spec_rule(tmp_path):
    table = synthetic_table(h=6, L=40, channels=3)
    write_bsdf(tmp_path / "t.bsdf", table)
    b = read_bsdf(tmp_path / "t.bsdf")
    n, h = table.n, table.n // 2
    tail = np.cumsum(np.abs(table.coeffs)[..., ::-1], axis=-1)[..., ::-1]        # Σ_{k>=j}
    tail = np.concatenate([tail, np.zeros(tail.shape[:-1] + (1,))], axis=-1)
    bound = 2e-3 * np.abs(table.coeffs[..., :1])
    truncated_somewhere = False
    for i in range(n):
        for o in range(n):
            k = b.order[i if i < h else i + 2, o if o < h else o + 2]
            assert k >= 1
            assert np.all(tail[:, i, o, k] <= bound[:, i, o, 0])                 # dropped tail is small
            if k > 1:
                assert np.any(tail[:, i, o, k - 1] > bound[:, i, o, 0])          # and K is the smallest
            truncated_somewhere |= k < table.coeffs.shape[-1]
    assert truncated_somewhere
    # at the nodes the error is bounded by the dropped tail
    got = b.eval(table.mu[3], table.mu[2], np.linspace(0, np.pi, 9), clamp="none")
    want = table_rgb_values(table, 3, 2, np.linspace(0, np.pi, 9))
    assert np.max(np.abs(got - want)) <= 2.5e-3 * np.max(np.abs(table.coeffs[:, 3, 2, 0])) + 1e-6


@pytest.mark.parametrize("kind", ["rgb", "grey", "mono", "quadrant"])
def test_truncated_file_holds_exactly_the_kept_float32_coefficients(tmp_path, kind):
    """Guards the writer's gather of the kept orders (only the first K_e orders of each entry are read and
    turned into Y, R, B): every stored coefficient is the table's, converted to the file's channels in
    float64 and cast to float32 (a slow loop over entries here), for an RGB table, a grey one (one channel
    broadcast to three, read once), a mono one and a reflection-only quadrant."""
    t = synthetic_table(h=6, L=40, channels=1 if kind in ("mono", "grey") else 3)
    if kind == "grey":
        t = BSDFTable(mu=t.mu, coeffs=np.broadcast_to(t.coeffs, (3,) + t.coeffs.shape[1:]), channels=None)
    if kind == "quadrant":
        h = t.n // 2
        t = BSDFTable(mu=t.mu, reflection=np.ascontiguousarray(t.coeffs[:, h:, :h]), channels=None)
    write_bsdf(tmp_path / "t.bsdf", t)
    b = read_bsdf(tmp_path / "t.bsdf")
    c = t.coeffs
    files = c if c.shape[0] == 1 else np.stack([0.212671 * c[0] + 0.715160 * c[1] + 0.072169 * c[2], c[0], c[2]])
    n, h, C = t.n, t.n // 2, files.shape[0]
    kept = 0
    for i in range(n):
        for o in range(n):
            e = (i if i < h else i + 2) * (n + 2) + (o if o < h else o + 2)
            K, start = int(b.offsets[e, 1]), int(b.offsets[e, 0])
            want = files[:, i, o, :K].astype(np.float32).ravel()
            np.testing.assert_array_equal(b.coeffs[start:start + C * K], want)
            kept += K
    assert 0 < kept < n * n * c.shape[-1]  # truncated, and not empty


@pytest.mark.parametrize("name", FILES)
def test_rewrite_layerlab_file(tmp_path, name):
    src = os.path.join(DATA, name + ".bsdf")
    if not os.path.exists(src):
        pytest.skip("reference file not available")
    a = read_bsdf(src)
    write_bsdf(tmp_path / "re.bsdf", a.to_table(), truncation=0)
    b = read_bsdf(tmp_path / "re.bsdf")
    raw_a, raw_b = open(src, "rb").read(), (tmp_path / "re.bsdf").read_bytes()
    assert len(raw_a) == len(raw_b)
    assert raw_a[:64] == raw_b[:64]                                  # header byte-identical
    np.testing.assert_array_equal(a.offsets, b.offsets)
    assert a.coeffs.tobytes() == b.coeffs.tobytes()                   # coefficient block byte-identical
    assert a.metadata_text == b.metadata_text
    # the cdf differs only because layerlab integrated over the double-precision nodes
    assert np.max(np.abs(a.cdf - b.cdf)) <= 1e-6 * np.max(a.cdf)


def test_lambertian_golden(tmp_path):
    """f = rho/pi in reflection on both sides: albedo = rho, pdf = |mu_o|/pi, weight = rho exactly."""
    rho = np.array([0.8, 0.5, 0.2])
    mu = gauss_nodes(10)
    mi, mo = np.meshgrid(mu, mu, indexing="ij")
    a0 = np.where(mi * mo < 0, np.abs(mo) / np.pi, 0.0)
    table = BSDFTable(mu=mu, coeffs=rho[:, None, None, None] * a0[None, :, :, None])
    write_bsdf(tmp_path / "lam.bsdf", table)
    b = read_bsdf(tmp_path / "lam.bsdf")
    Y = 0.212671 * rho[0] + 0.715160 * rho[1] + 0.072169 * rho[2]
    np.testing.assert_allclose(b.albedo_nodes()[b.nodes != 0], Y, rtol=1e-6)
    np.testing.assert_allclose(b.albedo(np.array([0.3, 0.9, -0.5])), np.tile(rho, (3, 1)), rtol=1e-5)
    rng = np.random.default_rng(2)
    x2 = mu[mu > 0][1]                                   # above x_2 the mu_i rows are all Lambertian
    m_i = rng.uniform(x2, 1, 500)
    m_o = rng.uniform(-1, 0, 500)
    ph = rng.uniform(0, 2 * np.pi, 500)
    np.testing.assert_allclose(b.eval(m_i, m_o, ph), np.abs(m_o)[:, None] * rho / np.pi, rtol=1e-5)
    np.testing.assert_allclose(b.pdf(m_i, m_o, ph), np.abs(m_o) / np.pi, rtol=1e-5)
    mo_s, ph_s, w, pdf = b.sample(0.6, rng.random(20000), rng.random(20000))
    np.testing.assert_allclose(w, np.tile(rho, (20000, 1)), rtol=1e-5)
    np.testing.assert_allclose(pdf, np.abs(mo_s) / np.pi, rtol=1e-5)
    assert np.all(mo_s <= 0)
    assert stats.kstest(mo_s ** 2, "uniform").pvalue > 1e-3          # cosine-weighted: mu_o² ~ U(0, 1)
    assert stats.kstest(ph_s / (2 * np.pi), "uniform").pvalue > 1e-3


def test_writer_refuses_and_is_atomic(tmp_path, monkeypatch):
    import flakedb.bsdf.fourier_file as mod

    t = synthetic_table(h=4, L=5, channels=3)
    with pytest.raises(ValueError, match="1 or 3 channels"):
        write_bsdf(tmp_path / "x.bsdf", synthetic_table(h=4, L=5, channels=5))
    with pytest.raises(ValueError, match="metadata key"):
        write_bsdf(tmp_path / "x.bsdf", BSDFTable(mu=t.mu, coeffs=t.coeffs, metadata={"bad key": 1}))
    assert not os.path.exists(tmp_path / "x.bsdf")
    target = tmp_path / "keep.bsdf"
    target.write_bytes(b"old")

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(mod.os, "replace", boom)
    with pytest.raises(OSError):
        write_bsdf(target, t)
    with pytest.raises(OSError):
        write_h5(tmp_path / "keep.h5", t)
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.bsdf"]     # no temp files left
    with pytest.raises(ValueError, match="no node at 0"):
        BSDFTable(mu=np.array([-0.5, 0.0, 0.2, 0.5]), coeffs=np.zeros((1, 4, 4, 1)))
    with pytest.raises(ValueError, match="linear R, G, B"):
        write_bsdf(tmp_path / "x.bsdf", BSDFTable(mu=t.mu, coeffs=t.coeffs, channels=("a", "b", "c")))
    monkeypatch.undo()
    with pytest.warns(UserWarning, match="node at mu = 1"):        # readers return 0 beyond the last node
        write_bsdf(tmp_path / "g.bsdf", BSDFTable(mu=t.mu * 0.99, coeffs=t.coeffs))


# ------------------------------------------------------------------------------------------------
# Importance sampling
# ------------------------------------------------------------------------------------------------
def chi2_test(b, mu_i, mu_o, phi, mu_i_pdf=None):
    """Pearson chi-square of samples (mu_o, phi) against n·∫pdf over (mu_o, folded phi) cells.

    mu_o cells are groups of 3 node intervals (the pdf is a cubic in mu_o on each interval, so
    4-point Gauss-Legendre per interval integrates it exactly); phi is folded to [0, π] (the BSDF is
    even in phi) in 16 cells with 24-point Gauss-Legendre each.  Cells expecting < 5 are pooled."""
    mu_i_pdf = mu_i if mu_i_pdf is None else mu_i_pdf
    nodes = np.unique(b.nodes)
    edges_mu = np.unique(np.concatenate([nodes[::3], [1.0]]))
    gx, gw = np.polynomial.legendre.leggauss(4)
    qm = ((nodes[1:] + nodes[:-1]) / 2)[:, None] + ((nodes[1:] - nodes[:-1]) / 2)[:, None] * gx
    wm = ((nodes[1:] - nodes[:-1]) / 2)[:, None] * gw
    cell_mu = np.clip(np.searchsorted(edges_mu, qm.ravel(), side="right") - 1, 0, edges_mu.size - 2)
    nphi = 16
    edges_phi = np.linspace(0, np.pi, nphi + 1)
    px, pw = np.polynomial.legendre.leggauss(24)
    hw = np.pi / nphi / 2
    qp = ((edges_phi[1:] + edges_phi[:-1]) / 2)[:, None] + hw * px
    wp = hw * pw * np.ones((nphi, 1))
    dens = b.pdf(mu_i_pdf, qm.ravel()[:, None], qp.ravel()[None, :])           # (n_mu_q, n_phi_q)
    integ = (dens * wm.ravel()[:, None] * wp.ravel()[None, :]) @ np.repeat(np.eye(nphi), 24, axis=0)
    expected = np.zeros((edges_mu.size - 1, nphi))
    np.add.at(expected, cell_mu, integ)
    expected *= 2 * mu_o.size                                                   # two halves of [0, 2π)
    folded = np.where(phi > np.pi, 2 * np.pi - phi, phi)
    obs, _, _ = np.histogram2d(mu_o, folded, bins=[edges_mu, edges_phi])
    e, o = expected.ravel(), obs.ravel()
    assert np.sum(o[e == 0]) == 0, "samples where the pdf is zero"
    small = e < 5                                               # pool sparse cells (as Mitsuba does)
    e = np.concatenate([[e[small].sum()], e[~small]])
    o = np.concatenate([[o[small].sum()], o[~small]])
    keep = e > 0
    chi = np.sum((o[keep] - e[keep]) ** 2 / e[keep])
    return stats.chi2.sf(chi, keep.sum() - 1), abs(expected.sum() / mu_o.size - 1)


def test_sampling_chi2(carpaint):
    rng = np.random.default_rng(11)
    n = 100_000
    mu_o, phi, w, pdf = carpaint.sample(0.7, rng.random(n), rng.random(n))
    assert np.all((phi >= 0) & (phi < 2 * np.pi)) and np.all(pdf > 0)
    p, mass_err = chi2_test(carpaint, 0.7, mu_o, phi)
    assert mass_err < 1e-4                                     # the pdf integrates to 1
    assert p > 1e-3, f"chi-square rejects the sampler (p = {p:.3g})"
    # negative controls: the same test must reject slightly wrong distributions
    p_wrong_mu, _ = chi2_test(carpaint, 0.7, mu_o, phi, mu_i_pdf=0.66)
    assert p_wrong_mu < 1e-6
    p_wrong_phi, _ = chi2_test(carpaint, 0.7, mu_o, np.mod(phi * 1.03, 2 * np.pi))
    assert p_wrong_phi < 1e-6
    # returned pdf and weight agree with pdf() and eval()
    np.testing.assert_allclose(pdf[:2000], carpaint.pdf(0.7, mu_o[:2000], phi[:2000]), rtol=1e-9)
    np.testing.assert_allclose(w[:2000] * pdf[:2000, None],
                               carpaint.eval(0.7, mu_o[:2000], phi[:2000], clamp="none"), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("mu_i", [0.7, 0.15, -0.5])
def test_sampling_weight_mean_is_albedo(carpaint, mu_i):
    rng = np.random.default_rng(3)
    n = 60_000
    _, _, w, _ = carpaint.sample(mu_i, rng.random(n), rng.random(n))
    mean, se = w.mean(0), w.std(0) / np.sqrt(n)
    alb = carpaint.albedo(mu_i)
    assert np.all(np.abs(mean - alb) <= 5 * se + 1e-6 * alb), (mean, alb, se)


def test_sampling_out_of_range(carpaint):
    mu_o, phi, w, pdf = carpaint.sample([1.5, np.nan, 0.0], 0.5, 0.5)
    np.testing.assert_array_equal(w, 0.0)
    np.testing.assert_array_equal(pdf, 0.0)


# ------------------------------------------------------------------------------------------------
# HDF5
# ------------------------------------------------------------------------------------------------
def test_h5_round_trip(tmp_path):
    table = synthetic_table(channels=3)
    info = write_h5(tmp_path / "t.h5", table, {"recipe_text": "layers:\n  - coat", "store_version": 2})
    assert info["size"] == os.path.getsize(tmp_path / "t.h5")
    h = read_h5(tmp_path / "t.h5")
    t2 = h.to_table()
    np.testing.assert_array_equal(t2.coeffs, table.coeffs)
    np.testing.assert_array_equal(t2.mu, table.mu)
    assert (t2.eta, t2.alpha, t2.delta, t2.channels) == (1.5, (0.1, 0.25), {"kind": "fresnel", "eta": 1.5},
                                                        ("R", "G", "B"))
    assert h.metadata["recipe_text"] == "layers:\n  - coat" and h.metadata["store_version"] == 2
    assert h.metadata["recipe"] == "synthetic test paint"
    from flakedb import __version__
    assert h.metadata["flakedb_version"] == __version__
    assert open_bsdf(tmp_path / "t.h5").kind == "h5"
    # the same evaluation as the .bsdf of the same table, up to float32
    write_bsdf(tmp_path / "t.bsdf", table, truncation=0)
    b = open_bsdf(tmp_path / "t.bsdf")
    rng = np.random.default_rng(4)
    pts = rng.uniform(-1, 1, (3, 3000))
    pts[2] *= np.pi
    e_h, e_b = h.eval(*pts), b.eval(*pts)
    assert np.max(np.abs(e_h - e_b)) <= 5e-6 * np.max(np.abs(e_h))
    assert np.max(np.abs(h.pdf(*pts) - b.pdf(*pts))) <= 5e-6 * np.max(h.pdf(*pts))
    np.testing.assert_allclose(h.albedo(table.mu), table.albedo().T, rtol=1e-12)


def test_h5_spectral(tmp_path):
    table = synthetic_table(h=6, L=10, channels=5)
    write_h5(tmp_path / "s.h5", table, {"wavelength_nm": [400, 475, 550, 625, 700]})
    h = read_h5(tmp_path / "s.h5")
    assert h.channels == ("c0", "c1", "c2", "c3", "c4")
    phi = np.linspace(0, np.pi, 5)
    np.testing.assert_allclose(h.eval(table.mu[2], table.mu[9], phi, clamp="none"),
                               table_rgb_values(table, 2, 9, phi), rtol=1e-12, atol=1e-14)
    rng = np.random.default_rng(8)
    _, _, w, _ = h.sample(0.8, rng.random(40000), rng.random(40000))
    se = w.std(0) / np.sqrt(40000)
    assert np.all(np.abs(w.mean(0) - h.albedo(0.8)) <= 5 * se + 1e-9)


# ------------------------------------------------------------------------------------------------
# Metadata text and corrupt files
# ------------------------------------------------------------------------------------------------
def test_metadata_text_round_trip():
    md = {"recipe": "silver metallic", "flakedb_version": "0.1.0", "n": 3, "x": 1.5, "s": "1.5",
          "lst": [1, 2], "multi": "a\nb=c", "none": None, "text": "free words, eta=1.5 inside"}
    text = format_metadata(md, {"kind": "fresnel", "eta": 1.5})
    lines = text.split("\n")
    assert lines[:2] == ["delta=fresnel", "delta_eta=1.5"] and "recipe=silver metallic" in lines
    assert lines[-1] == "free words, eta=1.5 inside"
    back, delta = parse_metadata(text)
    assert back == md and delta == {"kind": "fresnel", "eta": 1.5}
    with pytest.raises(ValueError):
        format_metadata({"delta": "x"}, {"kind": "fresnel", "eta": 1.5})


def test_corrupt_files_are_refused(tmp_path):
    good = os.path.join(DATA, "carpaint_rgb_n100.bsdf")
    if not os.path.exists(good):
        pytest.skip("reference file not available")
    raw = open(good, "rb").read()
    cases = {"missing.bsdf": None, "trunc.bsdf": raw[:1000], "short.bsdf": raw[:40],
             "long.bsdf": raw + b"x", "magic.bsdf": b"NOTAFUN" + raw[7:],
             "version.bsdf": raw[:7] + b"\x02" + raw[8:],
             "nbases.bsdf": raw[:28] + struct.pack("<I", 2) + raw[32:], "junk.h5": b"hello world"}
    for name, content in cases.items():
        p = tmp_path / name
        if content is not None:
            p.write_bytes(content)
        with pytest.raises(BSDFFileError, match=name):
            open_bsdf(p)


# ------------------------------------------------------------------------------------------------
# flakedb info
# ------------------------------------------------------------------------------------------------
def test_info_command(tmp_path):
    from flakedb.cli.main import cli

    table = synthetic_table(channels=3)
    write_bsdf(tmp_path / "t.bsdf", table)
    write_h5(tmp_path / "t.h5", table)
    # the synthetic table reflects more than it receives: the energy check fails, and so does info (issue 25)
    r = CliRunner().invoke(cli, ["info", str(tmp_path / "t.bsdf")])
    assert r.exit_code == 1 and "check(s) failed: energy" in r.output, r.output
    assert "nodes:         18" in r.output and "fresnel" in r.output and "synthetic test paint" in r.output
    r = CliRunner().invoke(cli, ["info", "--json", str(tmp_path / "t.h5")])
    assert r.exit_code == 1, r.output
    d = json.loads(r.stdout)
    assert d["nodes"] == 18 and d["channels"] == 3 and d["max_order"] == 14 and d["delta"]["eta"] == 1.5
    np.testing.assert_allclose(d["albedo"][0]["albedo"], read_h5(tmp_path / "t.h5").albedo(1.0), rtol=1e-12)
    r = CliRunner().invoke(cli, ["info", str(tmp_path / "nope.bsdf")])
    assert r.exit_code != 0 and "no such file" in r.output
    (tmp_path / "bad.bsdf").write_bytes((tmp_path / "t.bsdf").read_bytes()[:-3])
    r = CliRunner().invoke(cli, ["info", str(tmp_path / "bad.bsdf")])
    assert r.exit_code != 0 and "truncated" in r.output


@pytest.mark.parametrize("where", ["coeffs", "broadcast", "reflection"])
def test_table_refuses_nan_and_inf(where):
    """A BSDFTable holding NaN or inf is refused, also when its channels are one broadcast array (a grey
    table, whose check reads each stored value once)."""
    t = synthetic_table(h=4, L=5, channels=1 if where == "broadcast" else 3)
    for bad in (np.nan, np.inf):
        c = t.coeffs.copy()
        c[-1, 5, 2, 3] = bad  # in the last channel
        kw = {"coeffs": c}
        if where == "broadcast":
            kw = {"coeffs": np.broadcast_to(c, (3,) + c.shape[1:])}
        elif where == "reflection":
            kw = {"reflection": np.ascontiguousarray(c[:, 4:, :4])}
        with pytest.raises(ValueError, match="NaN or inf"):
            BSDFTable(mu=t.mu, **kw)
    BSDFTable(mu=t.mu, coeffs=np.broadcast_to(t.coeffs[:1], (3,) + t.coeffs.shape[1:]))  # finite: accepted


@pytest.mark.parametrize("reflection_only", [True, False])
def test_h5_compressed_chunks_read_back_exactly(tmp_path, reflection_only):
    """A table of mostly zeros (orders beyond each pair's count, as a rough coat's) is written compressed,
    its chunks shuffled and deflated on several threads (flakedb.bsdf.h5file.write_chunks_deflated) and stored
    with write_direct_chunk: HDF5 itself (h5py's reader and its filters) must decode every chunk to the table,
    bit for bit, as it does h5py's own compressed write of the same data."""
    import h5py

    base = synthetic_table(h=6, L=40, channels=5)
    coeffs = np.array(base.coeffs)
    ell = np.arange(coeffs.shape[-1])
    rng = np.random.default_rng(11)
    counts = rng.integers(1, 12, size=coeffs.shape[1:3])  # each pair's own order count
    coeffs[..., ell[None, None, :] >= counts[..., None]] = 0.0
    h = coeffs.shape[1] // 2
    if reflection_only:
        table = BSDFTable(base.mu, reflection=np.ascontiguousarray(coeffs[:, h:, :h]), eta=1.5)
    else:
        table = BSDFTable(base.mu, coeffs=coeffs, eta=1.5)
    assert h5_filters(table.stored)  # the compressed path is the one under test
    write_h5(tmp_path / "c.h5", table)
    with h5py.File(tmp_path / "c.h5", "r") as f:
        d = f["coeffs"]
        assert d.compression == "gzip" and d.shuffle
        got = d[...]
        with h5py.File(tmp_path / "own.h5", "w") as g:  # h5py's own filters on the same data, as a reference
            own = g.create_dataset("c", data=table.coeffs, chunks=d.chunks, **h5_filters(table.stored))[...]
    np.testing.assert_array_equal(got, table.coeffs)
    np.testing.assert_array_equal(own, got)
    np.testing.assert_array_equal(read_h5(tmp_path / "c.h5").to_table().coeffs, table.coeffs)


def test_h5_of_a_grey_table_holds_every_channel_as_its_written_out_copy(tmp_path):
    """A grey table's channels as one array (stride 0: a grey stack solved once) are deflated once and stored for
    every channel (flakedb.bsdf.h5file.write_chunks_deflated): the file's datasets are those of the same table with
    its channels written out, bit for bit, and HDF5's own filters decode every channel's chunks."""
    import h5py

    base = synthetic_table(h=6, L=40, channels=1)
    coeffs = np.array(base.coeffs)
    ell = np.arange(coeffs.shape[-1])
    counts = np.random.default_rng(5).integers(1, 12, size=coeffs.shape[1:3])
    coeffs[..., ell[None, None, :] >= counts[..., None]] = 0.0
    h = coeffs.shape[1] // 2
    q = np.ascontiguousarray(coeffs[:, h:, :h])
    grey = BSDFTable(base.mu, reflection=np.broadcast_to(q, (3,) + q.shape[1:]), eta=1.5)
    written = BSDFTable(base.mu, reflection=np.repeat(q, 3, axis=0), eta=1.5)
    assert h5_filters(grey.stored) == h5_filters(written.stored) != {}
    write_h5(tmp_path / "grey.h5", grey)
    write_h5(tmp_path / "written.h5", written)
    with h5py.File(tmp_path / "grey.h5", "r") as f, h5py.File(tmp_path / "written.h5", "r") as g:
        assert set(f) == set(g)
        for k in f:
            np.testing.assert_array_equal(f[k][...], g[k][...])
        assert f["coeffs"].id.get_num_chunks() == g["coeffs"].id.get_num_chunks() == 3 * h
    np.testing.assert_array_equal(read_h5(tmp_path / "grey.h5").to_table().coeffs, written.coeffs)


def test_reflection_only_evaluator_is_the_dense_one_without_the_dense_array(tmp_path):
    """flakedb.bsdf.evaluator.table_evaluator builds a reflection-only table's sparse layout from its quadrant
    (the full (n + 2)² × C × L array was 4x the table: a rough coat's 41-band table at n = 200 read as 4.3 GiB,
    refused by the reader's limit): the same orders, coefficients, offsets and sampling table as from the
    densified table, and an .h5 holding only that quadrant reads back as a reflection-only table."""
    from flakedb.bsdf.evaluator import table_evaluator

    base = synthetic_table(h=6, L=12, channels=5)
    h = base.n // 2
    q = np.array(base.coeffs[:, h:, :h])
    q[..., 7:] *= np.random.default_rng(2).integers(0, 2, size=q.shape[:3])[..., None]  # orders that stop early
    lean = table_evaluator(BSDFTable(base.mu, reflection=q, eta=1.5))
    dense = table_evaluator(BSDFTable(base.mu, coeffs=BSDFTable(base.mu, reflection=q).coeffs, eta=1.5))
    for name in ("order", "_flat", "_start", "cdf", "nodes", "_a0s"):
        np.testing.assert_array_equal(getattr(lean, name), getattr(dense, name), err_msg=name)
    write_h5(tmp_path / "q.h5", BSDFTable(base.mu, reflection=q, eta=1.5))
    back = read_h5(tmp_path / "q.h5").to_table()
    assert back.reflection_only
    np.testing.assert_array_equal(back.stored, q)


@pytest.mark.parametrize("truncation", [0.0, 2e-3])
def test_truncation_orders_follow_their_definition(truncation):
    """The order count K of every entry (flakedb.bsdf.fourier_file._truncation_orders; truncation 0 found from the
    last non-zero order directly) against its definition entry by entry: per channel the smallest j ≥ 1 with
    Σ_{k≥j} |a_k| ≤ truncation·|a_0|, the largest over channels, 0 where every coefficient is 0."""
    from flakedb.bsdf.fourier_file import _truncation_orders

    rng = np.random.default_rng(4)
    c = rng.standard_normal((3, 5, 6, 9)) * (rng.random((3, 5, 6, 9)) < 0.4)
    c[..., 0] += 4.0 * (rng.random((3, 5, 6)) < 0.7)
    c[:, 0, 0] = 0.0                                   # an entry with nothing
    c[:, 0, 1] = -0.0
    c[:, 1, 1, 1:] = 0.0                               # only a_0
    c[1, 2, 2, 8] = 1e-300                             # a tail of one tiny coefficient
    want = np.zeros(c.shape[1:3], dtype=int)
    for i in range(c.shape[1]):
        for o in range(c.shape[2]):
            if not np.any(c[:, i, o]):
                continue
            ks = []
            for a in c[:, i, o]:
                ks.append(next(j for j in range(1, a.size + 1) if np.abs(a[j:]).sum() <= truncation * abs(a[0])))
            want[i, o] = max(ks)
    np.testing.assert_array_equal(_truncation_orders(c, truncation), want)


@pytest.mark.parametrize("channels", ["grey", "distinct"])
def test_h5_chunks_encoded_early_write_the_same_file(tmp_path, channels):
    """Chunks encoded before the write (flakedb.bsdf.h5file.encode_chunks_early, compose's deflate beside its
    other work) are stored as the write's own encoding stores them: the same chunk bytes, the same file; an
    encoding of another table is not used."""
    import h5py

    from flakedb.bsdf.h5file import encode_chunks_early

    base = synthetic_table(h=6, L=40, channels=1 if channels == "grey" else 3)
    coeffs = np.array(base.coeffs)
    ell = np.arange(coeffs.shape[-1])
    counts = np.random.default_rng(7).integers(1, 12, size=coeffs.shape[1:3])
    coeffs[..., ell[None, None, :] >= counts[..., None]] = 0.0
    q = np.ascontiguousarray(coeffs[:, 6:, :6])
    table = BSDFTable(base.mu, reflection=np.broadcast_to(q, (3,) + q.shape[1:]) if channels == "grey" else q, eta=1.5)
    other = BSDFTable(base.mu, reflection=np.zeros_like(table.stored), eta=1.5)
    early = encode_chunks_early(table)
    assert early is not None and len(early.keys) == (1 if channels == "grey" else 3) * 6
    write_h5(tmp_path / "late.h5", table)
    write_h5(tmp_path / "early.h5", table, encoded=early)
    write_h5(tmp_path / "foreign.h5", table, encoded=encode_chunks_early(other))
    with h5py.File(tmp_path / "late.h5", "r") as f, h5py.File(tmp_path / "early.h5", "r") as g:
        d, e = f["coeffs"].id, g["coeffs"].id
        offsets = [tuple(d.get_chunk_info(k).chunk_offset) for k in range(d.get_num_chunks())]
        assert len(offsets) == 3 * 6
        assert all(d.read_direct_chunk(o) == e.read_direct_chunk(o) for o in offsets)
    late = (tmp_path / "late.h5").read_bytes()
    assert (tmp_path / "early.h5").read_bytes() == late == (tmp_path / "foreign.h5").read_bytes()
    np.testing.assert_array_equal(read_h5(tmp_path / "early.h5").to_table().coeffs, table.coeffs)
