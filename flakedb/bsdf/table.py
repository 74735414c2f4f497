"""The solver's hand-over to the file side: :class:`BSDFTable` (docs/bsdf-format.md), the file
constants shared by the codecs, and :class:`BSDFFileError`."""

from __future__ import annotations

import math

import numpy as np

from flakedb.bsdf.metadata import check_delta
from flakedb.bsdf.spline import catmull_rom_cdf, insert_zero_nodes
from flakedb.optics.fresnel import fresnel_dielectric

#: The spec's (layerlab's) truncation rule: keep orders until the tail sum is <= this times |a_0|.
TRUNCATION_DEFAULT = 2e-3

#: Y from linear R, G, B (spec, "colour") and the readers' G from Y, R, B.
RGB_TO_Y = (0.212671, 0.715160, 0.072169)
G_FROM_YRB = (1.39829, -0.297375, -0.100913)  # coefficients of Y, R, B

class BSDFFileError(ValueError):
    """A BSDF file that cannot be read: missing, truncated, corrupt or unsupported."""

# --------------------------------------------------------------------------------------------
# The solver's table
# --------------------------------------------------------------------------------------------
class BSDFTable:
    """A tabulated azimuthally-isotropic BSDF as the solver produces it.

    Attributes
    ----------
    mu : float64 (n,)
        Quadrature nodes (cosines, conventions), ascending, ``[-x_h … -x_1, x_1 … x_h]`` with
        ``0 < x_1 < … < x_h <= 1``, n = 2h even, no node at 0.
    coeffs : float64 (C, n, n, L)
        ``coeffs[c, i, o, l]``: cosine-series coefficient ``l`` of **f · |mu_o|** [1/sr] for
        incident node ``mu[i]``, outgoing node ``mu[o]``, channel ``c`` (``a_0`` is the mean over
        ``phi_d``; no quadrature weights, no extra 1/π).  C = 1 (mono) or 3 (linear R, G, B) for
        ``.bsdf``; any C for HDF5.
    reflection : float64 (C, h, h, L) or None
        An opaque paint's table can be given as this alone instead of ``coeffs``: the reflection
        quadrant ``coeffs[:, h:, :h]`` (incident ``mu[h:]``, down into the paint; outgoing
        ``mu[:h]``, up), the other three quadrants being zero.  The table is then
        :attr:`reflection_only`: :attr:`coeffs` is built from it when first read (4× the memory),
        and the ``.bsdf`` writer and :meth:`albedo` never build it.
    eta : float
        Relative index eta_below / eta_above of the whole stack (header field; renderers scale
        transmitted radiance with it).
    alpha : (float, float)
        Beckmann-equivalent roughness of the top and bottom surfaces (informational).
    delta : dict or None
        The smooth coat's first-surface mirror term, e.g. ``{"kind": "fresnel", "eta": 1.5}``:
        ``F(theta_i; eta)`` times a delta in the mirror direction, *not* in ``coeffs``.
    metadata : dict
        str -> JSON-able (recipe name, flakedb version, ...).
    channels : tuple of str or None
        Channel names; default ``("R", "G", "B")`` for C = 3, ``("mono",)`` for C = 1,
        ``("c0", "c1", …)`` otherwise.

    Examples
    --------
    A white Lambertian primer, f·|μ_o| = |μ_o|/π, given as its reflection quadrant: its albedo is 1 at
    every incident node going down into it, 0 for light arriving from below:

    >>> from flakedb.rt.basis.quadrature import gauss_radau_unit
    >>> x, _ = gauss_radau_unit(8)
    >>> refl = np.broadcast_to((x[::-1] / np.pi)[None, None, :, None], (1, 8, 8, 1))        # (C, h, h, L)
    >>> t = BSDFTable(np.concatenate([-x[::-1], x]), reflection=refl)
    >>> t.reflection_only, t.coeffs.shape
    (True, (1, 16, 16, 1))
    >>> bool(np.allclose(t.albedo()[0, 8:], 1.0, rtol=1e-14, atol=0)), bool(np.all(t.albedo()[0, :8] == 0))
    (True, True)
    """

    def __init__(self, mu, coeffs=None, eta=1.0, alpha=(0.0, 0.0), delta=None, metadata=None, channels=None,
                 reflection=None):
        if (coeffs is None) == (reflection is None):
            raise ValueError("BSDFTable needs exactly one of coeffs (C, n, n, L) and reflection (C, h, h, L)")
        self.mu = mu = np.asarray(mu, dtype=np.float64)
        if mu.ndim != 1 or mu.size < 2 or mu.size % 2:
            raise ValueError(f"BSDFTable.mu must be a 1-D array of even length n = 2h >= 2, got shape {mu.shape}")
        h = mu.size // 2
        if not (np.all(np.isfinite(mu)) and np.all(np.diff(mu) > 0)):
            raise ValueError("BSDFTable.mu must be finite and strictly ascending")
        if not (mu[h - 1] < 0 < mu[h] and mu[-1] <= 1.0 and mu[0] >= -1.0):
            raise ValueError(
                f"BSDFTable.mu must be [-x_h … -x_1, x_1 … x_h] in [-1, 1] with no node at 0; "
                f"got mu[h-1] = {mu[h - 1]!r}, mu[h] = {mu[h]!r}, range [{mu[0]!r}, {mu[-1]!r}]")
        if not np.allclose(mu[:h], -mu[h:][::-1], rtol=0, atol=1e-12):
            raise ValueError("BSDFTable.mu must be symmetric: mu[:h] == -mu[h:][::-1] (one rule per hemisphere)")
        self._coeffs = self._reflection = None
        if coeffs is not None:
            c = np.asarray(coeffs, dtype=np.float64)
            if c.ndim != 4 or c.shape[1] != mu.size or c.shape[2] != mu.size or c.shape[3] < 1 or c.shape[0] < 1:
                raise ValueError(f"BSDFTable.coeffs must have shape (C, n, n, L) with n = {mu.size}, got {c.shape}")
            self._coeffs = c
        else:
            c = np.asarray(reflection, dtype=np.float64)
            if c.ndim != 4 or c.shape[1] != h or c.shape[2] != h or c.shape[3] < 1 or c.shape[0] < 1:
                raise ValueError(f"BSDFTable.reflection must have shape (C, h, h, L) with h = {h}, got {c.shape}")
            self._reflection = c
        # each stored value once: a broadcast axis (a grey table's channels, stride 0) is checked at one index
        if not np.all(np.isfinite(c[tuple(slice(0, 1) if st == 0 else slice(None) for st in c.strides)])):
            raise ValueError("BSDFTable.coeffs contains NaN or inf")
        self.eta = float(eta)
        if not (math.isfinite(self.eta) and self.eta > 0):
            raise ValueError(f"BSDFTable.eta must be a positive finite relative index, got {eta!r}")
        alpha_t = tuple(float(a) for a in np.atleast_1d(alpha))
        if len(alpha_t) != 2:
            raise ValueError(f"BSDFTable.alpha must hold 2 roughness values (top, bottom), got {alpha!r}")
        self.alpha = alpha_t
        if delta is not None:
            check_delta(delta)
            delta = dict(delta)
        self.delta = delta
        self.metadata = dict(metadata or {})
        if channels is None:
            channels = _default_channels(c.shape[0])
        self.channels = tuple(str(s) for s in channels)
        if len(self.channels) != c.shape[0]:
            raise ValueError(f"BSDFTable.channels names {len(self.channels)} channels, coeffs has {c.shape[0]}")

    def __repr__(self):
        return (f"BSDFTable(n={self.n}, channels={self.channels}, orders={self.n_orders}, eta={self.eta}, "
                f"alpha={self.alpha}, delta={self.delta}, reflection_only={self.reflection_only})")

    @property
    def coeffs(self) -> np.ndarray:
        """(C, n, n, L), built from :attr:`reflection` on first access for a reflection-only table."""
        if self._coeffs is None:
            r = self._reflection
            C, h, _, L = r.shape
            c = np.zeros((C, 2 * h, 2 * h, L))
            c[:, h:, :h] = r
            self._coeffs, self._reflection = c, None
        return self._coeffs

    @coeffs.setter
    def coeffs(self, value):
        c = np.asarray(value, dtype=np.float64)
        if c.ndim != 4 or c.shape[1:3] != (self.n, self.n):
            raise ValueError(f"BSDFTable.coeffs must have shape (C, n, n, L) with n = {self.n}, got {c.shape}")
        self._coeffs, self._reflection = c, None

    @property
    def reflection_only(self) -> bool:
        """True when the table was given as its reflection quadrant alone (and not densified since)."""
        return self._reflection is not None

    @property
    def stored(self) -> np.ndarray:
        """The coefficients as the table holds them: :attr:`reflection` quadrant (C, h, h, L) of a
        :attr:`reflection_only` table, else :attr:`coeffs` (C, n, n, L).  ``replace(stored=…)`` gives a
        table holding the same kind."""
        return self._reflection if self.reflection_only else self._coeffs

    def live_quadrant(self) -> np.ndarray:
        """(C, h, h, L): the reflection quadrant ``coeffs[:, h:, :h]`` (a view), without building
        :attr:`coeffs` for a reflection-only table."""
        if self._reflection is not None:
            return self._reflection
        h = self.n // 2
        return self._coeffs[:, h:, :h]

    def replace(self, **changes) -> "BSDFTable":
        """A new table with the given constructor arguments changed (``coeffs=`` or ``reflection=``
        replaces the coefficients, ``stored=`` those of the kind this table holds (:attr:`stored`);
        the other fields are kept)."""
        if "stored" in changes:
            changes["reflection" if self.reflection_only else "coeffs"] = changes.pop("stored")
        kw = {"mu": self.mu, "eta": self.eta, "alpha": self.alpha, "delta": self.delta,
              "metadata": self.metadata, "channels": self.channels}
        if "coeffs" not in changes and "reflection" not in changes:
            kw.update({"reflection": self._reflection} if self.reflection_only else {"coeffs": self._coeffs})
        kw.update(changes)
        return BSDFTable(**kw)

    @property
    def n(self) -> int:
        return self.mu.size

    @property
    def n_channels(self) -> int:
        return (self._coeffs if self._coeffs is not None else self._reflection).shape[0]

    @property
    def n_orders(self) -> int:
        return (self._coeffs if self._coeffs is not None else self._reflection).shape[3]

    def albedo(self) -> np.ndarray:
        """(C, n): ``2π ∫ a_0(mu_i, mu_o) dmu_o`` per channel and incident node, with the spec's
        Catmull-Rom integral over the file nodes (zero nodes inserted).  For the Y channel of a
        written ``.bsdf`` this is ``2π·cdf[i][N-1]``."""
        nodes = insert_zero_nodes(self.mu)
        h = self.n // 2
        if self.reflection_only:  # rows h… alone (the others are 0), a broadcast channel axis once
            r = self._reflection[..., 0]                             # (C, h_i, h_o)
            one = r.shape[0] > 1 and r.strides[0] == 0
            v = np.zeros((1 if one else r.shape[0], h, nodes.size))
            v[..., :h] = r[:1] if one else r
            out = np.zeros((self.n_channels, self.n))
            out[:, h:] = 2.0 * np.pi * catmull_rom_cdf(nodes, v)[..., -1]
            return out
        a0 = self._coeffs[..., 0]                                    # (C, n_i, n_o)
        v = np.zeros(a0.shape[:2] + (nodes.size,))
        v[..., :h] = a0[..., :h]
        v[..., h + 2:] = a0[..., h:]
        return 2.0 * np.pi * catmull_rom_cdf(nodes, v)[..., -1]


#: Slack of the table's energy check (:func:`energy_albedo`): the readers' float32 and the Catmull-Rom integral.
ENERGY_SLACK = 1e-3


def energy_albedo(table) -> np.ndarray:
    """(C, n/2): the albedo a renderer integrates from ``table`` for light from above: the table's Catmull-Rom
    albedo (:meth:`BSDFTable.albedo`) plus the smooth coat's mirror term F(μ_i) when it has one.  The energy
    check of ``flakedb info`` and of compose (a file whose maximum exceeds 1 + :data:`ENERGY_SLACK` is not
    written without ``--allow-unphysical``): one function, so the two never disagree."""
    h = table.n // 2
    mu_in = np.asarray(table.mu[h:], float)
    alb = table.albedo()[:, h:]
    F = np.zeros(h) if not table.delta else fresnel_dielectric(mu_in, float(table.delta["eta"])).R
    return alb + F[None, :]


def _default_channels(c: int) -> tuple:
    if c == 3:
        return ("R", "G", "B")
    if c == 1:
        return ("mono",)
    return tuple(f"c{k}" for k in range(c))
