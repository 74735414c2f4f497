"""Gamut mapping of tabulated BSDFs (flakedb.colour.gamut, docs/gamut.md).

Guards against: negative channels left in an RGB file; a mapping that changes luminance (the
sampling channel and the energy balance), breaks reciprocity (different factors for a pair and its
reciprocal), touches in-gamut pairs, or raises a channel's albedo above 1; working-space matrices
that do not keep a flat spectrum grey or that disagree with the RGB mode's sRGB map.
"""

import numpy as np
import pytest

from flakedb.colour import gamut
from flakedb.colour.colorimetry import spectra_to_rgb_matrix, spectral_grid

WL = spectral_grid((380, 780), 10)


@pytest.mark.parametrize("space", list(gamut.RGB_SPACES))
def test_spaces_keep_a_flat_spectrum_grey_and_luminance_weights_sum_to_one(space):
    M = gamut.spectra_to_space_matrix(WL, space)
    np.testing.assert_allclose(np.full(WL.size, 0.37) @ M, [0.37] * 3, rtol=1e-12)
    w = gamut.luminance_weights(WL, space)
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    # luminance in the space = Y of the spectrum
    from flakedb.colour.colorimetry import reflectance_to_XYZ
    spec = np.linspace(0.1, 0.9, WL.size)
    assert (spec @ M) @ w == pytest.approx(reflectance_to_XYZ(spec, WL)[1], rel=1e-10)
    # the RGB mode's sRGB → space map agrees with going through the spectrum
    T = gamut.rgb_mode_to_space_matrix(WL, space)
    np.testing.assert_allclose((spec @ spectra_to_rgb_matrix(WL)) @ T, spec @ M, rtol=1e-10, atol=1e-12)


def test_srgb_is_the_rgb_mode_map():
    np.testing.assert_array_equal(gamut.spectra_to_space_matrix(WL, "srgb"), spectra_to_rgb_matrix(WL))


