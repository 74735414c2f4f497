"""Solver-core benchmarks (issue #11): before/after in one run, and the doubling loop's FLOP rate.

* 3-species basecoat under a smooth coat, 16 bands, n = 100 and 200: "before" = every order the
  components carry and per-channel kernel projection (``order_tol=None, kernel_basis=False``, the
  previous path, with today's matrix code), "after" = orders chosen at 1e-4 and the spectral-basis
  projection.  The row records both times and their ratio, measured back to back.
* Rough coat (Beckmann 0.1, η 1.5) / HG slab (g 0.7, albedo 0.95, τ 2) / Lambertian 0.5, RGB, n = 200:
  the solve with the rough interface built beforehand (its construction is excluded).
* The doubling loop (:func:`flakedb.rt.basis.layer.double_symmetric`) in GFLOP/s against a batched matmul
  of the same matrices in the same run.
* Homogeneous slabs: the eigen-solution (:func:`flakedb.rt.basis.layer.eigen_slab`, the default) against
  diamond start + doubling from a 2⁻⁷ slice, same kernels, back to back; max |ΔR|, |ΔT| relative.
"""

import time

import numpy as np
from threadpoolctl import threadpool_limits

from flakedb.rt.adding import stack as st
from flakedb.rt.basis.layer import double_symmetric, homogeneous_slab
from flakedb.rt.scattering.media import FlakeMedium, Mixture, PhaseMedium
from flakedb.rt.scattering.microflake import FlakeOptics
from flakedb.rt.basis.quadrature import default_tir_nodes, radau_hemisphere, snell_mapped_quadrature
from flakedb.rt.adding.stack import Lambertian, Rough, Slab, Smooth, SolverSettings, medium_kernel_blocks, solve_stack


def _three_species_medium(channels=16):
    c = np.linspace(0, 1, 33)
    R1 = np.tile(0.2 + 0.6 * (1 - c) ** 5, (channels, 1))
    T1 = np.tile(0.5 * c, (channels, 1))
    return Mixture([
        FlakeMedium(0.2, FlakeOptics(c, R1, T1), 1.0),
        FlakeMedium(0.3, FlakeOptics.constant(np.full(channels, 0.7), np.zeros(channels)), 0.5),
        PhaseMedium(np.full(channels, 2.0), np.linspace(0.3, 0.95, channels), ("hg", 0.5)),
    ])


def _three_species(n, before=True):
    def setup():
        return n, _three_species_medium()

    def solve(med, **kw):
        t0 = time.perf_counter()
        r = solve_stack(Smooth(1.5), [Slab(15.0, med)], Lambertian(np.full(16, 0.5)), SolverSettings(n=n, **kw))
        return r, time.perf_counter() - t0

    def run(arg):
        n, med = arg
        after, t_after = solve(med, order_tol=1e-4)
        out = {"orders": int(after.info["orders"]), "after_s": t_after}
        if before:
            prev, t_before = solve(med, order_tol=None, kernel_basis=False)
            phi = np.linspace(0, np.pi, 181)
            fa, fb = after.eval_nodes(phi), prev.eval_nodes(phi)
            cos2 = (after.x[:, None] * after.x[None, :])[None, :, :, None]
            out.update(before_s=t_before, speedup=t_before / t_after, orders_before=int(prev.info["orders"]),
                       bsdf_change_rel_max=float(np.abs(fa - fb).max() / np.abs(fb).max()),
                       cosine_weighted_change_rel_max=float(np.abs((fa - fb) * cos2).max() / np.abs(fb * cos2).max()))
        return out

    return (f"rt core: smooth coat + 3-species basecoat, 16 bands, n={n}, before/after", setup, run,
            {"n": n, "channels": 16, "what": "after: orders at 1e-4 + spectral-basis projection; before: all orders, "
             "per-channel projection (timed back to back in one run)"})


