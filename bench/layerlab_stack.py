"""layerlab's side of bench/bench_layerlab.py: the rough coat (Beckmann α, η 1.5) / Henyey–Greenstein slab
(g 0.7, τ 2) / Lambertian stack of bench/stack_rough_hg_lambertian.py, built with layerlab
(W. Jakob, github.com/wjakob/layerlab; tools/build_layerlab.sh builds it) and written as its Fourier ``.bsdf``.
Run as a process and time it from outside:

    python bench/layerlab_stack.py N ORDERS ALPHA {mono,rgb,colour} OUT

``N`` nodes in all (``layerlab.quad.gaussLobatto(N)``, N/2 per hemisphere: flakedb's n), ``ORDERS``
Fourier orders (the bench passes the count flakedb keeps for the same stack, so both solve the same
orders).  ``mono``: one channel (slab albedo 0.95, primer 0.5), ``BSDFStorage.fromLayer``; ``rgb``: the
grey stack as RGB, solved once and written three times (what flakedb does with equal channels);
``colour``: slab albedo 0.95 / 0.9 / 0.8 and primer 0.5 / 0.4 / 0.3, three solves sharing the coat
(layerlab's recipes/coated-diffuse.py pattern), ``BSDFStorage.fromLayerRGB``.

:func:`build` is also imported by the bench's agreement check (same construction, in-process)."""

import sys

import layerlab as ll

SLAB_TAU = 2.0
HG_G = 0.7
ETA = 1.5
CHANNELS = {"mono": ([0.95], [0.5]), "rgb": ([0.95], [0.5]), "colour": ([0.95, 0.9, 0.8], [0.5, 0.4, 0.3])}


def build(n, orders, alpha, mode):
    """The stack's layers, one per solved channel (``layerlab.Layer``, reflection from the top)."""
    mu, w = ll.quad.gaussLobatto(n)
    coat = ll.Layer(mu, w, orders)
    coat.setMicrofacet(eta=ETA, alpha=alpha)
    out = []
    for albedo, primer in zip(*CHANNELS[mode]):
        base = ll.Layer(mu, w, orders)
        base.setDiffuse(primer)
        slab = ll.Layer(mu, w, orders)
        slab.setHenyeyGreenstein(albedo=albedo, g=HG_G)
        slab.expand(SLAB_TAU)
        base.addToTop(slab)
        base.addToTop(coat)
        out.append(base)
    return out


def main(n, orders, alpha, mode, out):
    layers = build(n, orders, alpha, mode)
    if mode == "mono":
        storage = ll.BSDFStorage.fromLayer(out, layers[0])
    else:
        r, g, b = layers * 3 if len(layers) == 1 else layers
        storage = ll.BSDFStorage.fromLayerRGB(out, r, g, b)
    storage.close()


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), sys.argv[4], sys.argv[5])
