"""What a rough top shares between solves (issue 34 item 8, docs/compose-overhead.md): the height chain's solution on
its own grids, once per (η, α) (flakedb.rt.boundaries.microfacet._height_chain_grid), and the background thread that builds
rough tops (flakedb.rt.adding.stack._RoughBuild).

Guards against: a cached chain that differs from a fresh one (by a bit), that is solved again by a second thread
asking at the same time, or that keeps a failure; a solve whose rough top waits in the background thread's queue
behind another solve's top (compose's discretisation solve at n/2 or 3n/4 is submitted first) instead of being built by
the thread that needs it, and a top built that way that differs from the background build."""

import threading

import numpy as np
import pytest

import flakedb.rt.common.jobs as jobs
import flakedb.rt.boundaries.microfacet as mf
from flakedb.rt.scattering.media import PhaseMedium
from flakedb.rt.basis.quadrature import radau_hemisphere
from flakedb.rt.adding.stack import Lambertian, Rough, Slab, SolverSettings, solve_stack


def _fresh_escape(mu_a, mu_b, eta, alpha):
    """height_chain_escape with its grid solution computed anew (the cache bypassed)."""
    saved = dict(mf._HEIGHT_GRIDS)
    mf._HEIGHT_GRIDS.clear()
    try:
        return mf.height_chain_escape(mu_a, mu_b, eta, alpha)
    finally:
        mf._HEIGHT_GRIDS.clear()
        mf._HEIGHT_GRIDS.update(saved)


