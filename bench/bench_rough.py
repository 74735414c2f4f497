"""Rough-interface benchmarks (issue 12): building the rough dielectric coat's scattering matrices by
flux-cell integration (flakedb.rt.microfacet) against the former node-sampled projection, and the
rough conductor base.  Accuracy is in tests/test_rough_energy.py; here only the time."""

from flakedb.rt import interface as itf
from flakedb.rt.quadrature import radau_hemisphere


def _coat(n, alpha, scheme):
    def setup():
        return radau_hemisphere(n // 2)

    def run(q):
        fn = itf.rough_dielectric if scheme == "cells" else itf.rough_dielectric_point_sampled
        layer, _ = fn(q, q, 1.5, alpha, max_orders=2 * n)
        return {"orders": int(layer.n_orders)}

    return (f"rough coat interface ({scheme}), alpha={alpha}, n={n}", setup, run,
            {"n": n, "alpha": alpha, "eta": 1.5, "scheme": scheme, "what": "four blocks, all orders"})


def _conductor(n, alpha):
    def setup():
        return radau_hemisphere(n // 2)

    def run(q):
        Rt, _ = itf.rough_conductor(q, [0.18 + 2.3j, 0.9 + 6.1j, 1.1 + 7.0j], alpha, max_orders=2 * n)
        return {"orders": int(Rt.shape[0])}

    return (f"rough conductor base, alpha={alpha}, n={n}, 3 channels", setup, run,
            {"n": n, "alpha": alpha, "channels": 3})


BENCHMARKS = [_coat(200, 0.1, "cells"), _coat(200, 0.1, "points"), _coat(64, 0.1, "cells"),
              _coat(64, 0.1, "points"), _coat(64, 0.02, "cells"), _conductor(64, 0.1)]
