"""The ``flakedb`` BSDF plugin for Mitsuba 3: flakedb's reader inside the renderer, with the smooth
coat's mirror term as a delta lobe.

* ``eval`` = the table's f·|mu_o| (every channel clamped to >= 0, as pbrt-v3 does); ``pdf`` = the
  reader's ``pdf`` times the probability of choosing the tabulated lobe;
* ``sample``: with the mirror term present (``delta = {"kind": "fresnel", "eta": η}``), the delta
  lobe is chosen with probability ``F / (F + A(mu_i))`` (F the Fresnel reflectance at the coat,
  A the tabulated albedo of the sampling channel, 2π·cdf(mu_i)[N-1]), flagged ``DeltaReflection``
  (component 0); the tabulated lobe is ``GlossyReflection`` (component 1, or 0 without delta).
* the work is done by compiled kernels (numba) built around the reader's own compiled evaluation
  and sampling kernels of :mod:`flakedb.bsdf` (the reader's arrays from
  :meth:`flakedb.bsdf.FourierBSDF.kernel_arrays`): one compiled call per Mitsuba call.  Scalar
  variants make one Python call per sample (~0.1-0.2 ms a camera sample: keep scalar renders
  small); JIT variants (``llvm_ad_rgb``) call once per wavefront: render inside
  :func:`evaluated_mode` (symbolic loops and calls off), because the plugin needs evaluated arrays.
* colours: in RGB variants an RGB or mono file as is, a spectral HDF5 file converted to
  white-normalised linear sRGB (CIE 1931 / D65, as ``flakedb compose`` makes its ``.bsdf``); in
  spectral variants a mono file, or a spectral HDF5 file linear in wavelength between its channels
  (clamped beyond them).  Every channel is clamped to >= 0.

Mitsuba is imported inside :func:`register`, so this module imports without it.
"""

from __future__ import annotations

import contextlib
import math
import os

import numba
import numpy as np

from flakedb.bsdf import open_bsdf
from flakedb.bsdf.kernels import compiled as compiled_kernels
from flakedb.render.mitsuba.directions import (MeasuredExportError, channel_wavelengths, delta_reflectance,
                                               rgb_matrix)

# the reader's compiled kernels, by name: this module's own compiled kernels call them
cr_weights_1 = compiled_kernels().cr_weights_1
sample_kernel = compiled_kernels().sample_kernel
series_kernel = compiled_kernels().series_kernel

#: Where Debian's libllvm19 puts the library the ``llvm_ad_*`` variants need (renderers.md).
LLVM_LIBRARY_DEFAULT = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"


def llvm_library() -> str | None:
    """The libLLVM the ``llvm_ad_*`` variants should use: ``$DRJIT_LIBLLVM_PATH`` when it names an
    existing file, else Debian's libLLVM 19 (:data:`LLVM_LIBRARY_DEFAULT`) when present, else None.
    (Older libLLVMs on this image make Dr.Jit abort the process, renderers.md.)"""
    p = os.environ.get("DRJIT_LIBLLVM_PATH")
    if p and os.path.isfile(p):
        return p
    return LLVM_LIBRARY_DEFAULT if os.path.isfile(LLVM_LIBRARY_DEFAULT) else None


@contextlib.contextmanager
def evaluated_mode():
    """Turn Dr.Jit's symbolic loops and calls off (restored on exit) so that the ``flakedb`` plugin
    receives evaluated arrays in JIT variants (it calls numpy).  Not needed in scalar variants."""
    import drjit as dr  # lazy: optional renderer (test extra), large import

    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    old = [dr.flag(f) for f in flags]
    try:
        for f in flags:
            dr.set_flag(f, False)
        yield
    finally:
        for f, v in zip(flags, old):
            dr.set_flag(f, v)


def fresnel_unpolarised(c, eta):
    """Unpolarised Fresnel reflectance of light arriving from above (relative index eta = n_below /
    n_above > 0) at cosine ``c`` in (0, 1] (Born & Wolf §1.5.2; equals
    ``flakedb.optics.fresnel.fresnel_dielectric(c, eta).R``, checked by the tests).

    >>> round(fresnel_unpolarised(1.0, 1.5), 12), fresnel_unpolarised(0.3, 1.0), fresnel_unpolarised(0.3, 1 / 1.5)
    (0.040000000000, 0.0, 1.0)
    """
    if eta == 1.0:
        return 0.0
    ct2 = 1.0 - (1.0 - c * c) / (eta * eta)
    if ct2 <= 0.0:
        return 1.0
    ct = math.sqrt(ct2)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs * rs + rp * rp)


