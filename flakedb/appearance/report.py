"""The colour report of a composed paint: pure functions, arrays and dicts in, dicts and text out.

What a paint lab reads (docs/model.md §6): CIELAB at the multi-angle spectrophotometer geometries,
the flop index, and the directional albedo per incident angle.  The observer, illuminant and
geometry set are a :class:`flakedb.colour.settings.ColourSettings` (default D65 / CIE 1964 10°, the
E2194 45° set; an RGB-mode paint has D65 / 2° only: :func:`flakedb.colour.settings.resolve`).

Geometry (ASTM E2194 / X-Rite MA-T instruments)
-----------------------------------------------
Illumination at 45° from the normal (the E2539 set adds 15°: any θ_i below works alike).  The aspecular angle γ is measured from the specular direction
towards the illuminator, so the detector looks from θ_v = 45° − γ off the normal: on the specular
side for θ_v > 0, on the illuminator's side for θ_v < 0.  In flakedb's conventions
(:mod:`flakedb.conventions`: propagation directions, μ > 0 travels down, φ_d = 0 mirror/forward):
μ_i = cos 45°, μ_o = −cos θ_v, φ_d = 0 on the specular side and φ_d = π on the illuminator's side.
The aspecular angles are −15°, 15°, 25°, 45°, 75°, 110° (θ_v = 60°, 30°, 20°, 0°, −30°, −65°).
Out-of-plane geometries (a third angle, the azimuth; the set "xrite19") are points of the full azimuth:
(μ_i, μ_o, φ_d) from :func:`flakedb.colour.geometry.directions`, f from the table's Fourier series in φ_d.

Reflectance factor = π f(ω_i, ω_o): the tabulated part only.  The smooth coat's mirror term is a
delta at γ = 0, which no aspecular angle hits, so it adds nothing to these geometries (it is
included in the albedo).  f comes from the table by the file readers' interpolation (Catmull–Rom
in μ_i and μ_o over the file nodes, docs/bsdf-format.md "Evaluation"), here in float64 on the
full-precision table (:func:`eval_table`); it agrees with :meth:`flakedb.bsdf.FourierBSDF.eval` of
the written ``.h5`` (tested).

Colour: spectral channels → XYZ by :func:`flakedb.colour.tolerance.reflectance_to_XYZ` under the
settings' observer and illuminant (Y = 1 for the perfect white); RGB-mode channels (white-normalised linear sRGB) → XYZ by the exact inverse of
:func:`flakedb.colour.colorimetry.XYZ_to_linear_sRGB` after undoing the white normalisation; a mono channel
is a grey (XYZ = v · white).  CIELAB relative to the white integrated on the same grid, so the
perfect white is exactly L* = 100, a* = b* = 0.

Flop index (X-Rite's, after Alman 1987, "Directional color measurement of metallic flake
finishes"): FI = 2.69 (L*15 − L*110)^1.11 / L*45^0.86.  **Sign convention**: FI ≥ 0, and larger
means a stronger lightness travel from near-specular (15°) to the flop angle (110°); a solid colour
gives ≈ 0.  The formula is defined for L*15 ≥ L*110 only (a negative base has no
real non-integer power), and a flop index is by construction ≥ 0: a paint that is *darker* near the
specular than at 110° (a "reverse flop", e.g. a black paint whose coat reflection misses 15°) gets
the standard value 0.  ``flop_index`` is that standard value; ``flop_index_signed`` extends the formula
as sign(d)·2.69 |d|^1.11 / L*45^0.86, d = L*15 − L*110, so a reverse flop shows as negative, and
``flop_note`` says which case applies.  Both are None when L*45 = 0.

Directional albedo per incident angle: the solver's albedo at its nodes (quadrature, exact for
the table) including the mirror term's Fresnel reflectance F(θ_i; η), interpolated in μ_i by a
cubic spline; the mirror part is reported separately, exact at θ_i (the tabulated part is the
total minus it).
"""

