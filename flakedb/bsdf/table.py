"""The solver's hand-over to the file side: :class:`BSDFTable` (docs/bsdf-format.md), the file
constants shared by the codecs, and :class:`BSDFFileError`."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from flakedb.bsdf.metadata import check_delta
from flakedb.bsdf.spline import catmull_rom_cdf, insert_zero_nodes

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
@dataclasses.dataclass
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
    """

    mu: np.ndarray
    coeffs: np.ndarray
    eta: float = 1.0
    alpha: tuple = (0.0, 0.0)
    delta: dict | None = None
    metadata: dict = dataclasses.field(default_factory=dict)
    channels: tuple | None = None

    def __post_init__(self):
        self.mu = np.asarray(self.mu, dtype=np.float64)
        self.coeffs = np.asarray(self.coeffs, dtype=np.float64)
        mu, c = self.mu, self.coeffs
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
        if c.ndim != 4 or c.shape[1] != mu.size or c.shape[2] != mu.size or c.shape[3] < 1 or c.shape[0] < 1:
            raise ValueError(f"BSDFTable.coeffs must have shape (C, n, n, L) with n = {mu.size}, got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("BSDFTable.coeffs contains NaN or inf")
        self.eta = float(self.eta)
        if not (math.isfinite(self.eta) and self.eta > 0):
            raise ValueError(f"BSDFTable.eta must be a positive finite relative index, got {self.eta!r}")
        alpha = tuple(float(a) for a in np.atleast_1d(self.alpha))
        if len(alpha) != 2:
            raise ValueError(f"BSDFTable.alpha must hold 2 roughness values (top, bottom), got {self.alpha!r}")
        self.alpha = alpha
        if self.delta is not None:
            check_delta(self.delta)
            self.delta = dict(self.delta)
        self.metadata = dict(self.metadata or {})
        if self.channels is None:
            self.channels = _default_channels(c.shape[0])
        self.channels = tuple(str(s) for s in self.channels)
        if len(self.channels) != c.shape[0]:
            raise ValueError(f"BSDFTable.channels names {len(self.channels)} channels, coeffs has {c.shape[0]}")

    @property
    def n(self) -> int:
        return self.mu.size

    @property
    def n_channels(self) -> int:
        return self.coeffs.shape[0]

    def albedo(self) -> np.ndarray:
        """(C, n): ``2π ∫ a_0(mu_i, mu_o) dmu_o`` per channel and incident node, with the spec's
        Catmull-Rom integral over the file nodes (zero nodes inserted).  For the Y channel of a
        written ``.bsdf`` this is ``2π·cdf[i][N-1]``."""
        nodes = insert_zero_nodes(self.mu)
        h = self.n // 2
        a0 = self.coeffs[..., 0]                                    # (C, n_i, n_o)
        v = np.zeros(a0.shape[:2] + (nodes.size,))
        v[..., :h] = a0[..., :h]
        v[..., h + 2:] = a0[..., h:]
        return 2.0 * np.pi * catmull_rom_cdf(nodes, v)[..., -1]

def _default_channels(c: int) -> tuple:
    if c == 3:
        return ("R", "G", "B")
    if c == 1:
        return ("mono",)
    return tuple(f"c{k}" for k in range(c))
