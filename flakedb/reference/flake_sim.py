"""Independent discrete-flake simulation of sparkle and graininess (docs/texture.md, "Independent check").

Written separately from :mod:`flakedb.texture.model` and sharing no code with it (nor with the
solver): it places individual flakes at random in a periodic patch of the paint, with the recipe's
statistics, and traces them.

* Flakes: per species a Poisson number ρ d L² of discs, centres uniform in the patch (periodic in x
  and y) and in depth over the layer, diameters log-normal (median, σ_g), upper-hemisphere normals
  with the Beckmann density (tan²θ = −α² ln U, azimuth uniform: inverted here).
* Hiding: the straight paths up to the coat's surface, toward the source and toward the observer, are
  intersected with every other flake disc (a uniform cell grid finds the candidates) from 64 points of each
  possible glint's tilted disc (area hiding: a partly covered flake is dimmed by the share covered), from the
  centre for the other flakes (their mean only); each disc crossed multiplies the light by its T(|u·m|, λ);
  pigments and an absorbing coat by e^{−σ s}.  ``hiding="centre"``: the centre for all (the old shortcut).
* Directional light: for flakes near the mirror orientation, the fraction f of the flake's
  reflected beam that enters the aperture is integrated by stratified sampling of the source
  disc (in air, refracted exactly by Snell's law in vector form), exact mirror reflection about the
  flake's normal, a wavelength channel drawn with probability ∝ y R(c) (the flake's own colour) and a
  diffraction offset drawn from the Fraunhofer (Airy) pattern of the flake's projection seen along the
  reflected ray (radius by inverting the encircled energy 1 − J0² − J1² at that channel's λ' = λ/η,
  stretched by 1/|o·m| along the flake's tilt), exact refraction back into air (total internal
  reflection loses the sample) and an exact test against the aperture cone in air; each sample weighs
  its channel's path transmission.  A flake's luminance factor is
  β = π T_in T_out R_Y f c/(μ_l' μ_v Ω_a) (f: the transmission-weighted collected fraction); a glint is a flake with β ≥ β_peak/2, β_peak the
  same quantity for a flake of that diameter at the exact mirror orientation, unattenuated
  (computed by the same sampling); a glint above the fixed threshold, a flake with β ≥ half the peak of
  an aligned, unattenuated R = 1 flake of 16 µm at 555 nm.  Lit spots: pixels of the observer's spot size
  overlapped by a glint's disc; a glint's intensity: β × the largest fraction of one pixel its disc covers.
* Uniform sky, per ray (:func:`_sky_rays`): rays on a regular grid go down along the view; every flake disc a ray
  meets adds, in depth order, t_in t_out Σ y R(|v'·m|) V T_l e^{−τ} (V the flakes met above it: the topmost alone
  for opaque flakes, T_l its mirrored sky path traced from the hit point; 0 if that direction points down or
  is totally internally reflected at the coat); a pixel is the mean of its rays; graininess = std/mean of the
  pixels.  ``sky="deposit"``: each flake's footprint added to the pixels (the old shortcut).
* Collected fraction: "hit" (source and Airy offset sampled, aperture tested) or, for apertures small against
  the Airy core, "density" (:func:`_collected_density`: source and aperture points sampled, the Airy density
  evaluated).

Every function takes plain arrays; :func:`simulate` returns a dict.  numba compiles the loops
(cached).  Statistical errors: Poisson √N on counts; the standard error of the relative standard
deviation from the pixels' kurtosis.
"""

from __future__ import annotations

import numba
import numpy as np
from scipy.special import j0, j1

_FINE_C = 2001  # uniform c grid the per-band R, T tables are resampled to


def _resample(c, table):
    cf = np.linspace(0.0, 1.0, _FINE_C)
    t = np.atleast_2d(np.asarray(table, float))
    return np.stack([np.interp(cf, np.asarray(c, float), row) for row in t])


@numba.njit(cache=True)
def _lookup(table, c):
    """Linear interpolation of a (C, _FINE_C) table at c ∈ [0, 1] → (C,)."""
    n = table.shape[1] - 1
    x = min(max(c, 0.0), 1.0) * n
    i = min(int(x), n - 1)
    t = x - i
    return table[:, i] * (1.0 - t) + table[:, i + 1] * t


@numba.njit(cache=True)
def _fresnel_unpolarised(cos_i, n1, n2):
    """Unpolarised Fresnel reflectance from medium n1 into n2 at |cos θ_i| = cos_i (1 under TIR)."""
    s2 = (n1 / n2) ** 2 * (1.0 - cos_i * cos_i)
    if s2 >= 1.0:
        return 1.0
    ct = np.sqrt(1.0 - s2)
    rs = (n1 * cos_i - n2 * ct) / (n1 * cos_i + n2 * ct)
    rp = (n2 * cos_i - n1 * ct) / (n2 * cos_i + n1 * ct)
    return 0.5 * (rs * rs + rp * rp)


