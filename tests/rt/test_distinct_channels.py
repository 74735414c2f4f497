"""Channels that scatter identically are solved once (flakedb.rt.adding.channels.distinct_channels): the result
must be the channel-by-channel solve, whatever the grouping of equal channels."""

import numpy as np

from flakedb.rt.scattering.media import FlakeMedium, Mixture, PhaseMedium
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.adding.stack import Lambertian, Rough, Slab, Smooth, SolverSettings, solve_stack


def _one_channel_solves(top, make_slabs, albedos, n):
    return np.concatenate([solve_stack(top, make_slabs([c]), Lambertian([a]), SolverSettings.product(n)).Rt
                           [:, :, :, :] for c, a in enumerate(albedos)], axis=1)


def test_grey_rgb_is_the_mono_solve_spread():
    n = 16
    med = PhaseMedium([1.0] * 3, [0.9] * 3, ("hg", 0.5))
    rgb = solve_stack(Rough(1.5, 0.2), [Slab(2.0, med)], Lambertian([0.5] * 3), SolverSettings.product(n))
    mono = solve_stack(Rough(1.5, 0.2), [Slab(2.0, PhaseMedium(1.0, 0.9, ("hg", 0.5)))], Lambertian(0.5),
                       SolverSettings.product(n))
    assert rgb.info["distinct_channels"] == 1 and rgb.Rt.shape[1] == 3
    L = min(rgb.n_orders, mono.n_orders)
    assert np.array_equal(rgb.Rt[:L], np.broadcast_to(mono.Rt[:L], rgb.Rt[:L].shape))  # exact by construction: solved once, broadcast
    assert np.array_equal(rgb.albedo(), np.broadcast_to(mono.albedo(), (3, n // 2)))


def test_repeated_channels_match_each_channel_alone():
    n = 16
    g = np.array([0.3, 0.7, 0.3, 0.7, 0.3])
    alb = np.array([0.4, 0.6, 0.4, 0.6, 0.5])  # channels 0 = 2, 1 = 3; 4 differs by its primer only
    optics = FlakeOptics(np.array([0.0, 1.0]), np.array([[0.2, 0.3]] * 5), np.array([[0.5, 0.4]] * 5))

    def slabs(idx):
        idx = list(idx)
        return [Slab(3.0, Mixture([PhaseMedium(np.ones(len(idx)), np.full(len(idx), 0.8), ("hg", g[idx])),
                                   FlakeMedium(0.3, FlakeOptics(optics.c, optics.R[idx], optics.T[idx]), 0.2)]))]

    s = SolverSettings.product(n)
    all5 = solve_stack(Smooth(1.5), slabs(range(5)), Lambertian(alb), s)
    assert all5.info["distinct_channels"] == 3
    for c in range(5):
        one = solve_stack(Smooth(1.5), slabs([c]), Lambertian(alb[[c]]), s)
        L = min(one.n_orders, all5.n_orders)
        assert np.allclose(all5.Rt[:L, c], one.Rt[:L, 0], rtol=1e-12, atol=1e-13 * np.abs(one.Rt).max())