from __future__ import annotations

import numpy as np

from flakedb.bsdf import catmull_rom_weights, insert_zero_nodes
from flakedb.bsdf.spline import cubic_spline_not_a_knot
from flakedb.colour.colorimetry import (
    XYZ_to_Lab,
    XYZ_to_linear_sRGB,
    reflectance_to_XYZ,
    rgb_mode_to_XYZ,
    spectral_grid,
    white_XYZ,
)
from flakedb.colour.geometry import as_geometry_array, key as geometry_key
from flakedb.colour.geometry import directions as geometry_directions
from flakedb.colour.settings import FLOP_GEOMETRIES, ColourSettings, resolve
from flakedb.colour.tolerance import lch, observer_name
from flakedb.colour.tolerance import reflectance_to_XYZ as reflectance_to_XYZ_under
from flakedb.colour.tolerance import white_XYZ as white_XYZ_under
from flakedb.optics.fresnel import fresnel_dielectric

#: Illumination zenith angle (degrees) of the multi-angle geometries.
ILLUMINATION_DEG = 45.0
#: Aspecular angles (degrees) of the multi-angle spectrophotometer (X-Rite MA-T6/MA98 set).
ASPECULAR_DEG = (-15.0, 15.0, 25.0, 45.0, 75.0, 110.0)
#: Incident angles (degrees) at which the directional albedo is reported.
ALBEDO_THETA_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 85.0)
#: Grid on which a mono channel's white is integrated (any grid with these end points gives the same).
MONO_WHITE_GRID = ((380.0, 780.0), 10.0)


def multiangle_geometry(aspecular_deg, illumination_deg=ILLUMINATION_DEG, azimuth_deg=0.0):
    """(mu_i, mu_o, phi_d, theta_view_deg) of an aspecular angle (module docstring); with ``azimuth_deg`` ≠ 0 an
    out-of-plane geometry (:func:`flakedb.colour.geometry.directions`, X-Rite's notation)."""
    if azimuth_deg:
        mu_i, mu_o, phi_d, tv = (float(x[0]) for x in geometry_directions([(illumination_deg, aspecular_deg,
                                                                             azimuth_deg)]))
        return mu_i, mu_o, phi_d, tv
    tv = float(illumination_deg) - float(aspecular_deg)
    mu_i = np.cos(np.radians(illumination_deg))
    mu_o = -np.cos(np.radians(abs(tv)))
    phi_d = 0.0 if tv >= 0 else np.pi
    return mu_i, mu_o, phi_d, tv


def eval_table(table, mu_i, mu_o, phi_d) -> np.ndarray:
    """f·|μ_o| (1/sr) of a :class:`flakedb.bsdf.BSDFTable` at (μ_i, μ_o, φ_d), float64, unclamped.

    The readers' Catmull–Rom interpolation over the file nodes (zero nodes inserted, entries at them
    zero).  Arguments broadcast; returns (..., C).
    """
    mu_i, mu_o, phi_d = np.broadcast_arrays(*(np.asarray(a, float) for a in (mu_i, mu_o, phi_d)))
    nodes = insert_zero_nodes(table.mu)
    n, h = table.n, table.n // 2
    quadrant = table.reflection_only  # then only rows h… and columns …h−1 hold coefficients
    src = table.stored
    C, L = src.shape[0], src.shape[3]
    N = n + 2
    # file index -> table index (the two zero nodes hold no coefficients)
    tidx = np.r_[0:h, -1, -1, h:n]
    oi, wi = catmull_rom_weights(nodes, mu_i)
    oo, wo = catmull_rom_weights(nodes, mu_o)
    out = np.zeros(mu_i.shape + (C, L))
    for a in range(4):
        for b in range(4):
            ti = tidx[np.clip(oi + a, 0, N - 1)]
            to = tidx[np.clip(oo + b, 0, N - 1)]
            if quadrant:
                live = (ti >= h) & (to >= 0) & (to < h)
                ri, ro = np.clip(ti - h, 0, h - 1), np.clip(to, 0, h - 1)
            else:
                live = (ti >= 0) & (to >= 0)
                ri, ro = np.maximum(ti, 0), np.maximum(to, 0)
            w = wi[..., a] * wo[..., b] * live
            block = np.moveaxis(src[:, ri, ro, :], 0, -2)
            out += w[..., None, None] * block
    cos = np.cos(np.arange(L) * phi_d[..., None])  # (..., L)
    return np.einsum("...cl,...l->...c", out, cos)