# The plugin's compiled kernels (numba) around the reader's own compiled evaluation
# (``series_kernel``), sampling (``sample_kernel``) and Catmull-Rom weights: a scalar Mitsuba call
# costs one compiled call instead of dozens of small numpy operations.
_fresnel_1 = numba.njit(cache=True, nogil=True)(fresnel_unpolarised)


@numba.njit(cache=True, nogil=True)
def _choice_1(nodes, cdf, mu_i, delta_eta, delta_on, glossy_on, w):
    """(F, p_delta) at mu_i > 0: the mirror term's reflectance and its sampling probability."""
    F = _fresnel_1(min(mu_i, 1.0), delta_eta) if (delta_eta > 0.0 and delta_on) else 0.0
    if not glossy_on:
        return F, 1.0 if F > 0.0 else 0.0
    n = nodes.size
    off = cr_weights_1(nodes, mu_i, w)
    A = 0.0
    if off != -n:
        for a in range(4):
            if w[a] != 0.0:
                A += w[a] * cdf[off + a, n - 1]
    A = max(2.0 * np.pi * A, 0.0)
    return F, (F / (F + A) if F + A > 0.0 else 0.0)


@numba.njit(cache=True, nogil=True)
def _coordinates_kernel(wi, wo, mu_i, mu_o, phi):
    """file_coordinates (module function) per point; NaN where not front-side reflection."""
    for p in range(wi.shape[0]):
        si = math.sqrt(wi[p, 0] * wi[p, 0] + wi[p, 1] * wi[p, 1])
        so = math.sqrt(wo[p, 0] * wo[p, 0] + wo[p, 1] * wo[p, 1])
        c = 1.0
        if si * so > 0.0:
            c = min(1.0, max(-1.0, (wi[p, 0] * wo[p, 0] + wi[p, 1] * wo[p, 1]) / (si * so)))
        ok = wi[p, 2] > 0.0 and wo[p, 2] > 0.0
        mu_i[p] = wi[p, 2] if ok else np.nan
        mu_o[p] = -wo[p, 2] if ok else np.nan
        phi[p] = np.pi - math.acos(c)


@numba.njit(cache=True, nogil=True)
def _eval_pdf_kernel(nodes, cdf, flat, start, order, cs, mix, sflat, sstart, wi, wo, delta_eta,
                     delta_on, glossy_on, out_val, out_pdf):
    """out_val (P, Cout) = max(0, f·|mu_o|) per channel (FourierBSDF.eval, clamp="all"),
    out_pdf (P,) = (1 - p_delta) · FourierBSDF.pdf; 0 outside front-side reflection."""
    P = wi.shape[0]
    n = nodes.size
    mu_i = np.empty(P)
    mu_o = np.empty(P)
    phi = np.empty(P)
    _coordinates_kernel(wi, wo, mu_i, mu_o, phi)
    if not glossy_on:
        mu_i[:] = np.nan
    vals = np.zeros((P, cs))
    a0 = np.zeros((P, cs))
    fs = np.zeros((P, 1))
    a0s = np.zeros((P, 1))
    series_kernel(nodes, flat, start, order, cs, mu_i, mu_o, phi, vals, a0)
    series_kernel(nodes, sflat, sstart, order, 1, mu_i, mu_o, phi, fs, a0s)
    w = np.zeros(4)
    for p in range(P):
        for j in range(mix.shape[1]):
            s = 0.0
            for c in range(cs):
                s += vals[p, c] * mix[c, j]
            out_val[p, j] = max(s, 0.0)
        out_pdf[p] = 0.0
        if not (mu_i[p] > 0.0) or a0s[p, 0] == 0.0:
            continue
        off = cr_weights_1(nodes, mu_i[p], w)
        norm = 0.0
        for a in range(4):
            if w[a] != 0.0:
                norm += w[a] * cdf[off + a, n - 1]
        if norm > 0.0:
            F, pd = _choice_1(nodes, cdf, mu_i[p], delta_eta, delta_on, True, w)
            out_pdf[p] = (1.0 - pd) * max(fs[p, 0], 0.0) / (2.0 * np.pi * norm)