@numba.njit(cache=True)
def _path_transmission(x0, y0, z0, ux, uy, uz, self_idx, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab,
                       cell_start, cell_items, ncell, cell, rmax, absz, absd, abss):
    """Per-channel transmission of the straight path from (x0, y0, depth z0) going up along u (uz > 0 up)
    to the surface: flakes crossed (T of each) and absorbers (e^{−σ s})."""
    C = Ttab.shape[1]
    out = np.ones(C)
    smax = z0 / uz
    # absorbers: depth segments
    for a in range(absz.shape[0]):
        top, bot = absz[a], absz[a] + absd[a]
        seg = max(0.0, min(z0, bot) - max(0.0, top))
        if seg > 0.0:
            for ch in range(C):
                out[ch] *= np.exp(-abss[a, ch] * seg / uz)
    # cells covering the ray's xy extent (+ the largest radius)
    xe, ye = x0 + ux * smax, y0 + uy * smax
    ix0 = int(np.floor((min(x0, xe) - rmax) / cell))
    ix1 = int(np.floor((max(x0, xe) + rmax) / cell))
    iy0 = int(np.floor((min(y0, ye) - rmax) / cell))
    iy1 = int(np.floor((max(y0, ye) + rmax) / cell))
    for ix in range(ix0, ix1 + 1):
        for iy in range(iy0, iy1 + 1):
            cx, cy = ix % ncell, iy % ncell
            shx = (ix - cx) * cell  # periodic image offset
            shy = (iy - cy) * cell
            k = cx * ncell + cy
            for q in range(cell_start[k], cell_start[k + 1]):
                j = cell_items[q]
                if j == self_idx:
                    continue
                if Z[j] >= z0:  # only flakes above (smaller depth)
                    continue
                px, py = X[j] + shx, Y[j] + shy
                # plane of flake j: n·(P − Cj) = 0, P = P0 + s u, depth coordinate z = z0 − s uz
                dx, dy, dz = px - x0, py - y0, -(Z[j] - z0)  # height difference (up positive)
                nu = NX[j] * ux + NY[j] * uy + NZ[j] * uz
                if abs(nu) < 1e-12:
                    continue
                s = (NX[j] * dx + NY[j] * dy + NZ[j] * dz) / nu
                if s <= 1e-9 or s > smax:
                    continue
                hx, hy, hz = x0 + s * ux - px, y0 + s * uy - py, s * uz - dz
                if hx * hx + hy * hy + hz * hz <= RAD[j] * RAD[j]:
                    tr = _lookup(Ttab[SP[j]], abs(nu))
                    for ch in range(C):
                        out[ch] *= tr[ch]
    return out


@numba.njit(cache=True)
def _refract_up_to_air(ox, oy, oz, eta):
    """Refract a binder direction going up (oz > 0) into air; returns (ax, ay, az, ok)."""
    tx, ty = ox * eta, oy * eta
    t2 = tx * tx + ty * ty
    if t2 >= 1.0 or oz <= 0.0:
        return 0.0, 0.0, 0.0, False
    return tx, ty, np.sqrt(1.0 - t2), True


#: Airy radii x = π D θ/λ tabulated for sampling (encircled energy 1 − J0²(x) − J1²(x), Rayleigh); offsets
#: beyond the last (0.3 % of the energy) leave the aperture.
_AIRY_X = np.linspace(0.0, 200.0, 200001)


def _airy_cdf():
    """The Airy pattern's encircled energy at :data:`_AIRY_X` (Bessel functions: scipy.special)."""
    return 1.0 - j0(_AIRY_X) ** 2 - j1(_AIRY_X) ** 2


@numba.njit(cache=True)
def _source_mirrored(u1, u2, r_s, lx, ly, lz, ex, ey, ez, fx, fy, fz, eta, mx, my, mz):
    """A point of the source, uniform in the cone of half-angle r_s around the air direction l (frame e, f
    across it; u1 ↦ the cosine of its offset, u2 ↦ its azimuth), refracted into the binder (toward the source,
    going up: tangential / η) and mirrored about the flake normal m: (o_x, o_y, o_z, b·m)."""
    cth = 1.0 - u1 * (1.0 - np.cos(r_s))
    sth = np.sqrt(max(0.0, 1.0 - cth * cth))
    ph = 2.0 * np.pi * u2
    sx = cth * lx + sth * (np.cos(ph) * ex + np.sin(ph) * fx)
    sy = cth * ly + sth * (np.cos(ph) * ey + np.sin(ph) * fy)
    bx, by = sx / eta, sy / eta
    bz = np.sqrt(1.0 - bx * bx - by * by)
    dm = bx * mx + by * my + bz * mz
    return 2.0 * dm * mx - bx, 2.0 * dm * my - by, 2.0 * dm * mz - bz, dm


@numba.njit(cache=True)
def _collected_fraction(mx, my, mz, D, eta, lx, ly, lz, vx, vy, vz, r_s, r_a, lam_ch, p_ch, wt_ch, us, ud, uc,
                        rot1, rot2, airy_cdf, airy_x):
    """Mean over the source, the flake's diffraction and its colours of (weight of the sampled channel) × (the
    ray enters the aperture), for a flake of normal m: each sample draws a point of the source disc (air),
    refracts it, mirrors it about m, draws a wavelength channel with probability ``p_ch`` and an offset from
    the Fraunhofer pattern of the flake's projection seen along the reflected ray (a disc of diameter D
    foreshortened to D |o·m| along the tilt: Airy radius x = π D θ/λ' by inverting the encircled energy,
    stretched by 1/|o·m| along the tilt), refracts back to air and tests the aperture cone."""
    ex, ey, ez = lz, 0.0, -lx  # light is in the x-z plane
    nrm = np.sqrt(ex * ex + ey * ey + ez * ez)
    ex, ey, ez = ex / nrm, ey / nrm, ez / nrm
    fx, fy, fz = ly * ez - lz * ey, lz * ex - lx * ez, lx * ey - ly * ex
    cos_a = np.cos(r_a)
    K = us.shape[0]
    C = p_ch.shape[0]
    acc = np.zeros(C)
    for k in range(K):
        ox, oy, oz, dm = _source_mirrored((us[k, 0] + rot1) % 1.0, (us[k, 1] + rot2) % 1.0, r_s, lx, ly, lz, ex, ey, ez,
                                          fx, fy, fz, eta, mx, my, mz)
        # the wavelength channel
        uch = (uc[k] + rot1 + rot2) % 1.0
        ch = 0
        cum = p_ch[0]
        while uch > cum and ch < C - 1:
            ch += 1
            cum += p_ch[ch]
        # Airy offset: radius from the encircled energy, direction uniform
        w1 = (ud[k, 0] + rot2) % 1.0
        w2 = (ud[k, 1] + rot1) % 1.0
        j = np.searchsorted(airy_cdf, w1)
        if j >= airy_cdf.shape[0]:
            continue  # beyond the tabulated pattern: lost
        x = airy_x[j]
        if j > 0 and airy_cdf[j] > airy_cdf[j - 1]:
            x = airy_x[j - 1] + (w1 - airy_cdf[j - 1]) / (airy_cdf[j] - airy_cdf[j - 1]) * (airy_x[j] - airy_x[j - 1])
        rr = x * lam_ch[ch] / (np.pi * D)
        ps = 2.0 * np.pi * w2
        # frame around o: t along the flake's tilt as seen from o (where the projection is foreshortened)
        tx, ty, tz = mx - dm * ox, my - dm * oy, mz - dm * oz
        tn = np.sqrt(tx * tx + ty * ty + tz * tz)
        if tn < 1e-12:
            if abs(oz) < 0.9:
                tx, ty, tz = -oy, ox, 0.0
            else:
                tx, ty, tz = 0.0, -oz, oy
            tn = np.sqrt(tx * tx + ty * ty + tz * tz)
        tx, ty, tz = tx / tn, ty / tn, tz / tn
        kx, ky, kz = oy * tz - oz * ty, oz * tx - ox * tz, ox * ty - oy * tx
        a_t = rr * np.cos(ps) / max(abs(dm), 1e-6)
        a_k = rr * np.sin(ps)
        ox2 = ox + a_t * tx + a_k * kx
        oy2 = oy + a_t * ty + a_k * ky
        oz2 = oz + a_t * tz + a_k * kz
        on = np.sqrt(ox2 * ox2 + oy2 * oy2 + oz2 * oz2)
        ax, ay, az, ok = _refract_up_to_air(ox2 / on, oy2 / on, oz2 / on, eta)
        if ok and ax * vx + ay * vy + az * vz >= cos_a:
            acc[ch] += wt_ch[ch]
    return acc / K