def channels_to_XYZ(values, mode, wavelength_nm=None, settings: ColourSettings | None = None) -> np.ndarray:
    """XYZ (Y = 1 for white) of reflectance-type values (..., C) in a paint's channels.

    ``settings``: the observer and illuminant of a spectral paint (None: D65 / 2°, the package's
    RGB-mode conditions, which is what the RGB and mono channels are defined under anyway)."""
    v = np.asarray(values, float)
    if v.shape[-1] == 1 and mode in ("spectral", "rgb") and wavelength_nm is not None:
        # a wavelength-independent table (e.g. an index-matched coat alone): the same value everywhere
        v = np.broadcast_to(v, v.shape[:-1] + ((len(wavelength_nm),) if mode == "spectral" else (3,)))
    if mode == "spectral":
        if settings is not None:
            return reflectance_to_XYZ_under(v, wavelength_nm, settings.observer, settings.illuminant)
        return reflectance_to_XYZ(v, wavelength_nm)
    if mode == "rgb":
        return rgb_mode_to_XYZ(v, wavelength_nm)
    if mode == "mono":
        w = white_XYZ(spectral_grid(*MONO_WHITE_GRID))
        return v[..., :1] * w
    raise ValueError(f"unknown mode {mode!r}")


def reference_white(mode, wavelength_nm=None, settings: ColourSettings | None = None) -> np.ndarray:
    """XYZ of the perfect white in the same integration as :func:`channels_to_XYZ`."""
    if mode == "mono":
        return white_XYZ(spectral_grid(*MONO_WHITE_GRID))
    if mode == "spectral" and settings is not None:
        return white_XYZ_under(wavelength_nm, settings.observer, settings.illuminant)
    return white_XYZ(wavelength_nm)


def flop_index(L15, L45, L110):
    """Signed X-Rite flop index sign(d) 2.69 |d|^1.11 / L*45^0.86, d = L*15 − L*110 (None when
    L*45 = 0); the standard value is :func:`flop_index_standard` (module docstring).

    A flat grey (the same L* at every angle) has no flop; a metallic that darkens from the near-specular
    15° to the far 110° has a positive one, and the instruments' value clips a reverse flop to 0:

    >>> flop_index(50.0, 50.0, 50.0), round(flop_index(100.0, 60.0, 20.0), 4)
    (0.0, 10.3032)
    >>> round(flop_index(20.0, 40.0, 30.0), 4), flop_index_standard(20.0, 40.0, 30.0)
    (-1.452, 0.0)
    """
    if not L45 > 0:
        return None
    d = float(L15) - float(L110)
    return float(2.69 * np.sign(d) * abs(d) ** 1.11 / float(L45) ** 0.86)


def flop_index_standard(L15, L45, L110):
    """The X-Rite flop index as instruments report it: 2.69 (L*15 − L*110)^1.11 / L*45^0.86 for
    L*15 ≥ L*110, 0 for a reverse flop (L*15 < L*110), None when L*45 = 0 (module docstring)."""
    fi = flop_index(L15, L45, L110)
    return None if fi is None else max(fi, 0.0)


