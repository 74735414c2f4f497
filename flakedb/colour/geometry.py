"""Multi-angle measuring geometries, in plane and out of plane: angles ↔ directions ↔ names.

A geometry is ``(illumination_deg, aspecular_deg)`` (in the plane of incidence) or
``(illumination_deg, aspecular_deg, azimuth_deg)``; azimuth 0 is the in-plane geometry.

Frame (:mod:`flakedb.conventions`): z is the surface normal pointing out of the paint; the
illuminator's light travels along +x and down, propagation direction ``l = (sin θ_i, 0, −cos θ_i)``;
the specular direction is ``s = (sin θ_i, 0, cos θ_i)``; ``v`` is the view direction (from the panel
to the detector, the propagation direction of the measured light); ``y = z × x``.
With ``t = (−cos θ_i, 0, sin θ_i)``, the unit vector perpendicular to s in the plane of incidence
pointing towards the illuminator:

* **In plane** (azimuth 0; ASTM E2194's sign, :mod:`flakedb.colour.settings`): ``v = cos γ s + sin γ t``,
  i.e. the detector at θ_v = θ_i − γ from the normal, towards the illuminator for γ > 0.
* **Out of plane** (azimuth a ≠ 0; X-Rite's notation, e.g. ``45as25az90``): γ is the angle between v
  and s, a the rotation of v about s, measured from the in-plane direction *away* from the illuminator
  (−t), positive towards +y::

      v = cos γ s + sin γ (−cos a t + sin a y)

  Source: the geometry names and detector directions of X-Rite's cloud formulation software
  (github.com/StarNeit/bifrost_webapp, ``src/utils/colorimetry.ts`` and ``colorimetry.test.ts``,
  commit 3110643caacca371b32907c2e67d94f8f82c593d; names ``45as25az±90``, ``45as60az±125.3``,
  ``15as38.3az±43``, ``15as46.9az±104.5`` for two pairs of out-of-plane detectors at
  (0.640856, ±0.422618, 0.640856) and (0, ±0.7071, 0.7071) under 45° and 15° illumination, and the
  conversion "aspecular = angle of the view direction to the reflection direction, azimuth = rotation of
  the view direction around the reflection direction").  That the two formulas are those conventions is
  checked against every published vector ↔ name pair (tests/colour/test_geometry.py): the
  azimuth's origin on the far side of the specular is forced by the published 125.3° (the near side
  would give 54.7°).  Consequence of the notation, not of flakedb: an out-of-plane ``(γ, a → 0)``
  tends to the in-plane −γ and ``(γ, ±180°)`` is the in-plane +γ.

From v: ``mu_i = cos θ_i``, ``mu_o = −v_z`` (< 0: leaving the top), ``phi_d = |atan2(v_y, v_x)|``
(φ_d = 0 forward/mirror side, π back towards the illuminator; the BSDF of an isotropic stack is even
in φ_d, so ±a give the same value).  In plane this is :func:`flakedb.appearance.report.multiangle_geometry`.
"""

from __future__ import annotations

import numpy as np

#: Tolerance (degrees) under which an azimuth is 0 (in plane) when angles are recovered from vectors.
IN_PLANE_TOL_DEG = 1e-7


def as_geometry_array(geometries) -> np.ndarray:
    """(G, 3) float array ``(illumination_deg, aspecular_deg, azimuth_deg)`` of (G, 2) or (G, 3) geometries
    (a missing azimuth is 0: in plane).

    >>> as_geometry_array([(45, 15), (45, 25, 90)]).tolist()
    [[45.0, 15.0, 0.0], [45.0, 25.0, 90.0]]
    """
    if isinstance(geometries, (list, tuple)) and geometries and all(np.ndim(x) == 1 for x in geometries):
        # a list of 2- and 3-tuples (in and out of plane mixed): pad the azimuth
        geometries = [tuple(x) + (0.0,) * (3 - len(x)) if len(x) == 2 else x for x in geometries]
    g = np.asarray(geometries, float)
    if g.ndim == 1:
        g = g[None, :]
    if g.size == 0:
        return np.zeros((0, 3))
    if g.ndim != 2 or g.shape[1] not in (2, 3):
        raise ValueError(f"geometries of shape {g.shape}: expected (G, 2) (illumination, aspecular) or (G, 3) "
                         f"(illumination, aspecular, azimuth) in degrees")
    if g.shape[1] == 2:
        g = np.concatenate([g, np.zeros((g.shape[0], 1))], axis=1)
    return g