@numba.njit(cache=True, nogil=True)
def _plugin_sample_kernel(nodes, cdf, a0s_nodes, sflat, sstart, flat, start, order, cs, mix, wi, s1, s2,
                          delta_eta, delta_on, glossy_on, out_wo, out_w, out_pdf, out_delta):
    """Choose the delta lobe with probability F / (F + A), else FourierBSDF.sample; out_w is
    the weight (value / pdf, >= 0), out_pdf the density (or the discrete probability of the
    delta lobe), out_delta 1 where the delta lobe was chosen.  0 where nothing is sampled."""
    P = wi.shape[0]
    mu_i = np.full(P, np.nan)
    pds = np.zeros(P)
    w = np.zeros(4)
    for p in range(P):
        out_delta[p] = 0
        out_pdf[p] = 0.0
        for j in range(out_w.shape[1]):
            out_w[p, j] = 0.0
        if not wi[p, 2] > 0.0:
            continue
        F, pd = _choice_1(nodes, cdf, wi[p, 2], delta_eta, delta_on, glossy_on, w)
        if s1[p] < pd:
            out_delta[p] = 1
            out_wo[p, 0] = -wi[p, 0]
            out_wo[p, 1] = -wi[p, 1]
            out_wo[p, 2] = wi[p, 2]
            out_pdf[p] = pd
            for j in range(out_w.shape[1]):
                out_w[p, j] = F / pd
        elif glossy_on and pd < 1.0:
            mu_i[p] = wi[p, 2]
            pds[p] = pd
    mu_o = np.zeros(P)
    phi = np.zeros(P)
    wt = np.zeros((P, mix.shape[1]))
    pdf = np.zeros(P)
    u1 = np.ascontiguousarray(s2[:, 0])
    u2 = np.ascontiguousarray(s2[:, 1])
    sample_kernel(nodes, cdf, a0s_nodes, sflat, sstart, flat, start, order, cs, mix, mu_i,
                   u1, u2, mu_o, phi, wt, pdf)
    for p in range(P):
        if not (mu_i[p] > 0.0):
            continue
        s = math.sqrt(max(0.0, 1.0 - mu_o[p] * mu_o[p]))
        ph = math.atan2(wi[p, 1], wi[p, 0]) + np.pi - phi[p]
        out_wo[p, 0] = s * math.cos(ph)
        out_wo[p, 1] = s * math.sin(ph)
        out_wo[p, 2] = -mu_o[p]
        if pdf[p] > 0.0 and mu_o[p] < 0.0:
            out_pdf[p] = (1.0 - pds[p]) * pdf[p]
            for j in range(out_w.shape[1]):
                out_w[p, j] = max(wt[p, j], 0.0) / (1.0 - pds[p])