def directional_albedo(x_nodes, albedo_nodes, theta_deg, delta_eta=None):
    """Albedo (A, C) at incident angles ``theta_deg`` from the tabulated albedo (C, h) at the solver's
    nodes ``x_nodes`` (h,) and, when ``delta_eta``, the mirror term F(θ; η): the nodal total
    (tabulated + F) by a cubic spline in μ; the mirror part exact at θ.

    Returns ``(total, tabulated, mirror)`` with mirror (A,).
    """
    mu = np.cos(np.radians(np.asarray(theta_deg, float)))
    x = np.asarray(x_nodes, float)
    a = np.asarray(albedo_nodes, float)
    if delta_eta is None:
        mirror, mirror_nodes = np.zeros(mu.shape), np.zeros(x.shape)
    else:
        mirror = fresnel_dielectric(mu, float(delta_eta)).R
        mirror_nodes = fresnel_dielectric(x, float(delta_eta)).R
    # the total (tabulated + mirror) is the smoother function of μ (constant for a white furnace):
    # interpolate it, and give the tabulated part as the total minus the exact mirror term
    total = cubic_spline_not_a_knot(x, (a + mirror_nodes[None, :]).T, np.clip(mu, x[0], x[-1]))  # (A, C)
    return total, total - mirror[:, None], mirror


def texture_ground(table, mode, wavelength_nm, x_nodes, albedo_nodes, delta_eta=None):
    """The smooth BSDF's luminance factors for the texture indices (docs/texture.md §3.4, §4): a callable
    ``observer -> {"directional": {light_deg: Y of π f(l, v)}, "diffuse": Y of the directional albedo at
    the view (mirror term included)}``, for :func:`flakedb.paint.texture_inputs.texture_report`."""
    white = reference_white(mode, wavelength_nm)

    def ground(obs):
        mu_o = -np.cos(np.radians(obs.view_deg))
        rf = {float(a): np.pi * eval_table(table, np.cos(np.radians(a)), mu_o, 0.0) / abs(mu_o) for a in obs.light_deg}
        tot = directional_albedo(x_nodes, albedo_nodes, [obs.view_deg], delta_eta)[0]
        return {"directional": {a: float(channels_to_XYZ(v, mode, wavelength_nm)[1] / white[1]) for a, v in rf.items()},
                "diffuse": float(channels_to_XYZ(tot, mode, wavelength_nm)[0, 1] / white[1])}
    return ground


