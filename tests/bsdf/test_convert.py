"""The one stack → table conversion (flakedb.bsdf.convert.stack_to_table): what the solver computed
is what the file holds.  Guards against a second, diverging conversion (issue #10: two existed, one
with and one without the η² factor on transmission) and against node-ordering or cosine-factor slips.
"""

import tempfile

import numpy as np
import pytest

from flakedb.bsdf import BSDFTable, table_evaluator, write_bsdf
from flakedb.bsdf.convert import stack_to_table
from flakedb.compose.orchestrate import compose
from flakedb.paint.mapping import build_paint, solve_paint
from flakedb.paint.recipe import parse_recipe
from flakedb.rt.scattering.media import PhaseMedium
from flakedb.rt.adding.stack import Lambertian, Rough, Slab, Smooth, SolverSettings, solve_stack

PHI = np.array([0.0, 0.7, 2.0, np.pi])


def _series(f_l, phi):
    return np.einsum("l...,lp->...p", f_l, np.cos(np.arange(f_l.shape[0])[:, None] * phi[None, :]))


def test_reflection_at_the_nodes_is_the_solvers_bsdf_times_mu_o():
    s = solve_stack(Smooth(1.5), [Slab(1.0, PhaseMedium(1.0, 0.9, ("hg", 0.5)))], Lambertian(0.5), SolverSettings(n=12))
    ev = table_evaluator(stack_to_table(s))
    x = s.x
    f = s.f_coefficients("Rt")[:, 0]                     # (L, o, i)
    want = _series(f, PHI)                                # (o, i, P)
    mi, mo, ph = np.meshgrid(x, x, PHI, indexing="ij")    # [i, o, p]
    got = ev.eval(mi.ravel(), -mo.ravel(), ph.ravel(), clamp="none")[:, 0].reshape(mi.shape)
    np.testing.assert_allclose(got, np.transpose(want, (1, 0, 2)) * x[None, :, None], rtol=1e-10, atol=1e-14)
    assert stack_to_table(s).delta == {"kind": "fresnel", "eta": 1.5}


def test_transmission_blocks_are_basic_radiance_and_conserve_energy():
    """Index-matched lossless slab, no primer: every incident node's reflection + transmission
    from the table's order-0 coefficients (Σ_o 2π w_o a_0) is 1, both from above and from below."""
    s = solve_stack(None, [Slab(2.0, PhaseMedium(1.0, 1.0, ("hg", 0.3)))], None, SolverSettings(n=16))
    t = stack_to_table(s)
    h = s.x.size
    w = np.concatenate([s.w[::-1], s.w])
    a0 = t.coeffs[0, :, :, 0]                              # [i, o] of f·|μ_o|
    flux = 2 * np.pi * (a0 * w[None, :]).sum(axis=1)      # per incident node, all outgoing nodes
    np.testing.assert_allclose(flux, 1.0, atol=1e-9)
    # from below equals from above by the slab's symmetry
    np.testing.assert_allclose(a0[:h, :][::-1, ::-1], a0[h:, :], atol=1e-12)


def test_compose_ships_this_conversion():
    """compose's table is stack_to_table of the solved paint (same numbers, not a re-implementation)."""
    text = """flakedb: 1
name: convert-parity
spectral: {mode: mono}
resolution: 16
layers:
  - clearcoat: {thickness_um: 30, ior: 1.5}
  - basecoat:
      thickness_um: 10
      ior: 1.5
      particles:
        - custom: {kind: medium, name: grey, albedo: 0.7, phase: {hg: 0.4}}
          optical_depth: 1.0
  - primer: {color: gray}
"""
    recipe = parse_recipe(text)
    paint = build_paint(recipe)
    want = stack_to_table(solve_paint(paint, 16), paint.channels, paint.eta, paint.top_alpha, paint.delta)
    got = compose(recipe, tempfile.mkdtemp()).table
    np.testing.assert_array_equal(got.coeffs, want.coeffs)
    np.testing.assert_array_equal(got.mu, want.mu)