def compact(geometries) -> np.ndarray:
    """The geometries as (G, 2) when every azimuth is 0, else (G, 3): the form targets and reports keep."""
    g = as_geometry_array(geometries)
    return g[:, :2].copy() if not np.any(g[:, 2] != 0.0) else g


def key(geometry) -> tuple:
    """A hashable key of one geometry: ``(illumination, aspecular)`` in plane, ``(…, azimuth)`` out of plane,
    so an in-plane 2-tuple and its 3-tuple with azimuth 0 are the same key."""
    g = [float(v) for v in geometry]
    if len(g) == 3 and g[2] != 0.0:
        return (g[0], g[1], g[2])
    return (g[0], g[1])


def label(geometry) -> str:
    """The instruments' name of a geometry: ``45as15``, ``45as-15``, ``45as25az90``.

    >>> label((45, -15)), label((45.0, 25.0, 90.0)), label((15, 46.9, -104.5))
    ('45as-15', '45as25az90', '15as46.9az-104.5')
    """
    k = key(geometry)
    s = f"{k[0]:g}as{k[1]:g}"
    return s + (f"az{k[2]:g}" if len(k) == 3 else "")


def view_vector(illumination_deg, aspecular_deg, azimuth_deg=0.0) -> np.ndarray:
    """Unit view directions (..., 3) (from the panel to the detector, module docstring's frame) of geometries.

    Broadcasts its arguments.  In plane (azimuth 0): E2194's sign; out of plane: X-Rite's notation.

    >>> np.round(view_vector(45, 15), 6).tolist(), np.round(view_vector(45, 25, 90), 6).tolist()
    ([0.5, 0.0, 0.866025], [0.640856, 0.422618, 0.640856])
    """
    th, g, a = np.broadcast_arrays(*(np.radians(np.asarray(x, float)) for x in (illumination_deg, aspecular_deg,
                                                                                  azimuth_deg)))
    zero = np.zeros_like(th)
    s = np.stack([np.sin(th), zero, np.cos(th)], -1)
    t = np.stack([-np.cos(th), zero, np.sin(th)], -1)
    y = np.stack([zero, np.ones_like(th), zero], -1)
    in_plane = (a == 0.0)[..., None]
    side = np.where(in_plane, t, -np.cos(a)[..., None] * t + np.sin(a)[..., None] * y)
    return np.cos(g)[..., None] * s + np.sin(g)[..., None] * side


def directions(geometries):
    """``(mu_i, mu_o, phi_d, theta_view_deg)`` arrays (G,) of (G, 2) or (G, 3) geometries (module docstring).

    ``theta_view_deg``: in plane the signed θ_i − γ (E2194: negative on the illuminator's side); out of plane
    the detector's angle from the normal (≥ 0).  Raises ValueError naming the first geometry whose
    illumination is outside [0, 90)° or whose detector is not above the surface.

    >>> mu_i, mu_o, phi_d, tv = directions([(45, 110), (45, 25, 90)])
    >>> np.round(mu_o, 6).tolist(), np.round(phi_d, 6).tolist(), np.round(tv, 4).tolist()
    ([-0.422618, -0.640856], [3.141593, 0.582996], [-65.0, 50.1443])
    """
    g = as_geometry_array(geometries)
    check(g)
    v = view_vector(g[:, 0], g[:, 1], g[:, 2])
    mu_i = np.cos(np.radians(g[:, 0]))
    mu_o = -v[:, 2]
    phi_d = np.abs(np.arctan2(v[:, 1], v[:, 0]))
    in_plane = g[:, 2] == 0.0
    # in plane: μ_o = −cos|θ_i − γ| and φ_d exactly 0 or π, bit for bit as the in-plane evaluation always had them
    mu_o = np.where(in_plane, -np.cos(np.radians(np.abs(g[:, 0] - g[:, 1]))), mu_o)
    phi_d = np.where(in_plane, np.where(g[:, 0] - g[:, 1] >= 0.0, 0.0, np.pi), phi_d)
    theta_view = np.where(in_plane, g[:, 0] - g[:, 1], np.degrees(np.arccos(np.clip(v[:, 2], -1.0, 1.0))))
    return mu_i, mu_o, phi_d, theta_view


