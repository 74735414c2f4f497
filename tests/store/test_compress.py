"""flakedb.store.compress: guards against a wrong R(μ_i, μ_o, φ_d) grid (wrong flake cosine, broken
reciprocity, a pigment R that does not integrate to its albedo), a pair expansion that is not the
square of the rank-r √R approximation (a missing factor 2 off the diagonal, a lost singular value),
Fourier factors that do not give R's cosine coefficients, an NMF that is not deterministic or goes
negative, and storage arithmetic that disagrees with the paper's 61.04 / 11.04 MiB."""

import json

import numpy as np
import pytest

from figures.figure4 import figure4
from flakedb.paint import catalog as cat
from flakedb.paint import species as sp
from flakedb.rt.basis.fourier import cosine_coefficients
from flakedb.store import compress as C
from tests import tolerances as tol

N, M = 8, 17


@pytest.fixture(scope="module")
def catalog():
    return cat.load_catalog()


@pytest.fixture(scope="module")
def grids(catalog):
    allsp = cat.expand_sweeps(catalog)
    wl = np.array([550.0])
    nb = sp.binder_index(catalog, wl)
    return {name: C.sample_reflectance(allsp[name], wl, nb, N, M, n_table=513)[0]
            for name in ("metallic", "pearlescent", "gray-mirror", "cadmium-yellow")}


# --- the sampled function ---------------------------------------------------------------------


def test_grid_nodes_refuse_odd_n():
    with pytest.raises(ValueError, match="even"):
        C.grid_nodes(7, 16)
    mu, phi = C.grid_nodes(8, 5)
    assert np.all(mu[:4] < 0) and np.all(mu[4:] > 0) and mu[-1] == 1.0
    assert phi[0] == 0.0 and phi[-1] == pytest.approx(np.pi)


def test_flake_cosine_against_explicit_vectors(catalog):
    """R on the grid equals the flake R at c = |ω_o − ω_i|/2 built from 3-D propagation vectors."""
    entry = cat.get_species("pearlescent", catalog)
    wl = np.array([450.0, 650.0])
    nb = sp.binder_index(catalog, wl)
    R = C.sample_reflectance(entry, wl, nb, N, M, n_table=4097)
    mu, phi = C.grid_nodes(N, M)
    s = np.sqrt(1 - mu**2)
    wi = np.stack([s, np.zeros_like(mu), -mu], -1)[:, None, None, :]
    wo = np.stack([s[:, None] * np.cos(phi), s[:, None] * np.sin(phi), -np.broadcast_to(mu[:, None], (N, M))], -1)[None]
    c = np.linalg.norm(wo - wi, axis=-1) / 2
    direct, _ = sp.flake_reflectance_transmittance(entry, wl, c.ravel(), nb)
    assert np.max(np.abs(direct.reshape(R.shape) - R)) < 2e-4  # table interpolation error only
    # reciprocity of the flake reflection: R(μ_i, μ_o, φ) = R(−μ_o, −μ_i, φ)
    flipped = R[:, ::-1, ::-1].swapaxes(1, 2)
    np.testing.assert_allclose(flipped, R, rtol=0, atol=1e-12)


def test_mirror_flake_is_its_albedo(grids):
    assert np.all(grids["gray-mirror"] == 0.5)


