"""Why the graininess of dense metallic layers reads high against the per-ray reference (issue 36; docs/texture.md
§8): an isolation experiment of one assumption of eq. G5.

    PYTHONPATH=$PWD python bench/texture_mosaic_sky.py VOLUME_FRACTION PATCHES [SEED]

A mosaic of horizontal opaque discs (the layer of tests.texture.cases' metallic recipe, 20 µm, α 0.2, Beckmann
tilts) seen along the normal on a 1.25 µm ray grid in 15 µm pixels (the BYK-like spot), each ray showing its topmost
flake's sky luminance T_in(l_m)|v'·m| (R = 1, no absorber: both variants alike).  The flake's mirrored sky path
from the ray's point is traced (b) through the same flakes, as the reference does, or (a) through an independent
copy of the layer per top flake without the flakes that cover the ray itself (G5's assumptions: the light path's
crossings not shared with the view ray, two rays on one flake sharing their sky paths' flakes, different flakes
independent).  Same mosaics and normals: G_a / G_b isolates the correlation of the sky paths' blocking with the
mosaic (the upper neighbour that is itself a tile of the mosaic blocks the lower tile's sky path).  Prints the
cumulative G of both and the ratio, then the ratio's standard error over the patches."""
import sys

import numpy as np

from flakedb.texture import model as tm
from tests.texture.cases import stack_of

vf, D, alpha, npatch = float(sys.argv[1]), 20.0, 0.2, int(sys.argv[2])
st = stack_of(species="metallic", vf=vf, alpha=alpha, D=D)
f = st.flakes[0]
rho, d, eta = f.number_density_per_um3, f.thickness_um, st.eta
s_g = np.log(f.diameter_gsd)
L, p, ray = 240.0, 15.0, 1.25
rng = np.random.default_rng(int(sys.argv[3]) if len(sys.argv) > 3 else 1)
g = np.arange(0, L, ray) + 0.5 * ray
RX, RY = [a.ravel() for a in np.meshgrid(g, g, indexing="ij")]
pix = (np.floor(RX / p).astype(int) * int(L / p) + np.floor(RY / p).astype(int))
npx = int(L / p) ** 2

def place():
    n = rng.poisson(rho * d * L * L)
    X, Y, Z = rng.random(n) * L, rng.random(n) * L, f.z_top_um + rng.random(n) * d
    R = 0.5 * f.diameter_median_um * np.exp(s_g * rng.standard_normal(n))
    th = np.arctan(alpha * np.sqrt(-np.log(rng.random(n))))  # Beckmann tilt
    ph = 2 * np.pi * rng.random(n)
    m = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    return X, Y, Z, R, m

def covers(x, y, X, Y, R):
    dx = (x[:, None] - X[None, :] + 0.5 * L) % L - 0.5 * L
    dy = (y[:, None] - Y[None, :] + 0.5 * L) % L - 0.5 * L
    return dx * dx + dy * dy < (R * R)[None, :]

res = []
for it in range(npatch):
    X, Y, Z, R, m = place()
    X2, Y2, Z2, R2, _ = place()  # the independent copy
    top = np.full(RX.size, -1)
    for lo in range(0, RX.size, 2000):
        c = covers(RX[lo:lo + 2000], RY[lo:lo + 2000], X, Y, R)
        zz = np.where(c, Z[None, :], np.inf)
        k = np.argmin(zz, axis=1)
        top[lo:lo + 2000] = np.where(np.isfinite(zz[np.arange(k.size), k]), k, -1)
    hit = top >= 0
    mm = m[np.maximum(top, 0)]
    v = np.array([0, 0, 1.0])
    cv = mm[:, 2]
    lm = 2 * cv[:, None] * mm - v
    s2 = (1 - lm[:, 2] ** 2) * eta * eta
    ok = hit & (lm[:, 2] > 1e-6) & (s2 < 1)
    amp = np.where(ok, tm.coat_transmittance(np.sqrt(np.clip(1 - s2, 0, 1)), eta) * np.abs(cv), 0.0)
    t = lm[:, :2] / np.where(ok, lm[:, 2], 1.0)[:, None]
    zF = np.where(hit, Z[np.maximum(top, 0)], 0)
    off = rng.random((X.size, 2)) * L  # per top flake: its own translate of the copy
    vis = {}
    for name in ("b", "a"):
        free = np.ones(RX.size, bool)
        for lo in range(0, RX.size, 1000):
            sl = slice(lo, lo + 1000)
            if name == "b":
                Xo, Yo, Zo, Ro = X, Y, Z, R
                x0, y0 = RX[sl], RY[sl]
            else:
                Xo, Yo, Zo, Ro = X2, Y2, Z2, R2
                o = off[np.maximum(top[sl], 0)]
                x0, y0 = RX[sl] + o[:, 0], RY[sl] + o[:, 1]
            h = zF[sl][:, None] - Zo[None, :]  # height of each flake above the ray's top flake
            px = x0[:, None] + h * t[sl, 0][:, None]
            py = y0[:, None] + h * t[sl, 1][:, None]
            dx = (px - Xo[None, :] + 0.5 * L) % L - 0.5 * L
            dy = (py - Yo[None, :] + 0.5 * L) % L - 0.5 * L
            blk = (h > 0) & (dx * dx + dy * dy < (Ro * Ro)[None, :])
            if name == "a":  # no flake above the top flake covers the ray itself
                blk &= ~covers(x0, y0, Xo, Yo, Ro)
            free[sl] = ~np.any(blk, axis=1)
        val = amp * free
        px_ = np.bincount(pix, val, npx) / np.bincount(pix, None, npx)
        vis[name] = px_
    res.append((vis["a"], vis["b"]))
    A = np.concatenate([r[0] for r in res]); B = np.concatenate([r[1] for r in res])
    print(it, f"G_a {A.std() / A.mean():.4f}  G_b {B.std() / B.mean():.4f}  ratio {A.std() / A.mean() / (B.std() / B.mean()):.4f}  mean a {A.mean():.4f} b {B.mean():.4f}", flush=True)
r = np.array([x[0].std() / x[0].mean() / (x[1].std() / x[1].mean()) for x in res])
print(f"ratio per patch {r.mean():.4f} ± {r.std(ddof=1) / np.sqrt(r.size):.4f} ({r.size} patches)")