@numba.njit(cache=True)
def _area_transmission(i, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab, cell_start, cell_items, ncell, cell, rmax,
                       absz, absd, abss, blx, bly, blz, bvx, bvy, bvz, disc):
    """Per channel, the mean over points of flake i's tilted disc (``disc``: (Q, 2) points of the unit disc) of
    the light path's × the view path's transmission from that point (:func:`_path_transmission`): the flakes
    above and the absorbers crossed, per point, so a partly covered flake is dimmed by the share covered
    (area hiding).  One point at (0, 0): the path from the centre only."""
    mx, my, mz = NX[i], NY[i], NZ[i]
    if abs(mz) < 0.9:
        ax, ay, az = 0.0, 0.0, 1.0
    else:
        ax, ay, az = 1.0, 0.0, 0.0
    e1x, e1y, e1z = ay * mz - az * my, az * mx - ax * mz, ax * my - ay * mx
    n1 = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    e1x, e1y, e1z = e1x / n1, e1y / n1, e1z / n1
    e2x, e2y, e2z = my * e1z - mz * e1y, mz * e1x - mx * e1z, mx * e1y - my * e1x
    C = Ttab.shape[1]
    acc = np.zeros(C)
    Q = disc.shape[0]
    for q in range(Q):
        dx = RAD[i] * (disc[q, 0] * e1x + disc[q, 1] * e2x)
        dy = RAD[i] * (disc[q, 0] * e1y + disc[q, 1] * e2y)
        dz = RAD[i] * (disc[q, 0] * e1z + disc[q, 1] * e2z)  # up
        z0 = max(Z[i] - dz, 1e-9)
        tl = _path_transmission(X[i] + dx, Y[i] + dy, z0, blx, bly, blz, i, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab,
                                cell_start, cell_items, ncell, cell, rmax, absz, absd, abss)
        tv = _path_transmission(X[i] + dx, Y[i] + dy, z0, bvx, bvy, bvz, i, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab,
                                cell_start, cell_items, ncell, cell, rmax, absz, absd, abss)
        for ch in range(C):
            acc[ch] += tl[ch] * tv[ch]
    return acc / Q


@numba.njit(cache=True)
def _airy_density(airy_x, airy_pdf, x):
    """[2 J1(x)/x]² from the table (0 beyond it)."""
    n = airy_x.shape[0] - 1
    step = airy_x[1] - airy_x[0]
    u = x / step
    if u >= n:
        return 0.0
    j = int(u)
    t = u - j
    return airy_pdf[j] * (1.0 - t) + airy_pdf[j + 1] * t


@numba.njit(cache=True)
def _collected_density(mx, my, mz, D, eta, lx, ly, lz, vx, vy, vz, r_s, r_a, lam_ch, p_ch, wt_ch, us, ua, uc,
                       rot1, rot2, airy_x, airy_pdf):
    """The same mean as :func:`_collected_fraction` by a second estimator, for cones that are not wide against
    the flake's diffraction (a person's pupil): pairs of a source point and an aperture point (air, uniform in
    their cones), the source point refracted and mirrored about m, the aperture point refracted into the
    binder, and the flake's Fraunhofer density (:func:`airy_pattern`'s (A c/λ²)[2 J1(x)/x]² of its projection
    seen along the mirrored ray, D c along the tilt × D) evaluated at their offset, × Ω_a μ_a/(η² μ_a') (the
    aperture's solid angle mapped into the binder); a channel drawn per pair with probability p_ch.  Both
    estimators return the per-channel sums (C,) (× wt_ch), so one pass serves any path transmissions."""
    ex, ey, ez = lz, 0.0, -lx
    nrm = np.sqrt(ex * ex + ey * ey + ez * ez)
    ex, ey, ez = ex / nrm, ey / nrm, ez / nrm
    fx, fy, fz = ly * ez - lz * ey, lz * ex - lx * ez, lx * ey - ly * ex
    gx, gy, gz = vz, 0.0, -vx
    nrm = np.sqrt(gx * gx + gy * gy + gz * gz)
    gx, gy, gz = gx / nrm, gy / nrm, gz / nrm
    hx, hy, hz = vy * gz - vz * gy, vz * gx - vx * gz, vx * gy - vy * gx
    om_a = 2.0 * np.pi * (1.0 - np.cos(r_a))
    K = us.shape[0]
    C = p_ch.shape[0]
    acc = np.zeros(C)
    for k in range(K):
        ox, oy, oz, dm = _source_mirrored((us[k, 0] + rot1) % 1.0, (us[k, 1] + rot2) % 1.0, r_s, lx, ly, lz, ex, ey, ez,
                                          fx, fy, fz, eta, mx, my, mz)
        # aperture point (air), refracted into the binder
        w1 = (ua[k, 0] + rot2) % 1.0
        w2 = (ua[k, 1] + rot1) % 1.0
        cta = 1.0 - w1 * (1.0 - np.cos(r_a))
        sta = np.sqrt(max(0.0, 1.0 - cta * cta))
        pa = 2.0 * np.pi * w2
        ax = cta * vx + sta * (np.cos(pa) * gx + np.sin(pa) * hx)
        ay = cta * vy + sta * (np.cos(pa) * gy + np.sin(pa) * hy)
        az = cta * vz + sta * (np.cos(pa) * gz + np.sin(pa) * hz)
        qx, qy = ax / eta, ay / eta
        qz = np.sqrt(1.0 - qx * qx - qy * qy)
        jac = om_a * az / (eta * eta * qz)
        # offset of q from o in o's tangent plane, along the tilt t and across it k
        tx, ty, tz = mx - dm * ox, my - dm * oy, mz - dm * oz
        tn = np.sqrt(tx * tx + ty * ty + tz * tz)
        if tn < 1e-12:
            if abs(oz) < 0.9:
                tx, ty, tz = -oy, ox, 0.0
            else:
                tx, ty, tz = 0.0, -oz, oy
            tn = np.sqrt(tx * tx + ty * ty + tz * tz)
        tx, ty, tz = tx / tn, ty / tn, tz / tn
        kx, ky, kz = oy * tz - oz * ty, oz * tx - ox * tz, ox * ty - oy * tx
        dq = qx * ox + qy * oy + qz * oz
        if dq <= 0.0:
            continue
        th_t = (qx * tx + qy * ty + qz * tz) / dq  # gnomonic coordinates around o
        th_k = (qx * kx + qy * ky + qz * kz) / dq
        c = max(abs(dm), 1e-6)
        rr = np.sqrt((c * th_t) ** 2 + th_k * th_k)
        uch = (uc[k] + rot1 + rot2) % 1.0
        ch = 0
        cum = p_ch[0]
        while uch > cum and ch < C - 1:
            ch += 1
            cum += p_ch[ch]
        lam = lam_ch[ch]
        dens = 0.25 * np.pi * D * D * c / (lam * lam) * _airy_density(airy_x, airy_pdf, np.pi * D * rr / lam)
        acc[ch] += wt_ch[ch] * dens * jac
    return acc / K