@pytest.mark.parametrize("eta, alpha", [(1.5, 0.1), (1.0 / 1.3, 0.3)])
def test_the_chain_solved_once_gives_every_node_set_the_fresh_escape_bit_for_bit(eta, alpha, monkeypatch):
    monkeypatch.setattr(mf, "_HEIGHT_GRIDS", {})
    solved = []
    real = mf._solve_height_chain_grid
    monkeypatch.setattr(mf, "_solve_height_chain_grid", lambda *a: solved.append(a) or real(*a))
    for n in (40, 30, 16):  # compose's n and 3n/4, then another
        q = radau_hemisphere(n // 2)
        shared = mf.height_chain_escape(q.x, q.x[::-1], eta, alpha)
        fresh = _fresh_escape(q.x, q.x[::-1], eta, alpha)
        for a, b in zip(shared, fresh):
            assert a.tobytes() == b.tobytes()
    assert solved.count((float(eta), float(alpha))) == 1 + 3  # once shared, once per fresh solve
    zs, c, flip, d = mf._height_chain_grid(eta, alpha)
    assert not d.flags.writeable and d.shape == (2, len(zs), len(c))


def test_threads_asking_at_once_solve_the_chain_once_and_a_failure_is_not_kept(monkeypatch):
    monkeypatch.setattr(mf, "_HEIGHT_GRIDS", {})
    started, release, calls = threading.Event(), threading.Event(), []
    real = mf._solve_height_chain_grid

    def slow(*a):
        calls.append(a)
        started.set()
        assert release.wait(20)
        return real(*a)

    monkeypatch.setattr(mf, "_solve_height_chain_grid", slow)
    mu = radau_hemisphere(6).x
    out = {}
    first = threading.Thread(target=lambda: out.setdefault(1, mf.height_chain_escape(mu, mu, 1.5, 0.2)))
    first.start()
    assert started.wait(20)
    second = threading.Thread(target=lambda: out.setdefault(2, mf.height_chain_escape(mu, mu, 1.5, 0.2)))
    second.start()
    second.join(0.2)
    assert second.is_alive()  # waiting for the first thread's solution, not solving its own
    release.set()
    first.join(20)
    second.join(20)
    assert len(calls) == 1 and all(a.tobytes() == b.tobytes() for a, b in zip(out[1], out[2]))

    def fail(*a):
        raise FloatingPointError("chain failed")

    monkeypatch.setattr(mf, "_solve_height_chain_grid", fail)
    with pytest.raises(FloatingPointError):
        mf.height_chain_escape(mu, mu, 1.5, 0.3)
    monkeypatch.setattr(mf, "_solve_height_chain_grid", real)
    assert mf.height_chain_escape(mu, mu, 1.5, 0.3)[0].shape == mu.shape  # solved now, not the failure again


def _stack(threads):
    slab = Slab(2.0, PhaseMedium(sigma_t_per_um=[1.0], albedo=[0.95], phase=("hg", 0.7)))
    return solve_stack(Rough(1.5, 0.2), [slab], Lambertian([0.5]), SolverSettings.product(16, threads=threads))


def test_a_rough_top_queued_behind_another_is_built_by_the_solve_that_needs_it_bit_for_bit():
    """The background thread ("flakedb-solve", one per process) held by another job: the solve builds its top in
    its own thread and returns while that job still runs (before, it waited for it), with the serial values."""
    serial = _stack(1)
    busy, release = threading.Event(), threading.Event()
    pool = jobs.thread_pool(1, "flakedb-solve")
    blocker = pool.submit(lambda: busy.set() or release.wait(60))
    try:
        assert busy.wait(20)
        out = {}
        t = threading.Thread(target=lambda: out.setdefault("s", _stack(2)))
        t.start()
        t.join(60)
        assert not t.is_alive(), "the solve waited for the background thread's other job"
        assert not blocker.done()
    finally:
        release.set()
    blocker.result(20)
    assert out["s"].Rt.tobytes() == serial.Rt.tobytes()
    assert np.array_equal(out["s"].x, serial.x) and out["s"].info["orders"] == serial.info["orders"]


@pytest.mark.parametrize("eta, alpha", [(1.5, 0.1), (1.0 / 1.3, 0.3)])
def test_one_rule_on_both_sides_shares_the_facets_and_gives_each_side_its_own_escape_bit_for_bit(eta, alpha):
    """With the same cosines above and below, the facet events are sampled once for both sides
    (mf._facet_outcomes with both indices); each side's escape must be what it is beside another side's rule."""
    mu = radau_hemisphere(10).x
    other = radau_hemisphere(7).x
    Pa, Pb = mf.height_chain_escape(mu, mu, eta, alpha)
    assert Pa.tobytes() == mf.height_chain_escape(mu, other, eta, alpha)[0].tobytes()
    assert Pb.tobytes() == mf.height_chain_escape(other, mu, eta, alpha)[1].tobytes()
    # and the reflected spread shared by both indices is each index's own
    ev = mf._facet_outcomes(-mu, (eta, 1.0 / eta), alpha, 16, 6)
    zs = np.concatenate([-np.linspace(1e-3, 1.0, 9)[::-1], np.linspace(1e-3, 1.0, 9)])
    both = mf._spread_signed_all(zs, ev[0][1], [ev[0][0], ev[1][0]])
    for k in (0, 1):
        alone = mf._facet_outcomes(-mu, ((eta, 1.0 / eta)[k],), alpha, 16, 6)[0]
        assert both[k].tobytes() == mf._spread_signed(zs, alone[1], alone[0]).tobytes()


@pytest.mark.parametrize("eta, alpha", [(1.5, 0.1), (1.0 / 1.5, 0.3), (1.1, 0.02)])
def test_one_rule_on_both_sides_gives_each_side_microfacet_albedo_bit_for_bit(eta, alpha):
    """The single-scattering albedos of both sides from one set of facet samples (mf._single_albedos with both
    indices, a rough top's rule above and below) are microfacet_albedo's, bit for bit, over several chunks of
    cosines (MS_CHUNK_SAMPLES)."""
    mu = radau_hemisphere(50).x
    assert len(mu) * mf.MS_CHAIN_QUAD**2 > 2 * mf.MS_CHUNK_SAMPLES
    (Ra, Ta), (Rb, Tb), _ = mf.dielectric_albedo_and_escape(mu, mu, eta, alpha)
    for (R, T), e in (((Ra, Ta), eta), ((Rb, Tb), 1.0 / eta)):
        R2, T2 = mf.microfacet_albedo(mu, e, alpha)
        assert R.tobytes() == np.asarray(R2).tobytes() and T.tobytes() == np.asarray(T2).tobytes()