def colour_report(table, mode, wavelength_nm, x_nodes, albedo_nodes, delta_eta=None, name="",
                  settings: ColourSettings | None = None):
    """The colour report (a JSON-able dict) of a paint's full-precision ``table`` (channels of ``mode``).

    ``x_nodes``/``albedo_nodes``: the solver's positive nodes (h,) and tabulated albedo (C, h) at them.
    ``settings``: observer, illuminant and geometry set (None: :func:`flakedb.colour.settings.resolve`'s
    defaults for ``mode``); a spectral paint is reported under them, an RGB one under D65 / 2°.
    """
    if settings is None:
        settings = resolve(mode=mode)
    elif mode == "rgb":  # an RGB paint has one set of conditions: refuse others, keep the geometry set
        settings = resolve(settings.observer, settings.illuminant, settings.geometry_set, mode)
    white = reference_white(mode, wavelength_nm, settings)
    rows = []
    for th_i, g, az in as_geometry_array(settings.geometries):
        mu_i, mu_o, phi_d, tv = multiangle_geometry(g, th_i, az)
        f_cos = eval_table(table, mu_i, mu_o, phi_d)  # (C,)
        rf = np.pi * f_cos / abs(mu_o)
        XYZ = channels_to_XYZ(rf, mode, wavelength_nm, settings)
        lab = XYZ_to_Lab(XYZ, white=white)
        rgb = XYZ_to_linear_sRGB(XYZ)
        rows.append({
            "illumination_deg": float(th_i), "aspecular_deg": float(g), "azimuth_deg": float(az),
            "theta_view_deg": abs(float(tv)),
            "side": ("out of plane" if az else "specular" if tv > 0 else ("normal" if tv == 0 else "illuminator")),
            "mu_i": float(mu_i), "mu_o": float(mu_o), "phi_d": float(phi_d),
            "L": float(lab[0]), "a": float(lab[1]), "b": float(lab[2]),
            "C": float(lch(lab)[1]), "h_deg": float(lch(lab)[2]),
            "XYZ": [float(v) for v in XYZ], "linear_sRGB": [float(v) for v in rgb],
            "reflectance_factor": [float(v) for v in rf],
        })
    Ls = {geometry_key((r["illumination_deg"], r["aspecular_deg"], r["azimuth_deg"])): r["L"] for r in rows}
    L15, L45, L110 = (Ls[geometry_key(g)] for g in FLOP_GEOMETRIES)
    fi = flop_index(L15, L45, L110)
    fi_std = flop_index_standard(L15, L45, L110)
    if fi is None:
        note = "undefined: L*45 = 0"
    elif fi < 0:
        note = (f"reverse flop: L*15 ({L15:.2f}) < L*110 ({L110:.2f}); the X-Rite formula is defined for "
                f"L*15 >= L*110, so the standard value is 0 (signed extension {fi:.2f})")
    else:
        note = "L*15 >= L*110: the standard X-Rite value (>= 0; larger = stronger lightness flop)"
    tot, tab, mirror = directional_albedo(x_nodes, albedo_nodes, ALBEDO_THETA_DEG, delta_eta)
    Y_tot = channels_to_XYZ(tot, mode, wavelength_nm, settings)[:, 1] / white[1]
    Y_tab = channels_to_XYZ(tab, mode, wavelength_nm, settings)[:, 1] / white[1]
    albedo = [{"theta_i_deg": t, "albedo_Y": float(yt), "tabulated_Y": float(yb), "mirror": float(m),
               "albedo_channels": [float(v) for v in tt]}
              for t, yt, yb, m, tt in zip(ALBEDO_THETA_DEG, Y_tot, Y_tab, mirror, tot)]
    rep = {
        "name": name,
        "mode": mode,
        "colour": (f"CIELAB (CIE 1976), illuminant {settings.illuminant}, {observer_name(settings.observer)}; "
                   f"white = perfect diffuser"),
        "observer": settings.observer,
        "illuminant": settings.illuminant,
        "geometry_set": settings.geometry_set,
        "illumination_deg": ILLUMINATION_DEG,
        "reflectance_factor": "pi * f(omega_i, omega_o), tabulated part (no aspecular angle hits the mirror delta)",
        "geometries": rows,
        "flop_index": fi_std,
        "flop_index_signed": fi,
        "flop_note": note,
        "flop_index_formula": ("X-Rite: 2.69 (L*15 - L*110)^1.11 / L*45^0.86, >= 0; defined for L*15 >= L*110 "
                               "(0 for a reverse flop; flop_index_signed keeps the sign of L*15 - L*110); "
                               "45 deg illumination"),
        "albedo": albedo,
        "albedo_note": (f"directional albedo (reflected flux / incident flux) from above; albedo_Y is its luminance "
                        f"(Y, {settings.label}) including the mirror term 'mirror' = F(theta_i) of a smooth coat"),
        "wavelength_nm": None if wavelength_nm is None else [float(w) for w in wavelength_nm],
    }
    if settings.note:
        rep["colour_note"] = settings.note
    return rep


def format_formulation(layers) -> list:
    """Lines of the report's ``formulation`` (per basecoat: each particle's volume and weight fraction,
    the PVC and the CPVC estimate; docs/formulation.md)."""
    lines = []
    for f in layers:
        cpvc = (f"CPVC estimate {f['cpvc_estimate']:.3f}" if f.get("cpvc_estimate") is not None
                else f"CPVC {f.get('cpvc_basis') or 'not estimated'}")
        rho = f.get("film_density_g_cm3")
        lines.append(f"formulation {f['layer']}: PVC {f['pvc']:.4f}; {cpvc}"
                     + (f"; dry film {rho:.3f} g/cm³ (binder {f['binder_density_g_cm3']:g})" if rho is not None else ""))
        for p in f["particles"]:
            wf = "-" if p["weight_fraction"] is None else f"{p['weight_fraction']:.4f}"
            lines.append(f"  {p['species']:<24} volume {p['volume_fraction']:.4f}  weight {wf}"
                         + ("" if p["density_g_cm3"] is None else f"  ({p['density_g_cm3']:g} g/cm³)")
                         + f"  given by {p['given'].split('_')[0]}")
    return lines