def _reciprocal_table(rng, n=8, L=5):
    """Coefficients (3, n, n, L) of f·|mu_o| with f(i, o) = f(n-1-o, n-1-i) (reflection reciprocity),
    saturated so that the blue channel is negative at some pairs."""
    mu = np.concatenate([-np.linspace(0.9, 0.1, n // 2), np.linspace(0.1, 0.9, n // 2)])
    f = rng.random((3, n, n, L)) * np.array([1.0, 0.5, 0.3, 0.1, 0.05])
    f = 0.5 * (f + f[:, ::-1, ::-1].transpose(0, 2, 1, 3))                # reciprocal
    f[2] -= 0.35 * f[0]                                                   # push blue out of gamut
    return mu, f * np.abs(mu)[None, None, :, None], f


def test_desaturation_keeps_luminance_reciprocity_and_removes_negatives():
    rng = np.random.default_rng(1)
    mu, c, _ = _reciprocal_table(rng)
    w = gamut.luminance_weights(WL, "srgb")
    mapped, s = gamut.desaturate_to_gamut(c, w, n_phi=32)
    assert (s < 1).any() and (s == 1).any()
    np.testing.assert_allclose(np.einsum("k,k...->...", w, mapped), np.einsum("k,k...->...", w, c), atol=1e-14)
    np.testing.assert_array_equal(s, s[::-1, ::-1].T)
    g = mapped / np.abs(mu)[None, None, :, None]
    np.testing.assert_allclose(g, g[:, ::-1, ::-1].transpose(0, 2, 1, 3), atol=1e-13)   # still reciprocal
    keep = s == 1
    np.testing.assert_array_equal(mapped[:, keep], c[:, keep])                          # in gamut untouched
    phi = np.linspace(0, np.pi, 32)
    v = mapped @ np.cos(np.arange(c.shape[-1])[:, None] * phi[None, :])
    Y = np.einsum("k,k...->...", w, v)
    assert v[:, Y > 0].min() >= -1e-15 and mapped[..., 0].min() >= -1e-15
    # a channel lies between its value and the luminance: never above max(c, Y)
    Yc = np.einsum("k,k...->...", w, c)
    assert np.all(mapped <= np.maximum(c, Yc[None]) + 1e-15)


def test_points_desaturation():
    w = gamut.luminance_weights(WL, "srgb")
    rgb = np.array([[0.6, 0.3, -0.05], [0.2, 0.2, 0.2], [-0.1, -0.1, -0.1]])
    out = gamut.desaturate_points(rgb, w)
    assert out.min() >= 0 and out[0, 2] == pytest.approx(0, abs=2 * gamut.GAMUT_MARGIN)
    assert out[0] @ w == pytest.approx(rgb[0] @ w)
    np.testing.assert_array_equal(out[1], rgb[1])
    np.testing.assert_array_equal(out[2], 0.0)


def test_a_grey_table_is_in_gamut_as_it_is():
    """Three equal channels are returned unchanged (desaturate_to_gamut's shortcut), and the general
    factors agree: with Σw = 1 every channel equals Y, so none is negative where Y > 0, ringing below 0
    included."""
    rng = np.random.default_rng(5)
    one = rng.normal(0.0, 1.0, (1, 6, 6, 5))
    one[..., 0] = np.abs(one[..., 0])
    c = np.repeat(one, 3, axis=0)
    w = gamut.luminance_weights(np.arange(380.0, 781.0, 10.0))
    assert np.all(gamut.desaturation_factors(c, w) == 1.0)
    mapped, s = gamut.desaturate_to_gamut(c, w)
    assert np.all(s == 1.0) and np.array_equal(mapped, c)


def _factors_every_block(c, w, n_phi, rows):
    """desaturation_factors without its screen: every block of rows evaluated at n_phi azimuths (the reference)."""
    n = c.shape[1]
    s = np.ones((n, n))
    for r0 in range(0, n, rows):
        v = gamut._pair_values(c[:, r0:r0 + rows], n_phi)
        Y = np.einsum("k,k...->...", w, v)
        with np.errstate(divide="ignore", invalid="ignore"):
            bound = np.where((v < 0) & (Y > 0)[None], (1.0 - gamut.GAMUT_MARGIN) * Y[None] / (Y[None] - v), 1.0)
        s[r0:r0 + rows] = np.clip(bound.min(axis=(0, 3)), 0.0, 1.0)
    return np.minimum(s, s[::-1, ::-1].T)


def test_screened_factors_and_mapping_are_those_of_every_pair_evaluated():
    """desaturation_factors skips a block of rows whose every channel has a_0 > Σ_{l≥1} |a_l| (no value can be
    negative at any azimuth) and desaturate_to_gamut applies (G1) to the mapped pairs alone: the factors and the
    mapped table are those of evaluating and mapping every pair, bit for bit, for a table whose rows are partly
    in gamut by that bound, partly in gamut only at the sampled azimuths, partly out of gamut."""
    rng = np.random.default_rng(7)
    mu, c, _ = _reciprocal_table(rng, n=24)
    c[:, :8] = np.abs(c[:, :8]) * np.array([1.0] + [0.01] * 4)  # rows 0-7: a dominant a_0, screened out
    c[:, :8, :, 0] += 0.05
    w = gamut.luminance_weights(WL, "srgb")
    s = gamut.desaturation_factors(c, w, n_phi=16, rows=4)
    want = _factors_every_block(c, w, 16, 4)
    np.testing.assert_array_equal(s, want)
    a0, tail = c[..., 0], np.abs(c[..., 1:]).sum(-1)
    assert (s < 1).any() and (a0 > 2 * tail)[:, :8].all() and not (a0 > tail)[:, 8:].all()  # some blocks skipped
    mapped, s2 = gamut.desaturate_to_gamut(c, w, n_phi=gamut.N_PHI_DEFAULT)
    s_all = _factors_every_block(c, w, gamut.N_PHI_DEFAULT, 16)
    np.testing.assert_array_equal(s2, s_all)
    Y = np.einsum("k,k...->...", w, c)
    out = Y[None] + s_all[None, :, :, None] * (c - Y[None])
    keep = s_all >= 1.0
    out[:, keep] = c[:, keep]
    np.testing.assert_array_equal(mapped, out)