@pytest.mark.parametrize("grey", [False, True])
def test_an_opaque_paints_table_is_its_reflection_quadrant(tmp_path, grey):
    """An opaque stack's table holds only reflection from above (reflection_only): its dense
    coefficients are that quadrant and zeros, and the .bsdf file and the albedo made from the quadrant
    alone are those of the dense table (byte for byte, to the last bit); a grey stack's (channels solved
    once, one array for all) too."""
    albedo, primer = ([0.9] * 3, [0.5] * 3) if grey else ([0.9, 0.5, 0.2], [0.5, 0.3, 0.1])
    s = solve_stack(Smooth(1.5), [Slab(1.0, PhaseMedium([1.0, 1.0, 1.0], albedo, ("hg", 0.5)))],
                    Lambertian(primer), SolverSettings(n=12))
    t = stack_to_table(s)
    assert t.reflection_only and (t.stored.strides[0] == 0) == grey
    a_quadrant = t.albedo()
    write_bsdf(tmp_path / "q.bsdf", t)
    assert t.reflection_only                                 # neither call built the dense array
    dense = BSDFTable(mu=t.mu, coeffs=t.coeffs.copy(), delta=t.delta, eta=t.eta)
    assert not t.reflection_only                             # reading .coeffs built it
    h = t.n // 2
    c = dense.coeffs
    assert np.any(c[:, h:, :h] != 0)
    assert not np.any(c[:, :h]) and not np.any(c[:, h:, h:])
    np.testing.assert_array_equal(a_quadrant, dense.albedo())
    write_bsdf(tmp_path / "d.bsdf", dense)
    assert (tmp_path / "q.bsdf").read_bytes() == (tmp_path / "d.bsdf").read_bytes()


def test_a_grey_rgb_paint_is_written_as_its_dense_copy(tmp_path):
    """A grey stack in RGB is solved once and its table is one channel broadcast to three
    (flakedb.rt.adding.stack._distinct_channels): the values are the solver's f·μ_o at the nodes, and the
    .bsdf written from the broadcast (truncated once) is byte for byte the one of a dense copy."""
    s = solve_stack(Smooth(1.5), [Slab(1.0, PhaseMedium([1.0] * 3, [0.9] * 3, ("hg", 0.5)))], Lambertian([0.5] * 3),
                    SolverSettings(n=12))
    t = stack_to_table(s)
    r = t.live_quadrant()
    assert r.shape[0] == 3 and r.strides[0] == 0                      # not copied per channel
    f = s.f_coefficients("Rt")[:, 0]                                   # (L, o, i)
    x = s.x
    want = np.transpose(f * x[:, None], (2, 1, 0))[:, ::-1]            # [i, o reversed (table's −x order), l]
    np.testing.assert_allclose(r[1], want, rtol=1e-13, atol=0)
    dense = BSDFTable(mu=t.mu, reflection=np.array(r), delta=t.delta, eta=t.eta)
    write_bsdf(tmp_path / "g.bsdf", t)
    write_bsdf(tmp_path / "d.bsdf", dense)
    assert (tmp_path / "g.bsdf").read_bytes() == (tmp_path / "d.bsdf").read_bytes()


def test_an_opaque_paints_h5_is_its_dense_table(tmp_path):
    """write_h5 writes a reflection-only table's quadrant alone (the rest is the dataset's fill value):
    read back, it is the dense table, bit for bit."""
    from flakedb.bsdf import read_h5, write_h5

    s = solve_stack(Smooth(1.5), [Slab(1.0, PhaseMedium([1.0, 1.0, 1.0], [0.9, 0.5, 0.2], ("hg", 0.5)))],
                    Lambertian([0.5, 0.3, 0.1]), SolverSettings(n=12))
    t = stack_to_table(s)
    assert t.reflection_only
    write_h5(tmp_path / "q.h5", t)
    back = read_h5(tmp_path / "q.h5").to_table()
    np.testing.assert_array_equal(back.coeffs, t.coeffs)


def test_table_roughness_comes_from_the_solved_stack():
    """The file's α is the solved stack's rough top (issue #21: it came from a second copy in the paint)."""
    rough = solve_stack(Rough(1.5, 0.3), [], Lambertian(0.5), SolverSettings.product(16))
    smooth = solve_stack(Smooth(1.5), [], Lambertian(0.5), SolverSettings.product(16))
    assert rough.top_alpha == 0.3 and stack_to_table(rough).alpha[0] == 0.3
    assert smooth.top_alpha == 0.0 and stack_to_table(smooth).alpha[0] == 0.0
