"""The mosaic's two-point moment E[β(x)β(x+s)] (docs/texture.md §4, eqs. G5, G6) against a brute-force Monte Carlo of
the same geometric quantity (issue 36: the sky paths' coupling to the mosaic).

    PYTHONPATH=$PWD python bench/texture_mosaic_pairs.py VOLUME_FRACTION PATCHES [SEED]

Horizontal opaque discs (the layer of tests.texture.cases' metallic recipe, 20 µm, gsd 1.3: its density, diameters,
depth) placed as a Poisson process in a periodic patch; each flake draws one of four sky paths (drift g per µm of
height, luminance a; azimuth uniform).  A ray at x shows its topmost flake's a if that flake's sky path from (x, z)
meets no flake above, else 0.  Pairs x, x + s e_θ (θ uniform) give E[β(x)β(x+s)] at each s; "traced" traces the
sky paths through the same flakes (what a paint does), "independent" through an independent copy per top flake
without the flakes over its own ray (G5's assumption).  The model's pair moment (flakedb.texture.model.
mosaic_pair_moment) takes the exact inputs of this setting (κ = 1, T = 0, λ_l' from the discs' lens areas).
Prints the model's covariances (G5, G6) at OFFSETS and the Monte Carlo's (within each patch) with standard errors
over the patches; docs/texture.md §4 quotes them (16 and 8 %, 24 patches, seeds 7 and 8)."""
from __future__ import annotations

import sys

import numpy as np

from flakedb.texture import model as tm

#: the four sky paths: drift per µm of height, luminance, weight
DRIFT = np.array([0.1, 0.3, 0.55, 0.85])
LUM = np.array([1.0, 0.8, 0.6, 0.4])
WEIGHT = np.full(4, 0.25)
OFFSETS = np.array([0.0, 4.0, 8.0, 14.0, 22.0])


def model_inputs(f, n_depth=32):
    """(z, B1n, B2n, light) of the setting: λ_l'(m, h) = ρ∫_0^h ⟨A − lens(u g_m)⟩ du (the sky path's crossings
    that do not cover the ray itself)."""
    z, _ = tm._depth_nodes(f, n_depth)
    h = z - f.z_top_um
    Dn, Dw = f.diameters()
    r = 0.5 * Dn
    x, wx = tm.leggauss(32)
    u = 0.5 * h[None, :, None] * (x[None, None, :] + 1.0)  # (1, nz, n)
    sep = DRIFT[:, None, None] * u  # (M, nz, n)
    lens = np.einsum("d,dmzn->mzn", Dw, tm.lens_area(sep[None], r[:, None, None, None], r[:, None, None, None]))
    lo = f.number_density_per_um3 * np.sum((f.mean_area_um2() - lens) * wx, axis=-1) * 0.5 * h[None, :]
    B1m = (WEIGHT * LUM)[:, None] * np.exp(-lo)
    Q = (WEIGHT * LUM**2)[:, None] * np.ones_like(lo)
    B2n = np.sum(Q * np.exp(-lo), axis=0)
    return z, B1m.sum(axis=0), B2n, (Q, lo, np.zeros_like(lo), B1m, DRIFT.copy())


