"""The solved stack (:class:`StackBSDF`): reflection from above in the solver's normalisation, the
transmission blocks of a stack without a primer, the smooth top's analytic delta, and their evaluation
(docs/model.md §4, conventions)."""

from dataclasses import dataclass, field

import numpy as np

from flakedb.conventions import fourier_weight
from flakedb.rt.basis.pole import zero_pole_orders
from flakedb.rt.adding.specular import smoothed_specular

@dataclass
class StackBSDF:
    """The solved stack.  Blocks are in the solver's normalisation (conventions), air-side nodes.

    ``Rt`` (L, C, h, h): reflection from above; ``Ttb``/``Rb``/``Tbt`` are present only for stacks
    without a primer (transmission to a medium below with the binder's index).  ``delta_F`` (h,) is
    the first-surface Fresnel reflectance of a smooth top at the air-side nodes (None otherwise).
    """

    x: np.ndarray
    w: np.ndarray
    Rt: np.ndarray
    eta: float
    delta_F: np.ndarray | None
    Ttb: np.ndarray | None = None
    Rb: np.ndarray | None = None
    Tbt: np.ndarray | None = None
    x_in: np.ndarray | None = None
    w_in: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    #: R_s (C, h, h): the never-scattered paths of a smooth inner interface (docs/model.md §4, "Specular paths
    #: and the pole"), held in ``Rt`` as a Jackson-smoothed series of ``specular_orders`` (C,) orders; None: none
    specular: np.ndarray | None = None
    specular_orders: np.ndarray | None = None
    #: index of the binder below the stack relative to the air (where ``Ttb`` leads): basic radiance there
    #: carries η² times its flux per unit of the solver's measure
    eta_bottom: float = 1.0
    #: Beckmann roughness of a rough top interface (0: smooth or none): what the file's header records
    top_alpha: float = 0.0

    @property
    def n_orders(self):
        return self.Rt.shape[0]

    def scattered(self):
        """The stack without the smoothed specular series of inner mirrors in ``Rt`` (itself when it has none):
        what an aspecular geometry sees (the delta hits no aspecular angle, but its smoothed series would reach
        neighbouring nodes through the readers' interpolation in μ)."""
        if self.specular is None:
            return self
        L = self.n_orders
        Rt = np.array(np.broadcast_to(self.Rt, self.Rt.shape[:1] + (self.specular.shape[0],) + self.Rt.shape[2:]))
        for Lc in np.unique(self.specular_orders):
            c = np.nonzero(self.specular_orders == Lc)[0]
            series = zero_pole_orders(smoothed_specular(self.specular[c], int(Lc)), self.x, self.x)
            Rt[:int(Lc), c] -= series[:L]
        return StackBSDF(x=self.x, w=self.w, Rt=Rt, eta=self.eta, delta_F=self.delta_F, Ttb=self.Ttb, Rb=self.Rb,
                         Tbt=self.Tbt, x_in=self.x_in, w_in=self.w_in, info=self.info, eta_bottom=self.eta_bottom,
                         top_alpha=self.top_alpha)

    def f_coefficients(self, block="Rt"):
        """Cosine coefficients f_l(μ_i → μ_o) (1/sr) of a block, (L, C, h_out, h_in).

        f_l = S_l[o, i] / (c_l w_i μ_i) (conventions).  For transmission blocks this is the
        basic-radiance BSDF; multiply by (η_o/η_i)² for radiance.
        """
        S = getattr(self, block)
        x_i, w_i = (self.x, self.w) if block in ("Rt", "Ttb") else (self.x_in, self.w_in)
        cl = fourier_weight(np.arange(S.shape[0]))[:, None, None, None]
        if S.shape[1] > 1 and S.strides[1] == 0:  # channels solved once (grey): stays a broadcast view
            return np.broadcast_to(S[:, :1] / (cl * (w_i * x_i)[None, None, None, :]), S.shape)
        return S / (cl * (w_i * x_i)[None, None, None, :])

    def albedo(self, include_delta=True):
        """Directional albedo of reflection at the air-side nodes, (C, h): ∫ f |μ_o| dω_o (+ F).

        >>> from flakedb.rt.adding.components import Lambertian, Smooth, SolverSettings
        >>> from flakedb.rt.adding.stack import solve_stack
        >>> white = solve_stack(Smooth(1.5), [], Lambertian(1.0), SolverSettings(n=8))   # a lossless stack
        >>> bool(np.allclose(white.albedo(), 1.0, rtol=0, atol=1e-12)), bool(np.all(white.albedo(False) < 1.0))
        (True, True)
        """
        S0 = self.Rt[0]  # (C, h_o, h_i)
        a = np.einsum("coi,o->ci", S0, self.w * self.x) / (self.w * self.x)[None, :]
        if include_delta and self.delta_F is not None:
            a = a + self.delta_F[None, :]
        return a

    def transmittance(self):
        """Directional transmittance (C, h) into the medium below (flux fraction), if transmissive."""
        if self.Ttb is None:
            return None
        S0 = self.Ttb[0]
        return self.eta_bottom**2 * np.einsum("coi,o->ci", S0, self.w_in * self.x_in) / (self.w * self.x)[None, :]

    def eval_nodes(self, phi_d):
        """f (1/sr) of reflection at all node pairs and azimuths: (C, h_o, h_i, len(phi_d))."""
        f = self.f_coefficients("Rt")
        phi_d = np.atleast_1d(phi_d)
        cos = np.cos(np.arange(f.shape[0])[:, None] * phi_d[None, :])  # (L, P)
        return np.einsum("lcoi,lp->coip", f, cos)