def _rough_hg_rgb(n=200):
    def setup():
        q_out = st.radau_hemisphere(n // 2)
        layer, rinfo = st.itf.rough_dielectric(q_out, q_out, 1.5, 0.1, tol=1e-5, max_orders=2 * n)
        slab = Slab(2.0, PhaseMedium(np.ones(3), np.full(3, 0.95), ("hg", np.full(3, 0.7))))
        return layer, rinfo, slab

    def run(arg):
        layer, rinfo, slab = arg
        orig = st.itf.rough_dielectric
        st.itf.rough_dielectric = lambda *a, **k: (layer, rinfo)  # built in setup: excluded from the timing
        try:
            out = {}
            for name, tol in (("after", 1e-4), ("all_orders", None)):
                t0 = time.perf_counter()
                r = solve_stack(Rough(1.5, 0.1), [slab], Lambertian(np.full(3, 0.5)), SolverSettings(n=n, order_tol=tol))
                out[f"{name}_s"] = time.perf_counter() - t0
                out[f"{name}_orders"] = int(r.info["orders"])
        finally:
            st.itf.rough_dielectric = orig
        return out

    return (f"rt core: rough coat / HG / Lambertian, RGB, n={n}, solve without interface construction", setup, run,
            {"n": n, "channels": 3, "what": "Beckmann 0.1, eta 1.5 / HG g 0.7, albedo 0.95, tau 2 / Lambertian 0.5"})


def _doubling_rate(batch=256, h=69, times=8):
    """GFLOP/s of :func:`double_symmetric` against a batched matmul of the same (batch, h, h) stacks.

    Flops counted per matrix and doubling as the LU-based doubling's: R R (2h³), the LU of I − R R
    (2h³/3), its two triangular solves with h right-hand sides (2h³), R X, T (R X) and T X (3 × 2h³):
    32h³/3, whatever the solve does (the block inverse with its probe performs about 12h³,
    docs/model.md §4 "Doubling"), so the rate is a time per doubling in matmul-equivalent units.  The
    O(h²) updates (I − R R, R + …) are not counted.  Two comparisons, each
    in the same run: one core (BLAS at one thread for both, as :func:`flakedb.rt.adding.stack.solve_stack`
    runs the doubling; best of three for each) and the whole machine (matmul with BLAS's own threads against
    ``double_symmetric(threads=2)`` with BLAS at one thread per call, again as ``solve_stack`` runs it).
    """
    def setup():
        rng = np.random.default_rng(0)
        R = 0.3 * rng.random((batch, h, h)) / h
        T = 0.5 * rng.random((batch, h, h)) / h + 0.5 * np.eye(h)
        return R, T

    fl_mm = 2.0 * h**3 * batch
    fl_dbl = (2.0 + 2.0 / 3.0 + 2.0 + 3 * 2.0) * h**3 * batch  # R@R, LU, 2 triangular solves (h rhs), 3 products

    def rates(R, T, threads, blas_threads, repeat=3):  # best of ``repeat`` for each (the machine is shared)
        t_mm = t_dbl = np.inf
        for _ in range(repeat):
            with threadpool_limits(blas_threads, "blas"):
                t0 = time.perf_counter()
                for _ in range(times):
                    R @ T
                t_mm = min(t_mm, (time.perf_counter() - t0) / times)
            with threadpool_limits(1, "blas"):
                t0 = time.perf_counter()
                double_symmetric(R[:, None], T[:, None], times, threads)  # (orders, channels, h, h)
                t_dbl = min(t_dbl, (time.perf_counter() - t0) / times)
        return fl_mm / t_mm / 1e9, fl_dbl / t_dbl / 1e9

    def run(arg):
        R, T = arg
        mm1, dbl1 = rates(R, T, 1, 1)
        mm2, dbl2 = rates(R, T, 2, None)
        return {"matmul_gflops": mm1, "doubling_gflops": dbl1, "doubling_fraction_of_matmul": dbl1 / mm1,
                "two_cores": {"matmul_gflops": mm2, "doubling_gflops": dbl2, "doubling_fraction_of_matmul": dbl2 / mm2}}

    return (f"rt core: doubling loop vs batched matmul, ({batch}, {h}, {h})", setup, run,
            {"batch": batch, "h": h, "flops_per_matrix_and_doubling": "32 h^3 / 3",
             "what": "GFLOP/s of double_symmetric and of R @ T in the same run; one core (BLAS 1 thread) and "
                     "two cores (matmul: BLAS threads; doubling: threads=2, BLAS 1 thread per call)"})


def _slab_methods(n, channels, tau, albedo, g):
    def setup():
        q = snell_mapped_quadrature(radau_hemisphere(n // 2), 1.5, default_tir_nodes(n // 2, 1.5))
        med = PhaseMedium(np.ones(channels), np.linspace(albedo, 0.9 * albedo, channels), ("hg", g))
        K_T, K_R, _ = medium_kernel_blocks(med, q.x, q.w, 1e-5, 16)
        return q.x, q.w, med.sigma_t(q.x), K_T, K_R

    def run(arg):
        x, w, sig, K_T, K_R = arg
        with threadpool_limits(1, "blas"):  # as in solve_stack
            t0 = time.perf_counter()
            e = homogeneous_slab(x, w, sig, K_T, K_R, tau)
            t_e = time.perf_counter() - t0
            t0 = time.perf_counter()
            d = homogeneous_slab(x, w, sig, K_T, K_R, tau, method="doubling")
            t_d = time.perf_counter() - t0
        return {"eigen_s": t_e, "doubling_s": t_d, "doubling_over_eigen": t_d / t_e, "h": int(x.size),
                "orders": int(K_T.shape[0]),
                "max_dR_rel": float(np.abs(e.Rt - d.Rt).max() / np.abs(d.Rt).max()),
                "max_dT_rel": float(np.abs(e.Ttb - d.Ttb).max() / np.abs(d.Ttb).max())}

    return (f"rt core: slab eigen vs doubling, n={n}, {channels} ch, tau {tau:g}, albedo {albedo:g}, HG {g:g}",
            setup, run, {"n": n, "channels": channels, "tau": tau, "what": "one thread; timed = both, back to back"})


BENCHMARKS = [_doubling_rate(), _three_species(100), _three_species(200, before=False), _rough_hg_rgb(),
              _slab_methods(100, 41, 92.0, 0.999, 0.5), _slab_methods(100, 41, 2.0, 0.9, 0.7),
              _slab_methods(200, 16, 15.0, 0.95, 0.5)]