def problem(geometry) -> str | None:
    """What makes one geometry unmeasurable for flakedb (None when fine): the illumination outside [0, 90)°,
    the detector at or below the surface, or the detector on the specular direction (the smooth coat's mirror
    delta, which no colour geometry sees)."""
    th, asp, az = (float(x) for x in as_geometry_array(geometry)[0])
    if not (0.0 <= th < 90.0):
        return f"illumination_deg {th:g} must be in [0, 90)"
    if not (-180.0 <= az <= 180.0):
        return f"azimuth_deg {az:g} must be in [-180, 180]"
    vz = float(view_vector(th, asp, az)[2])
    if not vz > 1e-12:
        where = (f"{th - asp:g}° from the normal (must be within ±90°)" if az == 0.0
                 else f"{np.degrees(np.arccos(np.clip(vz, -1, 1))):.4g}° from the normal (must be below 90°)")
        return f"aspecular_deg {asp:g}" + (f", azimuth_deg {az:g}" if az else "") + f" puts the detector at {where}"
    if asp == 0.0:
        return "aspecular 0° is the specular direction (the smooth coat's mirror delta): not a colour geometry"
    return None


def check(geometries) -> None:
    """Raise ValueError naming the first geometry :func:`problem` refuses."""
    for g in as_geometry_array(geometries):
        p = problem(g)
        if p:
            raise ValueError(f"geometry {label(g)}: {p}")


def from_vectors(light_dir, view_dir):
    """``(illumination_deg, aspecular_deg, azimuth_deg)`` of an illumination *propagation* direction and a view
    direction, both in the panel's frame (z the normal out of the paint), any azimuth of the light; the inverse
    of :func:`view_vector` (azimuth 0 and E2194's signed aspecular when v lies in the plane of incidence).

    >>> [round(x, 1) for x in from_vectors([0.707106781, 0, -0.707106781], [0, 0.707, 0.707])]
    [45.0, 60.0, 125.3]
    """
    l = np.asarray(light_dir, float)
    l = l / np.linalg.norm(l)
    v = np.asarray(view_dir, float)
    v = v / np.linalg.norm(v)
    # rotate about z so that the light travels along +x
    phi_l = np.arctan2(l[1], l[0]) if np.hypot(l[0], l[1]) > 0 else 0.0
    c, s_ = np.cos(-phi_l), np.sin(-phi_l)
    v = np.array([c * v[0] - s_ * v[1], s_ * v[0] + c * v[1], v[2]])
    th = float(np.degrees(np.arccos(np.clip(-l[2], -1.0, 1.0))))
    tr = np.radians(th)
    s = np.array([np.sin(tr), 0.0, np.cos(tr)])
    t = np.array([-np.cos(tr), 0.0, np.sin(tr)])
    gamma = float(np.degrees(np.arccos(np.clip(v @ s, -1.0, 1.0))))
    a = float(np.degrees(np.arctan2(v[1], -(v @ t))))
    if abs(v[1]) < np.sin(np.radians(IN_PLANE_TOL_DEG)):   # in the plane of incidence: E2194's signed aspecular
        return th, (gamma if v @ t >= 0.0 else -gamma), 0.0
    return th, gamma, a


def cells(geometry) -> str:
    """The illumination and aspecular columns of the text tables (``   45°    15°``), and ``az90°`` after them
    for an out-of-plane geometry."""
    k = key(geometry)
    return f"{k[0]:5g}° {k[1]:5g}°" + (f" az{k[2]:g}°" if len(k) == 3 else "")
