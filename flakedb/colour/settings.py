"""The colour conditions of every report, comparison and fit, with their defaults stated once.

Defaults (docs/colorimetry.md, "Conditions"; every command's ``--observer``, ``--illuminant`` and
``--geometries`` fall back to these, and nothing else in the package names a default)
--------------------------------------------------------------------------------------------------
* **Observer: CIE 1964 10°** (:data:`DEFAULT_OBSERVER`).  Colour control of painted panels is
  reported under D65 with the 10° observer: a panel fills far more than the 4° field the 2°
  observer is defined for (CIE 15:2004 recommends the 10° observer for fields larger than about
  4°), and test laboratories state D65/10° as their default for coatings ("by standard, samples
  are illuminated with D65 … 10° normal observers", ifo GmbH, colour measurement to DIN EN ISO/CIE
  11664-4, https://www.ifo-gmbh.de/en/services/colour-measurement/).  No OEM specification's text
  was available to cite; the 2° observer stays one option away (``observer="2"``).
* **Illuminant: D65** (:data:`DEFAULT_ILLUMINANT`), CIE daylight.
* **Tolerance: ΔE00 ≤ 1 at every geometry** (:data:`DEFAULT_MAX_DE00`), a policy, not a standard.
* **Geometry set: "e2194"** (:data:`DEFAULT_GEOMETRY_SET`), the six 45° geometries every
  multi-angle instrument measures; "e2539" adds the five 15° geometries (:data:`E2539_EXTRA`);
  "xrite19" adds eight out-of-plane geometries (:data:`OUT_OF_PLANE_GEOMETRIES`).

**RGB-mode paints are the exception, by construction.**  Their channels are white-normalised linear
sRGB, defined under D65 and the 2° observer (docs/model.md, RGB mode); there is no spectrum from
which a 10° colour could be computed.  :func:`resolve` therefore gives an RGB paint D65/2° when the
caller did not choose, says so in :attr:`ColourSettings.note`, and refuses an explicit 10° or a
non-D65 illuminant (compose in spectral mode for those).  A mono (grey) paint is the same grey
under every observer and illuminant.

Geometries (illumination θ_i and aspecular γ in degrees, ASTM E2194's sign in plane: positive
towards the illuminator, the detector at θ_v = θ_i − γ from the normal; out of plane a third angle,
the azimuth, in X-Rite's notation: :mod:`flakedb.colour.geometry`)
-------------------------------------------------------------------------------------------------
* :data:`E2194_GEOMETRIES`: illumination 45°, aspecular −15°, 15°, 25°, 45°, 75°, 110° (X-Rite MA-T
  / MA98 class).  ASTM E2194 itself asks for three aspecular angles; the −15° geometry, beyond the
  specular, is one of E2539's additions, kept here because the instruments measure it with the 45°
  illuminator (docs/colour-matching.md, "Geometries").
* :data:`E2539_EXTRA`: illumination 15°, aspecular −45°, −15°, 15°, 45°, 80° (X-Rite's 15as-45 …
  15as80).  What is and is not verified about this set: :mod:`flakedb.match.targets`.

* :data:`OUT_OF_PLANE_GEOMETRIES`: the eight out-of-plane geometries X-Rite's formulation software
  names, (illumination, aspecular, azimuth) = 45as25az±90, 45as60az±125.3, 15as38.3az±43,
  15as46.9az±104.5: two pairs of detectors out of the plane of incidence, at (0.640856, ±0.422618,
  0.640856) and (0, ±0.7071, 0.7071), seen with the 45° and the 15° illuminator (source, notation and
  the checks of both against the published vectors: :mod:`flakedb.colour.geometry`).  The set "xrite19"
  is these with the eleven in-plane E2539 geometries (the 19 geometries that software names; which
  instrument model measures which subset is not stated there and not claimed here).  An out-of-plane
  geometry is a point of the BSDF's full azimuth, evaluated from its Fourier series in φ_d.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Default observer of reports, comparisons and fits (module docstring: why 10°).
DEFAULT_OBSERVER = "10"
#: Default illuminant.
DEFAULT_ILLUMINANT = "D65"
#: Default geometry set of the colour report and of a prediction without a target.
DEFAULT_GEOMETRY_SET = "e2194"
#: Default ΔE00 limit at every geometry of `compare` and of a match's outcome: a policy (the user's
#: --max-de / --limit replace it), not a standard's number (docs/colour-tolerances.md).
DEFAULT_MAX_DE00 = 1.0
#: The only conditions an RGB-mode paint has (module docstring).
RGB_MODE_OBSERVER, RGB_MODE_ILLUMINANT = "2", "D65"

#: The 45° set, (illumination_deg, aspecular_deg).
E2194_GEOMETRIES = tuple((45.0, g) for g in (-15.0, 15.0, 25.0, 45.0, 75.0, 110.0))
#: Extra in-plane geometries at 15° illumination of ASTM E2539-class instruments.
E2539_EXTRA = tuple((15.0, g) for g in (-45.0, -15.0, 15.0, 45.0, 80.0))
#: Both sets.
E2539_GEOMETRIES = E2194_GEOMETRIES + E2539_EXTRA
#: Out-of-plane geometries (illumination_deg, aspecular_deg, azimuth_deg), X-Rite's notation (module docstring).
OUT_OF_PLANE_GEOMETRIES = ((45.0, 25.0, 90.0), (45.0, 25.0, -90.0), (45.0, 60.0, 125.3), (45.0, 60.0, -125.3),
                           (15.0, 38.3, 43.0), (15.0, 38.3, -43.0), (15.0, 46.9, 104.5), (15.0, 46.9, -104.5))
#: The E2539 set and the out-of-plane geometries (azimuth 0 written out for the in-plane ones).
XRITE19_GEOMETRIES = tuple(g + (0.0,) for g in E2539_GEOMETRIES) + OUT_OF_PLANE_GEOMETRIES
#: Named sets (the CLI's --geometries).
GEOMETRY_SETS = {"e2194": E2194_GEOMETRIES, "e2539": E2539_GEOMETRIES, "xrite19": XRITE19_GEOMETRIES}
#: The geometries the flop index needs (all in every named set).
FLOP_GEOMETRIES = ((45.0, 15.0), (45.0, 45.0), (45.0, 110.0))


def _observer_key(observer) -> str:
    key = str(observer).strip().lower().replace("deg", "").replace("°", "").replace("_degree", "").strip()
    if key.endswith(".0"):
        key = key[:-2]
    if key not in ("2", "10"):
        raise ValueError(f"observer {observer!r}: use 2 (CIE 1931 2°) or 10 (CIE 1964 10°)")
    return key


@dataclass(frozen=True)
class ColourSettings:
    """Observer ("2" / "10"), illuminant name and geometry set of a report, comparison or fit."""

    observer: str = DEFAULT_OBSERVER
    illuminant: str = DEFAULT_ILLUMINANT
    geometry_set: str = DEFAULT_GEOMETRY_SET
    note: str = ""

    @property
    def geometries(self) -> tuple:
        return GEOMETRY_SETS[self.geometry_set]

    @property
    def label(self) -> str:
        return f"{self.illuminant}/{self.observer}°"


def resolve(observer=None, illuminant=None, geometry_set=None, mode="spectral") -> ColourSettings:
    """The settings of a paint in ``mode`` from the caller's choices (None: the default; module docstring).

    Raises ValueError naming the value and what is allowed: an unknown observer or geometry set; an
    RGB-mode paint asked for the 10° observer or a non-D65 illuminant.

    >>> resolve().label, len(resolve(geometry_set="e2539").geometries)
    ('D65/10°', 11)
    >>> resolve(mode="rgb").label
    'D65/2°'
    >>> resolve(observer="10", mode="rgb")
    Traceback (most recent call last):
    ...
    ValueError: an RGB-mode paint has colours under D65/2° only (its channels are linear sRGB), not D65/10°: compose it in spectral mode (mode: spectral)
    """
    gs = DEFAULT_GEOMETRY_SET if geometry_set is None else str(geometry_set).lower()
    if gs not in GEOMETRY_SETS:
        raise ValueError(f"geometry set {geometry_set!r}: use one of {', '.join(GEOMETRY_SETS)}")
    obs = None if observer is None else _observer_key(observer)
    ill = None if illuminant is None else str(illuminant)
    if mode == "rgb":
        if (obs not in (None, RGB_MODE_OBSERVER)) or (ill is not None and ill.upper() != RGB_MODE_ILLUMINANT):
            raise ValueError(f"an RGB-mode paint has colours under {RGB_MODE_ILLUMINANT}/{RGB_MODE_OBSERVER}° only "
                             f"(its channels are linear sRGB), not {ill or RGB_MODE_ILLUMINANT}/"
                             f"{obs or RGB_MODE_OBSERVER}°: compose it in spectral mode (mode: spectral)")
        note = "" if obs is not None else (f"RGB-mode paint: colours under {RGB_MODE_ILLUMINANT}/{RGB_MODE_OBSERVER}° "
                                           f"(its channels are linear sRGB), not the default "
                                           f"{DEFAULT_ILLUMINANT}/{DEFAULT_OBSERVER}°")
        return ColourSettings(RGB_MODE_OBSERVER, RGB_MODE_ILLUMINANT, gs, note)
    return ColourSettings(obs or DEFAULT_OBSERVER, ill or DEFAULT_ILLUMINANT, gs)


def for_target(mode, target=None, observer=None, illuminant=None, geometry_set=None) -> ColourSettings:
    """The conditions of a paint in ``mode`` compared with ``target`` (a :class:`flakedb.match.targets.Target`, or
    None): the caller's choice, else the target's own conditions, else the defaults (:func:`resolve`).  The one
    home of this rule: compare, batch compare, match and calibrate ask it.

    A spectral target can be integrated under any conditions, so against an RGB-mode paint (D65/2° by
    construction) its own conditions give way when the caller chose none; an L*a*b*-only target keeps its own
    (and an RGB paint is then refused unless they are D65/2°).

    >>> class T: observer, illuminant, spectral = "10", "D65", True
    >>> for_target("spectral", T()).label, for_target("rgb", T()).label, for_target("rgb").label
    ('D65/10°', 'D65/2°', 'D65/2°')
    >>> for_target("spectral", T(), observer="2").label
    'D65/2°'
    """
    free = target is None or (bool(getattr(target, "spectral", False)) and mode == "rgb")
    return resolve(observer if observer is not None else (None if free else target.observer),
                   illuminant if illuminant is not None else (None if free else target.illuminant),
                   geometry_set, mode)

