"""Observation conditions of the texture indices: light, view, source size, aperture, resolved spot
(docs/texture.md §2 "Observers").

An :class:`Observer` is what sees the panel: the side of one resolved spot on the panel (a camera
pixel's footprint, or what the eye resolves at its distance), the angular radius of its collecting
aperture seen from the panel (lens or pupil), and the angular radius of the directional source.
Each observer has directional geometries (light and view polar angles in air, in the plane of
incidence on opposite sides of the normal) and one diffuse geometry (uniform sky) for graininess.

Presets (every number's origin is stated; none is a manufacturer's specification):

* ``byk-mac-like``: camera normal to the panel, collimated LED light at 15°, 45°, 75° from the
  normal (the BYK-mac i sparkle geometries, BYK-Gardner product literature), diffuse light for
  graininess.  Assumed optics: a 15 µm pixel footprint, a collecting half-angle of 0.5° and a
  source half-angle of 1.0°.  The instrument's optics and its image-processing algorithm are not
  published (proprietary): flakedb's indices are *not* its S_a, S_i, G readings (docs/texture.md).
* ``person-1m`` / ``person-3m``: the sun (half-angle 0.2665°, the solar disc; Allen's Astrophysical
  Quantities) at 15°, 45°, 75° from the normal, the viewer on the normal at 1 m / 3 m, daylight
  pupil 3 mm (Watson & Yellott 2012, J. Vision 12(10):12: 2.9–3.5 mm at 1000–10000 cd/m²) and a
  resolved spot of one arcminute (normal visual acuity, 1/60°): 291 µm at 1 m, 873 µm at 3 m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Wavelength (nm) at which a flake's diffraction spread is evaluated (the peak of V(λ)).
DIFFRACTION_WAVELENGTH_NM = 555.0
#: One arcminute in radians: the resolved angle of normal visual acuity (20/20 vision).
ARCMIN_RAD = np.pi / (180.0 * 60.0)
#: Angular radius of the solar disc (degrees), mean Earth–Sun distance.
SUN_HALF_ANGLE_DEG = 0.2665


@dataclass(frozen=True)
class Observer:
    """``spot_um``: side of one resolved (square) spot on the panel, µm; ``aperture_half_angle_rad``:
    angular radius of the collecting aperture seen from the panel, rad; ``source_half_angle_deg``:
    angular radius of the directional source, degrees; ``light_deg``: light polar angles (air) of
    the directional geometries; ``view_deg``: the view's polar angle (air) for all of them."""

    name: str
    spot_um: float
    aperture_half_angle_rad: float
    source_half_angle_deg: float
    light_deg: tuple = (15.0, 45.0, 75.0)
    view_deg: float = 0.0
    description: str = ""

    def __post_init__(self):
        for f, lo, hi in (("spot_um", 0.1, 1e5), ("aperture_half_angle_rad", 1e-6, 0.5),
                          ("source_half_angle_deg", 1e-3, 90.0), ("view_deg", 0.0, 80.0)):
            v = float(getattr(self, f))
            if not (lo <= v <= hi):
                raise ValueError(f"Observer.{f}: {v!r} is outside {lo:g}–{hi:g}")
        for a in self.light_deg:
            if not (0.0 <= float(a) < 89.0):
                raise ValueError(f"Observer.light_deg: {a!r} is outside 0–89°")


def person(distance_m: float, pupil_mm: float = 3.0, acuity_rad: float = ARCMIN_RAD) -> Observer:
    """A person at ``distance_m`` under the sun (module docstring).

    >>> p = person(1.0)                                  # 1 arcmin at 1 m; a 3 mm pupil seen from 1 m
    >>> round(p.spot_um, 1), round(p.aperture_half_angle_rad * 1e3, 4), round(person(3.0).spot_um / p.spot_um, 12)
    (290.9, 1.5000, 3.000000000000)
    """
    d_um = float(distance_m) * 1e6
    return Observer(
        name=f"person-{distance_m:g}m",
        spot_um=d_um * float(acuity_rad),
        aperture_half_angle_rad=float(np.arctan(0.5e3 * float(pupil_mm) / d_um)),
        source_half_angle_deg=SUN_HALF_ANGLE_DEG,
        description=f"a person at {distance_m:g} m in sunlight (pupil {pupil_mm:g} mm, 1 arcmin acuity)",
    )


BYK_MAC_LIKE = Observer(
    name="byk-mac-like", spot_um=15.0, aperture_half_angle_rad=float(np.radians(0.5)), source_half_angle_deg=1.0,
    description="BYK-mac-like camera: normal view, LED at 15/45/75 deg (assumed optics, not the instrument's)",
)

PRESETS = {o.name: o for o in (BYK_MAC_LIKE, person(1.0), person(3.0))}