def simulate(f, n_patch, seed=1, L=200.0, n_pts=3000, variants=("traced", "independent")):
    """Cov(β(x), β(x+s)) at OFFSETS (within each patch: biased by −Var(the patch's mean), alike for both) and E[β]
    for "traced" and "independent" on the same mosaics and points, and their "difference", each with its standard
    error over patches: dict name → (mean, se of mean, cov (ns,), se (ns,), cov per patch (patches, ns))."""
    rng = np.random.default_rng(seed)
    rho, d, z0 = f.number_density_per_um3, f.thickness_um, f.z_top_um
    s_g = np.log(f.diameter_gsd)

    def place():
        n = rng.poisson(rho * d * L * L)
        k = rng.choice(DRIFT.size, n, p=WEIGHT)
        ph = 2 * np.pi * rng.random(n)
        return dict(X=rng.random(n) * L, Y=rng.random(n) * L, Z=z0 + rng.random(n) * d,
                    R=0.5 * f.diameter_median_um * np.exp(s_g * rng.standard_normal(n)), k=k,
                    t=DRIFT[k][:, None] * np.stack([np.cos(ph), np.sin(ph)], -1))

    def cover(px, py, F):  # (P, N)
        dx = (px[:, None] - F["X"][None, :] + 0.5 * L) % L - 0.5 * L
        dy = (py[:, None] - F["Y"][None, :] + 0.5 * L) % L - 0.5 * L
        return dx * dx + dy * dy < (F["R"] ** 2)[None, :]

    def beta(px, py, F, copy):
        """β at the points; ``copy``: (flakes, offset per flake of F) to trace each top flake's sky path through
        (the copy translated by its top flake's offset, the flakes over the translated ray left out), or None."""
        c = cover(px, py, F)
        zz = np.where(c, F["Z"][None, :], np.inf)
        top = np.argmin(zz, axis=1)
        hit = np.isfinite(zz[np.arange(px.size), top])
        t, zt = F["t"][top], F["Z"][top]
        if copy is None:
            G, qx, qy = F, px, py
        else:
            G, off = copy
            qx, qy = px + off[top, 0], py + off[top, 1]
        h = zt[:, None] - G["Z"][None, :]
        bx, by = qx[:, None] + h * t[:, 0:1], qy[:, None] + h * t[:, 1:2]
        dx = (bx - G["X"][None, :] + 0.5 * L) % L - 0.5 * L
        dy = (by - G["Y"][None, :] + 0.5 * L) % L - 0.5 * L
        blk = (h > 0) & (dx * dx + dy * dy < (G["R"] ** 2)[None, :])
        if copy is not None:
            blk &= ~cover(qx, qy, G)
        return np.where(hit & ~np.any(blk, axis=1), LUM[F["k"][top]], 0.0)

    def many(px, py, F, copy):
        return np.concatenate([beta(px[i:i + 500], py[i:i + 500], F, copy) for i in range(0, px.size, 500)])

    cov = {k: [] for k in variants}
    means = {k: [] for k in variants}
    for _ in range(n_patch):
        F = place()
        px, py = rng.random(n_pts) * L, rng.random(n_pts) * L
        th = 2 * np.pi * rng.random((OFFSETS.size, n_pts))
        copy = (place(), rng.random((F["X"].size, 2)) * L)
        for name, cp in (("traced", None), ("independent", copy)):  # the same mosaic and points for both
            if name not in variants:
                continue
            bx = many(px, py, F, cp)
            row = []
            for s, t in zip(OFFSETS, th):
                by = many((px + s * np.cos(t)) % L, (py + s * np.sin(t)) % L, F, cp)
                row.append(np.mean(bx * by) - bx.mean() * by.mean())  # within the patch (bias −Var(patch mean))
            cov[name].append(row)
            means[name].append(bx.mean())
    out = {k: (np.mean(means[k]), np.std(means[k], ddof=1) / np.sqrt(n_patch), np.mean(cov[k], axis=0),
               np.std(cov[k], axis=0, ddof=1) / np.sqrt(n_patch), np.array(cov[k])) for k in cov}
    if len(variants) == 2:
        dc = np.array(cov["traced"]) - np.array(cov["independent"])
        out["difference"] = (0.0, 0.0, dc.mean(axis=0), dc.std(axis=0, ddof=1) / np.sqrt(n_patch))
    return out


if __name__ == "__main__":
    from tests.texture.cases import stack_of

    vf, n_patch = float(sys.argv[1]), int(sys.argv[2])
    f = stack_of(species="metallic", vf=vf, alpha=0.2, D=20.0).flakes[0]
    z, B1n, B2n, light = model_inputs(f)
    res = simulate(f, n_patch, int(sys.argv[3]) if len(sys.argv) > 3 else 1)
    cm = []
    for coupled in (False, True):
        mean, mom = tm.mosaic_pair_moment(f, z, B1n, B2n, 0.0, 1.0, OFFSETS, light, coupled)
        cm.append(mom - mean * mean)
        print(f"model {'G6' if coupled else 'G5'}: mean {mean:.5f}  cov " + " ".join(f"{c:.5f}" for c in cm[-1]))
    # G6 − G5 holds the coupling (what "traced" − "independent" measures) and the exact shared share of one
    # flake's two sky paths (which G5 missed against "independent" too)
    print("model G6 − G5:                cov " + " ".join(f"{c:.5f}" for c in cm[1] - cm[0]))
    for name, (m, sm, C, sC, *_) in res.items():
        print(f"MC {name}: mean {m:.5f} ± {sm:.5f}  cov " + " ".join(f"{c:.5f}±{e:.5f}" for c, e in zip(C, sC)))