@numba.njit(cache=True)
def _sky_rays(X, Y, Z, NX, NY, NZ, RAD, SP, Rtab, Ttab, y, cell_start, cell_items, ncell, cell, rmax,
              absz, absd, abss, eta, vx, vy, vz, t_out, L, nsub, npx, zmax, nw):
    """The uniform sky's luminance factor of every pixel rendered per ray (npx, npx): ``nsub``² rays per pixel
    (a regular grid) go down along the view; every flake disc a ray meets, in depth order, adds
    t_in t_out Σ_c y_c R_c(|v'·m|) V_c T_l,c e^{−τ_v}, V the transmission of the flakes the ray met above it
    (0 for opaque flakes: the topmost flake alone), T_l the path from the hit point along the mirrored
    direction toward the sky (:func:`_path_transmission`: flakes and absorbers), τ_v the absorbers along the
    view (0 where the mirrored direction points down or is totally internally reflected at the coat)."""
    bvx, bvy = vx / eta, vy / eta
    bvz = np.sqrt(1.0 - bvx * bvx - bvy * bvy)
    C = y.shape[0]
    p = L / npx
    step = p / nsub
    img = np.zeros((nw, nw))  # the window of the first nw × nw pixels
    MAXH = 256
    hd = np.zeros(MAXH)
    hi = np.zeros(MAXH, dtype=np.int64)
    sx, sy = bvx / bvz, bvy / bvz  # lateral drift per µm of depth (the ray goes down: x − depth sx)
    for a in range(nw * nsub):
        for b in range(nw * nsub):
            x0 = (a + 0.5) * step
            y0 = (b + 0.5) * step
            xe, ye = x0 - zmax * sx, y0 - zmax * sy
            ix0 = int(np.floor((min(x0, xe) - rmax) / cell))
            ix1 = int(np.floor((max(x0, xe) + rmax) / cell))
            iy0 = int(np.floor((min(y0, ye) - rmax) / cell))
            iy1 = int(np.floor((max(y0, ye) + rmax) / cell))
            nh = 0
            for ix in range(ix0, ix1 + 1):
                for iy in range(iy0, iy1 + 1):
                    cx, cy = ix % ncell, iy % ncell
                    shx = (ix - cx) * cell
                    shy = (iy - cy) * cell
                    k = cx * ncell + cy
                    for q in range(cell_start[k], cell_start[k + 1]):
                        j = cell_items[q]
                        px, py = X[j] + shx, Y[j] + shy
                        # ray point at depth t: (x0 − t sx, y0 − t sy); plane m·(P − C) = 0, heights up = −depth
                        den = NZ[j] + NX[j] * sx + NY[j] * sy
                        num = NX[j] * (x0 - px) + NY[j] * (y0 - py) + NZ[j] * Z[j]
                        if abs(den) < 1e-12:
                            continue
                        t = num / den  # depth of the hit: m·((x0 − t sx − px), (y0 − t sy − py), (−t + Z)) = 0
                        if t <= 0.0:
                            continue
                        hx, hy, hz = x0 - t * sx - px, y0 - t * sy - py, Z[j] - t
                        if hx * hx + hy * hy + hz * hz <= RAD[j] * RAD[j] and nh < MAXH:
                            hd[nh] = t
                            hi[nh] = j
                            nh += 1
            # depth order (insertion sort: few hits)
            for u in range(1, nh):
                dv, iv = hd[u], hi[u]
                w = u - 1
                while w >= 0 and hd[w] > dv:
                    hd[w + 1] = hd[w]
                    hi[w + 1] = hi[w]
                    w -= 1
                hd[w + 1] = dv
                hi[w + 1] = iv
            V = np.ones(C)
            lum = 0.0
            for u in range(nh):
                j = hi[u]
                t = hd[u]
                mx, my, mz = NX[j], NY[j], NZ[j]
                cv = bvx * mx + bvy * my + bvz * mz
                if cv < 0.0:
                    mx, my, mz, cv = -mx, -my, -mz, -cv
                lx, ly, lz = 2.0 * cv * mx - bvx, 2.0 * cv * my - bvy, 2.0 * cv * mz - bvz
                s2 = (1.0 - lz * lz) * eta * eta
                if lz > 1e-6 and s2 < 1.0:
                    t_in = 1.0 - _fresnel_unpolarised(np.sqrt(1.0 - s2), 1.0, eta)
                    R = _lookup(Rtab[SP[j]], cv)
                    px, py = x0 - t * sx, y0 - t * sy
                    tl = _path_transmission(px, py, t, lx, ly, lz, j, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab,
                                            cell_start, cell_items, ncell, cell, rmax, absz, absd, abss)
                    for ch in range(C):
                        att = 1.0
                        for aa in range(absz.shape[0]):
                            seg = max(0.0, min(t, absz[aa] + absd[aa]) - max(0.0, absz[aa]))
                            att *= np.exp(-abss[aa, ch] * seg / bvz)
                        lum += t_in * t_out * y[ch] * R[ch] * tl[ch] * V[ch] * att
                Tj = _lookup(Ttab[SP[j]], cv)
                vmax = 0.0
                for ch in range(C):
                    V[ch] *= Tj[ch]
                    vmax = max(vmax, V[ch])
                if vmax < 1e-7:
                    break
            img[a // nsub, b // nsub] += lum
    return img / (nsub * nsub)


@numba.njit(cache=True)
def _directional(X, Y, Z, NX, NY, NZ, RAD, SP, Rtab, Ttab, y, cell_start, cell_items, ncell, cell, rmax,
                 absz, absd, abss, eta, lx, ly, lz, vx, vy, vz, r_s, r_a, lam_ch, us, ud, uc, rots,
                 cos_cut, t_in, t_out, mu_lb, mu_v, om_a, airy_cdf, airy_x, airy_pdf, disc, density, beta_ref_half):
    """Per flake: β (luminance factor), β_peak of its diameter, and whether it was examined.  Each flake's
    colours: channels drawn with probability ∝ y R(c) and weighted by their path transmissions, so the
    luminance Σ y R T_l T_v f is estimated per channel, each with its own wavelength's pattern."""
    N = X.shape[0]
    C = y.shape[0]
    beta = np.zeros(N)
    peak = np.zeros(N)
    # binder directions of the source and view centres (toward them, going up)
    blx, bly = lx / eta, ly / eta
    blz = np.sqrt(1.0 - blx * blx - bly * bly)
    bvx, bvy = vx / eta, vy / eta
    bvz = np.sqrt(1.0 - bvx * bvx - bvy * bvy)
    hx, hy, hz = blx + bvx, bly + bvy, blz + bvz
    hn = np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / hn, hy / hn, hz / hn
    c_h = blx * hx + bly * hy + blz * hz
    ones = np.ones(C)
    centre = np.zeros((1, 2))
    for i in range(N):
        D = 2.0 * RAD[i]
        if NX[i] * hx + NY[i] * hy + NZ[i] * hz < cos_cut[i]:
            continue
        Rh = _lookup(Rtab[SP[i]], c_h)
        yRh = y * Rh
        RYh = yRh.sum()
        if RYh <= 0.0:
            continue
        if density:
            f0 = _collected_density(hx, hy, hz, D, eta, lx, ly, lz, vx, vy, vz, r_s, r_a, lam_ch, yRh / RYh, ones,
                                    us, ud, uc, rots[i, 0], rots[i, 1], airy_x, airy_pdf).sum()
        else:
            f0 = _collected_fraction(hx, hy, hz, D, eta, lx, ly, lz, vx, vy, vz, r_s, r_a, lam_ch, yRh / RYh, ones,
                                     us, ud, uc, rots[i, 0], rots[i, 1], airy_cdf, airy_x).sum()
        peak[i] = np.pi * t_in * t_out * RYh * f0 * c_h / (mu_lb * mu_v * om_a)
        c = abs(blx * NX[i] + bly * NY[i] + blz * NZ[i])
        R = _lookup(Rtab[SP[i]], c)
        yR = y * R
        RY = yR.sum()
        if RY <= 0.0:
            continue
        if density:
            acc = _collected_density(NX[i], NY[i], NZ[i], D, eta, lx, ly, lz, vx, vy, vz, r_s, r_a, lam_ch, yR / RY,
                                     ones, us, ud, uc, rots[i, 0], rots[i, 1], airy_x, airy_pdf)
        else:
            acc = _collected_fraction(NX[i], NY[i], NZ[i], D, eta, lx, ly, lz, vx, vy, vz, r_s, r_a, lam_ch, yR / RY,
                                      ones, us, ud, uc, rots[i, 0], rots[i, 1], airy_cdf, airy_x)
        k = np.pi * t_in * t_out * RY * c / (mu_lb * mu_v * om_a)
        # hiding only dims: a flake below both thresholds unhidden is no glint, and its mean needs no area
        # average (over the placements the centre's transmission has the area mean's expectation)
        pts = disc if k * acc.sum() >= min(0.5 * peak[i], beta_ref_half) else centre
        wt = _area_transmission(i, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab, cell_start, cell_items, ncell, cell, rmax,
                                absz, absd, abss, blx, bly, blz, bvx, bvy, bvz, pts)
        beta[i] = k * (acc * wt).sum()
    return beta, peak


@numba.njit(cache=True)
def _sky(X, Y, Z, NX, NY, NZ, RAD, SP, Rtab, Ttab, y, cell_start, cell_items, ncell, cell, rmax,
         absz, absd, abss, eta, vx, vy, vz, t_out):
    """Per flake: its luminance factor b under a uniform sky (module docstring)."""
    N = X.shape[0]
    b = np.zeros(N)
    bvx, bvy = vx / eta, vy / eta
    bvz = np.sqrt(1.0 - bvx * bvx - bvy * bvy)
    for i in range(N):
        mx, my, mz = NX[i], NY[i], NZ[i]
        cv = bvx * mx + bvy * my + bvz * mz
        if cv < 0.0:
            mx, my, mz, cv = -mx, -my, -mz, -cv
        lx, ly, lz = 2.0 * cv * mx - bvx, 2.0 * cv * my - bvy, 2.0 * cv * mz - bvz
        if lz <= 1e-6:
            continue
        s2 = (1.0 - lz * lz) * eta * eta
        if s2 >= 1.0:
            continue
        t_in = 1.0 - _fresnel_unpolarised(np.sqrt(1.0 - s2), 1.0, eta)
        R = _lookup(Rtab[SP[i]], cv)
        tl = _path_transmission(X[i], Y[i], Z[i], lx, ly, lz, i, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab,
                                cell_start, cell_items, ncell, cell, rmax, absz, absd, abss)
        tv = _path_transmission(X[i], Y[i], Z[i], bvx, bvy, bvz, i, X, Y, Z, NX, NY, NZ, RAD, SP, Ttab,
                                cell_start, cell_items, ncell, cell, rmax, absz, absd, abss)
        s = 0.0
        for ch in range(y.shape[0]):
            s += y[ch] * R[ch] * tl[ch] * tv[ch]
        b[i] = t_in * t_out * s
    return b


@numba.njit(cache=True)
def _deposit(X, Y, Z, NX, NY, NZ, RAD, val, p, npx, L, disc, bvx, bvy, bvz):
    """Pixel map (npx, npx) of Σ val × (area of the flake's footprint in the pixel)/p², periodic: each point of
    the flake's tilted disc (normal m, points of ``disc`` on it) carried up along the view v' = (bvx, bvy, bvz)
    (binder, up) to the surface, so the footprint is the ellipse of area A |m·v'|/v'_z."""
    img = np.zeros((npx, npx))
    Q = disc.shape[0]
    sx, sy = bvx / bvz, bvy / bvz
    for i in range(X.shape[0]):
        if val[i] == 0.0:
            continue
        mx, my, mz = NX[i], NY[i], NZ[i]
        # an orthonormal basis (e1, e2) of the flake's plane
        if abs(mz) < 0.9:
            ax, ay, az = 0.0, 0.0, 1.0
        else:
            ax, ay, az = 1.0, 0.0, 0.0
        e1x, e1y, e1z = ay * mz - az * my, az * mx - ax * mz, ax * my - ay * mx
        n1 = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
        e1x, e1y, e1z = e1x / n1, e1y / n1, e1z / n1
        e2x, e2y, e2z = my * e1z - mz * e1y, mz * e1x - mx * e1z, mx * e1y - my * e1x
        area = np.pi * RAD[i] * RAD[i] * abs(mx * bvx + my * bvy + mz * bvz) / bvz
        w = val[i] * area / (Q * p * p)
        for q in range(Q):
            dx = RAD[i] * (disc[q, 0] * e1x + disc[q, 1] * e2x)
            dy = RAD[i] * (disc[q, 0] * e1y + disc[q, 1] * e2y)
            dz = RAD[i] * (disc[q, 0] * e1z + disc[q, 1] * e2z)  # up
            depth = Z[i] - dz
            x = (X[i] + dx + depth * sx) % L
            yy = (Y[i] + dy + depth * sy) % L
            img[min(int(x / p), npx - 1), min(int(yy / p), npx - 1)] += w
    return img


@numba.njit(cache=True)
def _brightest_fill(X, Y, RAD, glint, p, disc):
    """Per glint: the largest fraction of one p × p pixel its disc covers (its points binned into pixels)."""
    out = np.zeros(X.shape[0])
    Q = disc.shape[0]
    for i in range(X.shape[0]):
        if not glint[i]:
            continue
        r = RAD[i]
        i0, j0 = int(np.floor((X[i] - r) / p)), int(np.floor((Y[i] - r) / p))
        n = int(np.ceil(2.0 * r / p)) + 2
        counts = np.zeros((n, n))
        for q in range(Q):
            a = int(np.floor((X[i] + r * disc[q, 0]) / p)) - i0
            b = int(np.floor((Y[i] + r * disc[q, 1]) / p)) - j0
            counts[min(max(a, 0), n - 1), min(max(b, 0), n - 1)] += 1.0
        out[i] = min(counts.max() / Q * np.pi * r * r / (p * p), 1.0)
    return out


@numba.njit(cache=True)
def _lit(X, Y, RAD, glint, p, npx, L):
    """Pixels (npx, npx) overlapped by a glint's disc (closest-point test), periodic."""
    img = np.zeros((npx, npx), dtype=np.bool_)
    for i in range(X.shape[0]):
        if not glint[i]:
            continue
        r = RAD[i]
        i0, i1 = int(np.floor((X[i] - r) / p)), int(np.floor((X[i] + r) / p))
        j0, j1 = int(np.floor((Y[i] - r) / p)), int(np.floor((Y[i] + r) / p))
        for a in range(i0, i1 + 1):
            for bb in range(j0, j1 + 1):
                qx = min(max(X[i], a * p), (a + 1) * p)
                qy = min(max(Y[i], bb * p), (bb + 1) * p)
                if (qx - X[i]) ** 2 + (qy - Y[i]) ** 2 <= r * r:
                    img[a % npx, bb % npx] = True
    return img


def _stratified(n, rng):
    """n × 2 stratified points in the unit square (a jittered √n × √n grid, shuffled)."""
    m = int(np.ceil(np.sqrt(n)))
    g = (np.stack(np.meshgrid(np.arange(m), np.arange(m), indexing="ij"), -1).reshape(-1, 2) + rng.random((m * m, 2))) / m
    return g[rng.permutation(m * m)[:n]]


def _disc_points(n):
    """n points evenly spread on the unit disc (Vogel's sunflower spiral)."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    th = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(th), r * np.sin(th)], -1)


def place_flakes(species, L_um, rng):
    """Flake discs of every species in an L × L µm periodic patch: (X, Y, depth Z, normal NX NY NZ,
    radius, species index).  ``species``: dicts with z_top_um, thickness_um, number_density_per_um3,
    diameter_median_um, diameter_gsd, alpha.

    >>> sp = dict(z_top_um=5.0, thickness_um=10.0, number_density_per_um3=1e-3, diameter_median_um=15.0,
    ...           diameter_gsd=1.3, alpha=0.2)
    >>> X, Y, Z, NX, NY, NZ, RAD, S = place_flakes([sp], 200.0, np.random.default_rng(0))
    >>> abs(X.size - 400) < 4 * 20, bool(np.all((Z >= 5.0) & (Z <= 15.0))), bool(np.allclose(NX**2 + NY**2 + NZ**2, 1.0))
    (True, True, True)
    """
    cols = [[] for _ in range(8)]
    for s, sp in enumerate(species):
        n = rng.poisson(sp["number_density_per_um3"] * sp["thickness_um"] * L_um * L_um)
        u = rng.random((n, 5))
        D = sp["diameter_median_um"] * np.exp(np.log(sp["diameter_gsd"]) * rng.standard_normal(n))
        tan2 = -(sp["alpha"] ** 2) * np.log(1.0 - u[:, 3])
        ct = 1.0 / np.sqrt(1.0 + tan2)
        st = np.sqrt(tan2) * ct
        ph = 2.0 * np.pi * u[:, 4]
        for col, v in zip(cols, (u[:, 0] * L_um, u[:, 1] * L_um, sp["z_top_um"] + u[:, 2] * sp["thickness_um"],
                                 st * np.cos(ph), st * np.sin(ph), ct, 0.5 * D, np.full(n, s))):
            col.append(v)
    out = [np.concatenate(c) if c else np.zeros(0) for c in cols]
    out[7] = out[7].astype(np.int64)
    return out


def _cells(X, Y, L, cell_target):
    ncell = max(1, int(L // cell_target))
    cell = L / ncell
    k = (np.minimum((X // cell).astype(np.int64), ncell - 1) * ncell + np.minimum((Y // cell).astype(np.int64), ncell - 1))
    order = np.argsort(k, kind="stable")
    start = np.searchsorted(k[order], np.arange(ncell * ncell + 1))
    return start.astype(np.int64), order.astype(np.int64), ncell, cell


def simulate(eta, y_weights, species, absorbers, spot_um, aperture_half_angle_rad, source_half_angle_deg,
             view_deg, light_deg=(), L_um=2000.0, seed=0, n_samples=256, diffuse=True,
             wavelength_nm=555.0, hiding="area", hiding_points=64, estimator="auto", sky="rays", ray_um=1.0,
             sky_pixels=None) -> dict:
    """Simulate one patch (module docstring).  ``species``: dicts as :func:`place_flakes` plus c, R
    (C, nc), T (C, nc); ``absorbers``: dicts z_top_um, thickness_um, sigma_per_um (C,).  Returns
    {"flakes": N, "area_mm2", "directional": [{light_deg, glints, glints_per_mm2, sigma_glints_per_mm2,
    sparkle_area_fraction, sparkle_intensity, ...}], "diffuse": {graininess, sigma, mean}}.

    ``hiding``: "area" (the paths from ``hiding_points`` points of each flake's disc, so a partly covered flake is
    dimmed by the share covered) or "centre" (from its centre only: the shortcut the issue found, kept to
    measure it).  ``estimator``: "hit" (:func:`_collected_fraction`, source and diffraction sampled, the aperture
    tested), "density" (:func:`_collected_density`, source and aperture sampled, the Airy density evaluated)
    or "auto" (density where the aperture's radius in the binder is below the 16 µm flake's Airy half maximum at
    555 nm: a person's pupil, where hit-or-miss has almost no hits).  ``sky``: "rays" (:func:`_sky_rays`, the
    topmost flake per ray, rays ``ray_um`` apart, rounded to a whole number per pixel) or "deposit" (each
    flake's footprint added to the pixels, overlaps additive: the old shortcut); ``sky_pixels``: the rays render
    only the first sky_pixels × sky_pixels pixels of the patch (default all)."""
    rng = np.random.default_rng(seed)
    y = np.asarray(y_weights, float)
    X, Y, Z, NX, NY, NZ, RAD, SP = place_flakes(species, L_um, rng)
    Rtab = np.stack([_resample(s["c"], s["R"]) for s in species]) if species else np.zeros((1, y.size, _FINE_C))
    Ttab = np.stack([_resample(s["c"], s["T"]) for s in species]) if species else np.zeros((1, y.size, _FINE_C))
    absz = np.array([a["z_top_um"] for a in absorbers], float)
    absd = np.array([a["thickness_um"] for a in absorbers], float)
    abss = np.array([np.broadcast_to(np.asarray(a["sigma_per_um"], float), y.shape) for a in absorbers]).reshape(len(absorbers), y.size)
    cell_target = max(4.0 * float(np.median(RAD)) if RAD.size else 10.0, 10.0)
    start, items, ncell, cell = _cells(X, Y, L_um, cell_target)
    rmax = float(RAD.max()) if RAD.size else 0.0
    p = float(spot_um)
    npx = max(1, int(round(L_um / p)))
    p = L_um / npx
    th_v = np.radians(view_deg)
    vx, vy, vz = -np.sin(th_v), 0.0, np.cos(th_v)
    mu_v = np.cos(th_v)
    t_out = 1.0 - float(_fresnel_unpolarised(mu_v, 1.0, eta))
    om_a = 2.0 * np.pi * (1.0 - np.cos(aperture_half_angle_rad))
    r_s = np.radians(source_half_angle_deg)
    lam_b = float(np.max(wavelength_nm)) * 1e-3 / eta  # the widest pattern (the candidates' reach)
    lam_ch = np.broadcast_to(np.asarray(wavelength_nm, float), y.shape) * 1e-3 / eta  # per channel, binder
    airy_cdf = _airy_cdf()
    xs = np.where(_AIRY_X > 0, _AIRY_X, 1.0)
    airy_pdf = np.where(_AIRY_X > 0, (2.0 * j1(xs) / xs) ** 2, 1.0)
    disc = _disc_points(int(hiding_points)) if hiding == "area" else np.zeros((1, 2))
    if estimator == "auto":
        estimator = "density" if aperture_half_angle_rad / eta < 0.514 * 0.555 / eta / 16.0 else "hit"
    area_mm2 = (L_um * 1e-3) ** 2
    out = {"flakes": int(X.size), "area_mm2": area_mm2, "pixels": npx * npx, "directional": []}
    us, ud = _stratified(n_samples, rng), _stratified(n_samples, rng)
    uc = (np.arange(n_samples) + rng.random(n_samples)) / n_samples
    uc = uc[rng.permutation(n_samples)]
    # the fixed threshold's reference flake, once per light: 64× the samples (its estimate sets every count)
    n_ref = 64 * n_samples
    us_ref, ud_ref = _stratified(n_ref, rng), _stratified(n_ref, rng)
    uc_ref = (np.arange(n_ref) + rng.random(n_ref)) / n_ref
    for a in light_deg:
        th = np.radians(a)
        lx, ly, lz = np.sin(th), 0.0, np.cos(th)
        mu_lb = np.sqrt(1.0 - (np.sin(th) / eta) ** 2)
        t_in = 1.0 - float(_fresnel_unpolarised(np.cos(th), 1.0, eta))
        # the fixed threshold: half the peak of an aligned, unattenuated R = 1 flake of 16 µm at 555 nm
        blz = np.sqrt(1.0 - (lx / eta) ** 2)
        hx, hz = lx / eta + vx / eta, blz + np.sqrt(1.0 - (vx / eta) ** 2)
        hn = np.hypot(hx, hz)
        c_h = (lx / eta * hx + blz * hz) / hn
        if estimator == "density":
            f_ref = _collected_density(hx / hn, 0.0, hz / hn, 16.0, eta, lx, ly, lz, vx, vy, vz, r_s,
                                       aperture_half_angle_rad, np.array([0.555 / eta]), np.ones(1), np.ones(1),
                                       us_ref, ud_ref, uc_ref, 0.0, 0.0, _AIRY_X, airy_pdf).sum()
        else:
            f_ref = _collected_fraction(hx / hn, 0.0, hz / hn, 16.0, eta, lx, ly, lz, vx, vy, vz, r_s,
                                        aperture_half_angle_rad, np.array([0.555 / eta]), np.ones(1), np.ones(1),
                                        us_ref, ud_ref, uc_ref, 0.0, 0.0, airy_cdf, _AIRY_X).sum()
        beta_ref = np.pi * t_in * t_out * f_ref * c_h / (mu_lb * mu_v * om_a)
        # candidates: normals within reach of h': beam offsets up to the source + aperture + 6 λ'/D (the Airy
        # pattern there is 4e-4 of its peak), halved (the half-vector map), ×1.5 margin, over the flake cosine
        r_sb = r_s / eta
        reach = 0.75 * (r_sb + aperture_half_angle_rad / eta + 6.0 * lam_b / (2.0 * RAD)) / c_h + 1e-3
        cos_cut = np.cos(np.minimum(reach, np.pi / 2))
        rots = rng.random((X.size, 2))
        beta, peak = _directional(X, Y, Z, NX, NY, NZ, RAD, SP, Rtab, Ttab, y, start, items, ncell, cell, rmax,
                                  absz, absd, abss, eta, lx, ly, lz, vx, vy, vz, r_s, aperture_half_angle_rad,
                                  lam_ch, us, ud, uc, rots, cos_cut, t_in, t_out, mu_lb, mu_v, om_a, airy_cdf, _AIRY_X,
                                  airy_pdf, disc, estimator == "density", 0.5 * beta_ref)
        glint = (peak > 0) & (beta >= 0.5 * peak)
        n = int(glint.sum())
        A = np.pi * RAD**2
        bpx = beta[glint] * _brightest_fill(X, Y, RAD, glint, p, _disc_points(1024))[glint]
        n_fixed = int(np.sum(beta >= 0.5 * beta_ref))
        lit = _lit(X, Y, RAD, glint, p, npx, L_um)
        out["directional"].append({
            "light_deg": float(a), "glints": n, "glints_per_mm2": n / area_mm2,
            "glints_per_mm2_above_threshold": n_fixed / area_mm2,
            "sigma_glints_per_mm2_above_threshold": np.sqrt(max(n_fixed, 1)) / area_mm2,
            "glint_threshold_luminance_factor": float(0.5 * beta_ref),
            "sigma_glints_per_mm2": np.sqrt(max(n, 1)) / area_mm2,
            "sparkle_area_fraction": float(lit.mean()),
            "sparkle_intensity": float(bpx.mean()) if n else 0.0,
            "sigma_sparkle_intensity": float(bpx.std(ddof=1) / np.sqrt(n)) if n > 1 else np.inf,
            "flake_luminance_factor": float(np.sum(beta * A) / (L_um * L_um)),
            "sigma_flake_luminance_factor": float(np.sqrt(np.sum((beta * A) ** 2)) / (L_um * L_um)),
            "peak_luminance_factor_max": float(peak.max()) if peak.size else 0.0,
        })
    if diffuse:
        bvx, bvy = vx / eta, vy / eta
        if sky == "rays":
            zmax = max([s["z_top_um"] + s["thickness_um"] for s in species], default=0.0) + rmax
            img = _sky_rays(X, Y, Z, NX, NY, NZ, RAD, SP, Rtab, Ttab, y, start, items, ncell, cell, rmax,
                            absz, absd, abss, eta, vx, vy, vz, t_out, L_um, max(1, int(round(p / ray_um))), npx, zmax,
                            min(npx, int(sky_pixels or npx)))
        else:
            b = _sky(X, Y, Z, NX, NY, NZ, RAD, SP, Rtab, Ttab, y, start, items, ncell, cell, rmax,
                     absz, absd, abss, eta, vx, vy, vz, t_out)
            img = _deposit(X, Y, Z, NX, NY, NZ, RAD, b, p, npx, L_um, _disc_points(64), bvx, bvy,
                           np.sqrt(1.0 - bvx * bvx - bvy * bvy))
        v = img.ravel()
        m, sd = v.mean(), v.std(ddof=1)
        kurt = np.mean((v - m) ** 4) / max(sd**4, 1e-300)
        G = sd / m if m > 0 else 0.0
        # SE of a relative SD from n values: (G/2) √((κ − 1)/n), plus the mean's relative SE
        se = G * np.sqrt(max(kurt - 1.0, 0.0) / (4.0 * v.size) + (sd / max(m, 1e-300)) ** 2 / v.size)
        out["diffuse"] = {"graininess": float(G), "sigma_graininess": float(se), "mean": float(m),
                          "sigma_mean": float(sd / np.sqrt(v.size))}
    return out