def test_pigment_R_integrates_to_albedo(catalog):
    """R = 4π ϖ p: (1/4π) ∫ R dω_o = ϖ for every incident node (phase function normalised to 1)."""
    entry = cat.get_species("cadmium-yellow", catalog)
    wl = np.array([550.0])
    nb = sp.binder_index(catalog, wl)
    n, m = 24, 129
    R = C.sample_reflectance(entry, wl, nb, n, m, n_table=1025)[0]
    from flakedb.rt.basis.quadrature import radau_hemisphere

    _, w = radau_hemisphere(n // 2).full()
    dphi = np.pi / (m - 1)
    phi_int = 2 * dphi * (R.sum(-1) - 0.5 * (R[..., 0] + R[..., -1]))  # ∫_0^{2π} by the trapezoid rule
    total = (phi_int * w[None, :]).sum(1) / (4 * np.pi)
    po = sp.pigment_optics(entry, wl, nb)
    albedo = po.c_sca_um2[0] / po.c_ext_um2[0]
    np.testing.assert_allclose(total, albedo, rtol=2e-2)


# --- compression ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["metallic", "pearlescent", "cadmium-yellow"])
def test_full_rank_is_exact(grids, name):
    R = grids[name]
    f = C.sqrt_svd_compress(R, M)  # min(n², m) = m
    assert f.U_pairs.shape == (N * N, M * (M + 1) // 2) and f.V_pairs.shape == (M * (M + 1) // 2, M)
    # full-rank SVD of √R: backward error γ_{n²+m}‖√R‖₂ (Golub & Van Loan §8.6), squared (2√R δ), √ and the pairs' products
    S2 = np.linalg.norm(np.sqrt(R).reshape(N * N, M), 2)
    tol.assert_within(C.reconstruct(f.U_pairs, f.V_pairs, N), R, 2 * np.sqrt(R) * tol.gamma(N * N + M) * S2
                      + tol.product_tol(f.U_pairs, f.V_pairs, evaluations=1, extra_ops=3).reshape(R.shape))
    A, B = C.svd_compress(R, M)
    tol.assert_within((A @ B).reshape(R.shape), R, tol.gamma(N * N + M) * np.linalg.norm(R.reshape(N * N, M), 2)
                      + tol.product_tol(A, B, evaluations=1).reshape(R.shape))  # SVD backward error and the product


@pytest.mark.parametrize("rank", [1, 3, 8])
def test_pairs_are_the_square_of_the_sqrt_approximation(grids, rank):
    R = grids["pearlescent"].reshape(N * N, M)
    U, s, Vt = np.linalg.svd(np.sqrt(R), full_matrices=False)
    B = (U[:, :rank] * s[:rank]) @ Vt[:rank]
    f = C.sqrt_svd_compress(R, rank)
    assert f.U_pairs.shape[1] == rank * (rank + 1) // 2
    np.testing.assert_allclose(f.U_pairs @ f.V_pairs, B * B, rtol=0, atol=1e-12 * R.max())
    assert np.all(f.U_pairs @ f.V_pairs >= -1e-15)


def test_error_decreases_with_rank(grids):
    for name in ("metallic", "pearlescent", "cadmium-yellow"):
        R = grids[name]
        sq = np.sqrt(R.reshape(N * N, M))
        fro, mre = [], []
        for r in range(1, 9):
            f = C.sqrt_svd_compress(R, r)
            Rh = C.reconstruct(f.U_pairs, f.V_pairs)
            fro.append(np.linalg.norm(sq - np.sqrt(np.clip(Rh, 0, None))))
            mre.append(C.mean_relative_error(R, Rh))
        assert np.all(np.diff(fro) < 0), (name, fro)
        assert np.all(np.diff(mre) <= 1e-15), (name, mre)


def test_fourier_factors_give_the_cosine_coefficients(grids):
    R = grids["metallic"]
    f = C.sqrt_svd_compress(R, 4)
    F = C.fourier_factors(f.V_pairs)
    coef = C.reconstruct_fourier(f.U_pairs, F, N)
    direct = cosine_coefficients(C.reconstruct(f.U_pairs, f.V_pairs, N))
    np.testing.assert_allclose(coef, direct, rtol=0, atol=1e-13)
    # the cosine series synthesises the samples back, R̂(φ_k) = Σ_l a_l cos(l φ_k)
    _, phi = C.grid_nodes(N, M)
    synth = coef @ np.cos(np.arange(M)[:, None] * phi[None, :])
    np.testing.assert_allclose(synth, C.reconstruct(f.U_pairs, f.V_pairs, N), rtol=0, atol=1e-13)
    # at full rank: R's own coefficients
    g = C.sqrt_svd_compress(R, M)
    np.testing.assert_allclose(C.reconstruct_fourier(g.U_pairs, C.fourier_factors(g.V_pairs), N),
                               cosine_coefficients(R), rtol=0, atol=1e-12)


def test_nmf_deterministic_nonnegative_and_exact_for_rank_one():
    rng = np.random.default_rng(1)
    a, b = rng.random(40) + 0.1, rng.random(12) + 0.1
    R = np.outer(a, b)
    W, H = C.nmf_compress(R, 1, n_iter=300)
    W2, H2 = C.nmf_compress(R, 1, n_iter=300)
    assert np.array_equal(W, W2) and np.array_equal(H, H2)
    assert W.min() >= 0 and H.min() >= 0
    assert C.mean_relative_error(R, W @ H) < 1e-6
    Rr = rng.random((50, 20))
    e = [C.mean_relative_error(Rr, np.dot(*C.nmf_compress(Rr, 3, n_iter=k))) for k in (1, 200)]
    assert e[1] < e[0]


def test_mean_relative_error_definition():
    assert C.mean_relative_error([1.0, 2.0, 0.0], [1.1, 2.0, 5.0]) == pytest.approx(0.05)
    with pytest.raises(ValueError):
        C.mean_relative_error([0.0, 0.0], [1.0, 1.0])


def test_storage_matches_the_paper():
    s = C.storage_bytes(200, 200, 8, "float64")
    assert s["k"] == 36
    assert round(s["raw_MiB"], 2) == 61.04 and round(s["compressed_MiB"], 2) == 11.04
    assert round(s["ratio"], 2) == 5.53
    assert C.storage_bytes(200, 200, 8, "float32")["raw_MiB"] == pytest.approx(30.52, abs=0.01)


def test_figure4_writes_plot_and_table(tmp_path, catalog):
    t = figure4(tmp_path, species=("metallic", "cadmium-yellow"), n=8, m=16, ranks=range(1, 5), nmf_iter=50,
                  catalog=catalog)
    assert (tmp_path / "figure4.png").stat().st_size > 1000
    doc = json.loads((tmp_path / "figure4.json").read_text())
    assert doc["ranks"] == [1, 2, 3, 4] and set(doc["errors"]) == {"metallic", "cadmium-yellow"}
    for rows in t["errors"].values():
        assert rows["sqrt_svd"][-1] < rows["sqrt_svd"][0]
        assert all(np.isfinite(rows["nmf"]))