def format_report(rep) -> str:
    """The colour report as the text table ``flakedb compose`` prints."""
    cond = f"{rep.get('illuminant', 'D65')}/{rep.get('observer', '2')}°"
    asps = [(f"{r['aspecular_deg']:g}°az{r['azimuth_deg']:g}°" if r.get("azimuth_deg") else f"{r['aspecular_deg']:g}°")
            for r in rep["geometries"]]
    wa = max([10] + [len(a) for a in asps])   # out-of-plane names are longer
    lines = [f"colour report: {rep['name']} ({rep['mode']} mode; CIELAB {cond}, geometries "
             f"{rep.get('geometry_set', 'e2194').upper()})",
             f"{'illum':>6} {'aspecular':>{wa}} {'view':>12} {'L*':>8} {'a*':>8} {'b*':>8} {'C*':>8} {'h°':>6}"]
    if rep.get("colour_note"):
        lines.insert(1, f"note: {rep['colour_note']}")
    for r, asp in zip(rep["geometries"], asps):
        view = f"{r['theta_view_deg']:.4g}° {'out' if r.get('azimuth_deg') else r['side'][:5]}"
        lines.append(f"{r.get('illumination_deg', ILLUMINATION_DEG):>5g}° {asp:>{wa}} {view:>12} "
                     f"{r['L']:8.2f} {r['a']:8.2f} {r['b']:8.2f}"
                     + (f" {r['C']:8.2f} {r['h_deg']:6.1f}" if "C" in r else ""))
    lines += format_formulation(rep.get("formulation") or [])
    fi = rep["flop_index"]
    if fi is None:
        lines.append("flop index (X-Rite): undefined (L*45 = 0)")
    elif (rep.get("flop_index_signed") or 0.0) < 0:
        lines.append(f"flop index (X-Rite): 0 (reverse flop: L*15 < L*110, darker near the specular; "
                     f"signed extension {rep['flop_index_signed']:.2f})")
    else:
        lines.append(f"flop index (X-Rite): {fi:.2f} (>= 0; larger = stronger lightness flop, 15° vs 110°)")
    g = rep.get("rgb_file")
    if g:
        lines.append(f"RGB file: {g['rgb_space']}; {g['pairs_mapped']} of {g['pairs_reflection']} reflection node "
                     f"pairs desaturated into gamut (luminance kept), largest ΔE00 {g['max_dE00']:.2f}; "
                     f"the .h5 keeps the exact colour")
    d = rep.get("discretisation")
    if d and "estimate_dE00" in d:
        conv = d.get("estimate_dE00_converged")
        lines.append(f"discretisation: estimated ΔE00(n, 2n) {d['estimate_dE00']:.3f} at n = {d['n']}"
                     + (f", at most {conv:.3f} against the converged answer (error order ≥ {d.get('order_assumed', 1.5):g} "
                        "assumed)" if conv is not None else "")
                     + f" (second solve at n = {d['n_second']}: largest ΔE00 {max(d['dE00_second_vs_n']):.3f}, "
                     f"times {d['factor']:.2f})")
    lines.append(f"{'theta_i':>8} {'albedo Y':>9} {'tabulated':>10} {'mirror':>8}")
    for a in rep["albedo"]:
        lines.append(f"{a['theta_i_deg']:>7g}° {a['albedo_Y']:9.4f} {a['tabulated_Y']:10.4f} {a['mirror']:8.4f}")
    return "\n".join(lines)