class PluginCore:
    """The plugin's numpy side, independent of Mitsuba: methods take (P, 3) direction arrays.

    Evaluation and sampling run in the compiled kernels above, around the reader's own; the
    reader's arrays are taken from the :class:`flakedb.bsdf.FourierBSDF` here, in one place.
    """

    def __init__(self, path, variant: str, use_delta: bool = True):
        self.b = b = open_bsdf(path)
        self.delta = b.delta if use_delta else None
        delta_reflectance(self.delta, 1.0)                      # refuse unknown kinds early
        self.delta_eta = float(self.delta["eta"]) if self.delta is not None else 0.0
        self.spectral = "spectral" in variant
        wl = channel_wavelengths(b)
        chans = tuple(b.channels)
        if self.spectral:
            if wl is not None:
                order = np.argsort(wl)
                self.wavelengths, self.mix = wl[order], np.eye(b.n_channels)[:, order]
            elif len(chans) == 1 or (b.kind == "bsdf" and b.n_channels == 1):
                self.wavelengths, self.mix = None, np.eye(len(chans))[:, :1]
            else:
                raise ValueError(f"{path}: the {variant} variant renders mono or spectral files; this file "
                                 f"holds {', '.join(chans)}. Use an RGB variant (scalar_rgb, llvm_ad_rgb).")
        else:
            self.wavelengths = None
            try:                                   # R, G, B; mono; spectral -> linear sRGB (D65)
                self.mix = rgb_matrix(b)
            except MeasuredExportError as e:
                raise ValueError(f"{e}. In {variant}, the plugin renders R, G, B, mono, or spectral files "
                                 f"on a 1-20 nm grid (converted to linear sRGB)") from None
        # the reader's arrays, through its public accessor
        k = b.kernel_arrays()
        self._eval_args = (k.nodes, k.cdf, k.flat, k.start, k.order, k.n_channels, k.mix, k.sample_flat,
                           k.sample_start)
        self._sample_args = (k.nodes, k.cdf, k.sample_a0, k.sample_flat, k.sample_start, k.flat, k.start,
                             k.order, k.n_channels, k.mix)
        self._cout = k.mix.shape[1]

    def _colour(self, vals, wavelengths):
        """(P, Cout) reader channels -> (P, 3) RGB, or (P, n_λ) at ``wavelengths`` (P, n_λ) [nm];
        clamped to >= 0 after the mix (a spectral -> sRGB map has negative entries)."""
        out = np.maximum(vals @ self.mix, 0.0)
        if wavelengths is None:
            return out
        if self.wavelengths is None:
            return np.repeat(out[:, :1], wavelengths.shape[1], axis=1)
        wl = self.wavelengths
        x = np.clip(wavelengths, wl[0], wl[-1])
        j = np.clip(np.searchsorted(wl, x, side="right") - 1, 0, wl.size - 2)
        t = (x - wl[j]) / (wl[j + 1] - wl[j])
        rows = np.arange(out.shape[0])[:, None]
        return (1 - t) * out[rows, j] + t * out[rows, j + 1]

    def eval_pdf(self, wi, wo, wavelengths=None, delta_on=True, glossy_on=True):
        """(f·cos θ_o (P, C), pdf (P,)) of the tabulated lobe, 0 outside front-side reflection."""
        wi = np.ascontiguousarray(wi, dtype=np.float64).reshape(-1, 3)
        wo = np.ascontiguousarray(wo, dtype=np.float64).reshape(-1, 3)
        vals = np.empty((wi.shape[0], self._cout))
        pdf = np.empty(wi.shape[0])
        _eval_pdf_kernel(*self._eval_args, wi, wo, self.delta_eta, bool(delta_on), bool(glossy_on), vals, pdf)
        return self._colour(vals, wavelengths), pdf

    def sample(self, wi, s1, s2, wavelengths=None, delta_on=True, glossy_on=True):
        """Sample wo: returns (wo (P, 3), weight (P, C), pdf (P,), is_delta (P,) bool, ok (P,) bool)."""
        wi = np.ascontiguousarray(wi, dtype=np.float64).reshape(-1, 3)
        P = wi.shape[0]
        wo = np.zeros((P, 3))
        weight = np.empty((P, self._cout))
        pdf = np.empty(P)
        is_delta = np.empty(P, dtype=np.uint8)
        s1 = np.ascontiguousarray(s1, dtype=np.float64).reshape(-1)
        s2 = np.ascontiguousarray(s2, dtype=np.float64).reshape(-1, 2)
        _plugin_sample_kernel(*self._sample_args, wi, s1, s2, self.delta_eta, bool(delta_on), bool(glossy_on),
                              wo, weight, pdf, is_delta)
        ok = (pdf > 0) & (wo[:, 2] > 0)
        weight[~ok] = 0.0
        return wo, self._colour(weight, wavelengths), pdf, is_delta.astype(bool), ok


