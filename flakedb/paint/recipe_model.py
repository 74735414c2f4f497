"""The recipe's data model: what a parsed recipe holds (layers, particles, spectra) and its error type.

Made by :func:`flakedb.paint.recipe.parse_recipe`; field meanings in :mod:`flakedb.paint.recipe` and
schemas/recipe.schema.json.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Recipe format version this flakedb reads (the ``flakedb:`` key).
FORMAT_VERSION = 1


#: Σ volume fraction of spherical pigments per layer: random close packing (module docstring).
PIGMENT_PACKING_LIMIT = 0.64


#: Σ volume fraction above which a warning says the dilute (independent scattering) model is doubtful.
DILUTE_WARNING = 0.3


#: Lambertian albedo of the named primer colours.  black 0.04 (Munsell value ≈ 2.3 by ASTM D1535:
#: a carbon-black primer), gray 0.18 (the photographic 18 % grey card, Munsell ≈ N4.9, middle grey),
#: white 0.9 (Munsell ≈ N9.6, a good white primer; TiO2 whites reach 0.9-0.95).  Munsell values
#: computed with colour.munsell_value(Y, method="ASTM D1535").
PRIMER_ALBEDO = {"black": 0.04, "gray": 0.18, "white": 0.9}


#: Defaults of the ``spectral`` block.
DEFAULT_SPECTRAL = {"mode": "spectral", "range_nm": [380.0, 780.0], "step_nm": 10.0}


class RecipeError(ValueError):
    """An invalid recipe.  ``problems`` lists every problem as ``path: message``."""

    def __init__(self, source, problems):
        self.source = str(source)
        self.problems = list(problems)
        super().__init__(f"{self.source}: invalid recipe ({len(self.problems)} problem"
                         f"{'s' if len(self.problems) != 1 else ''}):\n  " + "\n  ".join(self.problems))


@dataclass
class Spectrum:
    """A tabulated spectrum (nm → value), linear between points, held constant beyond them.

    >>> Spectrum(np.array([400.0, 700.0]), np.array([0.2, 0.8])).at([400.0, 550.0, 800.0]).tolist()
    [0.2, 0.5, 0.8]
    """

    wavelength_nm: np.ndarray
    value: np.ndarray

    def at(self, wavelength_nm):
        return np.interp(np.asarray(wavelength_nm, float), self.wavelength_nm, self.value)


@dataclass
class Clearcoat:
    thickness_um: float
    ior: float
    roughness: float = 0.0
    absorption_per_um: float | Spectrum | None = None
    path: str = "layers[0].clearcoat"


@dataclass
class CatalogParticle:
    """A catalogue species with a volume fraction; ``entry`` is the resolved catalogue entry."""

    species: str
    entry: dict
    volume_fraction: float
    orientation_alpha: float | None = None
    diameter_um: float | None = None
    opaque: bool = False
    median_diameter_um: float | None = None
    gsd: float | None = None
    path: str = ""
    #: the recipe's ``orientation_distribution`` override (None: the catalogue's, else Beckmann)
    orientation_distribution: str | None = None
    #: flakes: geometric standard deviation of the log-normal diameter distribution (texture only)
    diameter_gsd: float | None = None
    #: the recipe's weight_fraction when the loading was given by weight (volume_fraction is then
    #: converted from it: flakedb.paint.formulation); None when given by volume
    weight_fraction: float | None = None
    #: interference flakes: the recipe's film overrides (coating_thickness_nm, coating_thickness_rel_sd,
    #: substrate_thickness_nm, substrate_thickness_rel_sd), already applied to ``entry``; empty: none
    film_overrides: dict = field(default_factory=dict)
    #: flakes: the recipe's grating fields (grating_period_nm, grating_amplitude_nm), already applied to ``entry``
    grating_overrides: dict = field(default_factory=dict)

    @property
    def kind(self):
        return self.entry["kind"]

    @property
    def is_flake(self):
        return self.kind in ("interference_flake", "mirror_flake")


@dataclass
class FlakeTable:
    """R or T of a custom flake over the flake cosine c (constant: c = [0, 1], equal values)."""

    c: np.ndarray
    value: np.ndarray


@dataclass
class CustomFlake:
    R: FlakeTable
    T: FlakeTable
    orientation_alpha: float
    optical_depth: float
    name: str = "custom-flake"
    path: str = ""
    #: the flake normals' distribution (flakedb.rt.scattering.microflake.FLAKE_DISTRIBUTIONS)
    orientation_distribution: str = "beckmann"


@dataclass
class CustomMedium:
    """``albedo``: a float or a :class:`Spectrum` (per band); ``phase``: ``"isotropic"``, ``("hg", g)``,
    ``("vmf", kappa)`` (a recipe's mean cosine g converted to κ, :func:`flakedb.rt.scattering.media.vmf_kappa_from_mean_cosine`)
    or ``("table", cos_theta, value)``."""

    albedo: float | Spectrum
    phase: object
    optical_depth: float
    name: str = "custom-medium"
    path: str = ""


@dataclass
class Basecoat:
    thickness_um: float
    ior: float
    particles: list = field(default_factory=list)
    path: str = ""
    #: Beckmann α of the inner interface at this basecoat's top (0: smooth; only where the ior changes)
    interface_roughness: float = 0.0
    #: volume and weight fractions, PVC and the CPVC estimate of the layer (recipe_checks.formulation_record)
    formulation: dict | None = None


@dataclass
class Primer:
    """Lambertian primer: ``albedo`` is a float or a :class:`Spectrum`; ``label`` says where it came from."""

    albedo: float | Spectrum
    label: str
    path: str = ""


@dataclass
class MetalBase:
    """A metal base in place of the primer (docs/model.md §4): a Beckmann microfacet conductor of
    roughness ``roughness``.  ``material``: a catalogue material name (complex index n + ik per
    wavelength, :func:`flakedb.paint.materials.refractive_index`) or a wavelength-independent complex
    index n + ik (relative to vacuum).  ``energy_compensation``: Kulla & Conty's lobe (default)."""

    material: str | complex
    roughness: float
    energy_compensation: bool = True
    label: str = ""
    path: str = ""


@dataclass
class Recipe:
    """A validated recipe.  ``wavelength_nm`` is the band grid (spectral mode) or the integration
    grid of the RGB conversion (rgb mode); None in mono mode.  ``n`` is None for ``auto``."""

    name: str
    mode: str
    wavelength_nm: np.ndarray | None
    n: int | None
    clearcoat: Clearcoat | None
    basecoats: list
    primer: Primer | None
    description: str = ""
    text: str = ""
    source: str = "<recipe>"
    warnings: list = field(default_factory=list)
    doc: dict = field(default_factory=dict)
    #: accuracy targets of ``resolution: auto`` ({albedo_error, lobe_error}; empty: the defaults of
    #: :data:`flakedb.solve.resolution.AUTO_TARGETS`)
    targets: dict = field(default_factory=dict)
    #: a metal base in place of the primer (None: the primer, or nothing)
    metal: MetalBase | None = None

    @property
    def binder_ior(self) -> float:
        """The single binder index below the top interface (1.0 when there is no layer with one)."""
        if self.clearcoat is not None:
            return self.clearcoat.ior
        if self.basecoats:
            return self.basecoats[0].ior
        return 1.0

    def particles(self):
        """(basecoat, particle) pairs, top to bottom."""
        return [(b, p) for b in self.basecoats for p in b.particles]