def register(name: str = "flakedb"):
    """Register the ``flakedb`` BSDF plugin with Mitsuba 3 for the **current** variant (call after
    ``mi.set_variant``) and return its class.  Scene usage::

        {"type": "flakedb", "filename": "paint.bsdf"}          # optional: "delta": False

    Properties: ``filename`` (a ``.bsdf`` or flakedb ``.h5``), ``delta`` (bool, default True: add
    the file's smooth-coat mirror term back as a delta lobe).  See the module docstring.
    """
    import drjit as dr  # lazy: optional renderer (test extra), large import
    import mitsuba as mi  # lazy: optional renderer (test extra), large import

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("call mi.set_variant(...) before flakedb.render.mitsuba.register()")
    jit = dr.is_jit_v(mi.Float)
    Flags = mi.BSDFFlags
    i_types = (int(Flags.GlossyReflection), int(Flags.DeltaReflection))

    # Conversions between Mitsuba values and numpy arrays of P points: one point in scalar
    # variants (kept cheap: each costs a few µs per call), a wavefront in JIT variants.
    if jit:
        def vec(v, n=None):
            cols = [np.asarray(c, dtype=np.float64).reshape(-1) for c in (v.x, v.y, v.z)]
            n = max([c.size for c in cols] + [n or 1])
            return np.stack([np.broadcast_to(c, (n,)) for c in cols], axis=-1)

        def arr(x, n, dtype=np.float64):
            return np.broadcast_to(np.asarray(x, dtype=dtype).reshape(-1), (n,)).copy()

        def out_spec(vals):
            return mi.Spectrum(*[mi.Float(np.ascontiguousarray(vals[:, k], dtype=np.float32))
                                 for k in range(vals.shape[1])])

        def out_float(x):
            return mi.Float(np.ascontiguousarray(x, dtype=np.float32))

        def out_vec(w):
            return mi.Vector3f(*[mi.Float(np.ascontiguousarray(w[:, k], dtype=np.float32)) for k in range(3)])
    else:
        def vec(v, n=None):
            return np.array([[v.x, v.y, v.z]])

        def arr(x, n, dtype=np.float64):
            return np.array([x], dtype=dtype)

        def out_spec(vals):
            return mi.Spectrum(*vals[0].tolist())

        def out_float(x):
            return float(x[0])

        def out_vec(w):
            return mi.Vector3f(*w[0].tolist())

    class FlakedbBSDF(mi.BSDF):
        """flakedb's Fourier BSDF file, evaluated and sampled by flakedb's reader."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            fname = props["filename"]
            path = str(mi.file_resolver().resolve(str(fname)))
            use_delta = bool(props["delta"]) if "delta" in props else True
            self.core = PluginCore(path, variant, use_delta)
            self.path = path
            glossy = Flags.GlossyReflection | Flags.FrontSide
            comps = []
            if self.core.delta is not None:
                comps.append(Flags.DeltaReflection | Flags.FrontSide)
            comps.append(glossy)
            self.i_delta = 0 if self.core.delta is not None else None
            self.i_glossy = len(comps) - 1
            self.m_components = comps
            flags = comps[0]
            for c in comps[1:]:
                flags = flags | c
            self.m_flags = flags

        # -- helpers ------------------------------------------------------------------------------
        def _enabled(self, ctx):
            d = self.i_delta is not None and ctx.is_enabled(Flags.DeltaReflection, self.i_delta)
            g = ctx.is_enabled(Flags.GlossyReflection, self.i_glossy)
            return bool(d), bool(g)

        def _check_mode(self):
            if jit and dr.flag(dr.JitFlag.SymbolicScope):
                raise RuntimeError(
                    "the flakedb BSDF plugin calls numpy, which cannot run while Dr.Jit records a "
                    f"symbolic kernel: in {variant}, render inside `with flakedb.render.mitsuba.evaluated_mode():`")

        def _wavelengths(self, si, n):
            if not self.core.spectral:
                return None
            w = si.wavelengths
            return np.stack([arr(w[k], n) for k in range(len(w))], axis=-1)

        # -- the BSDF interface -------------------------------------------------------------------
        def eval_pdf(self, ctx, si, wo, active=True):
            self._check_mode()
            d, g = self._enabled(ctx)
            wo_ = vec(wo)
            wi_ = vec(si.wi, wo_.shape[0])
            if wo_.shape[0] != wi_.shape[0]:
                wo_ = vec(wo, wi_.shape[0])
            n = wi_.shape[0]
            vals, pdf = self.core.eval_pdf(wi_, wo_, self._wavelengths(si, n), d, g)
            if active is not True:
                off = ~arr(active, n, bool)
                vals[off] = 0.0
                pdf[off] = 0.0
            return out_spec(vals), out_float(pdf)

        def eval(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[0]

        def pdf(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[1]

        def sample(self, ctx, si, sample1, sample2, active=True):
            self._check_mode()
            d, g = self._enabled(ctx)
            n = max(vec(si.wi).shape[0], np.size(np.asarray(sample1)) if jit else 1)
            wi = vec(si.wi, n)
            s2 = np.stack([arr(sample2.x, n), arr(sample2.y, n)], axis=-1)
            wo, weight, pdf, is_delta, ok = self.core.sample(wi, arr(sample1, n), s2, self._wavelengths(si, n), d, g)
            if active is not True:
                ok &= arr(active, n, bool)
            weight[~ok] = 0.0
            pdf[~ok] = 0.0
            if jit:
                bs = dr.zeros(mi.BSDFSample3f, n)
                bs.sampled_type = mi.UInt32(np.where(is_delta, i_types[1], i_types[0]).astype(np.uint32))
                bs.sampled_component = mi.UInt32(np.where(is_delta, self.i_delta or 0,
                                                          self.i_glossy).astype(np.uint32))
            else:
                bs = mi.BSDFSample3f()
                bs.sampled_type = i_types[1] if is_delta[0] else i_types[0]
                bs.sampled_component = (self.i_delta or 0) if is_delta[0] else self.i_glossy
            bs.wo = out_vec(wo)
            bs.pdf = out_float(pdf)
            bs.eta = 1.0
            return bs, out_spec(weight)

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"FlakedbBSDF[filename={self.path!r}, delta={self.core.delta}]"

    mi.register_bsdf(name, lambda props: FlakedbBSDF(props))
    return FlakedbBSDF


