"""Multi-angle geometries in and out of plane (flakedb.colour.geometry, the set "xrite19").

Guards against: an out-of-plane convention that is not the instruments' (the azimuth measured from the wrong
in-plane side, or about the normal instead of the specular direction, or a sign flipped), which gives other
directions for the same name; out-of-plane angles whose directions disagree with the published detector
vectors; an in-plane geometry whose directions change when it gains an explicit azimuth 0; and geometries
accepted whose detector is at or below the surface or on the specular delta.

Published pairs: X-Rite's cloud formulation software (github.com/StarNeit/bifrost_webapp,
src/utils/colorimetry.test.ts, commit 3110643caacca371b32907c2e67d94f8f82c593d): illumination propagation
direction → detector direction → (illumination, aspecular, azimuth), the names rounded to 0.1°.
"""

import numpy as np
import pytest

from flakedb.appearance.report import multiangle_geometry
from flakedb.colour.geometry import (
    as_geometry_array,
    compact,
    directions,
    from_vectors,
    key,
    label,
    problem,
    view_vector,
)
from flakedb.colour.settings import (
    E2539_GEOMETRIES,
    GEOMETRY_SETS,
    OUT_OF_PLANE_GEOMETRIES,
    XRITE19_GEOMETRIES,
    resolve,
)

L45 = (0.707106781186547, 0.0, -0.707106781186547)
L15 = (0.258819045102521, 0.0, -0.965925826289068)
#: (illumination propagation direction, detector direction, published (illumination, aspecular, azimuth)).
PUBLISHED = [
    (L45, (-0.906307787036650, 0, 0.422618261740700), (45, 110, 0)),
    (L45, (0.5, 0, 0.866025403784439), (45, 15, 0)),
    (L45, (0.866025403784439, 0, 0.5), (45, -15, 0)),
    (L45, (0.713151411403254, -0.410064693213191, 0.568561352708323), (45, 25, -76)),
    (L45, (0.859789397188856, 0.066987298107781, 0.506236006595582), (45, 15, 15)),
    (L15, (0.000255605307491, -0.706904885203488, 0.707308573354918), (15, 46.9, -104.5)),
]
#: The instrument's two out-of-plane detector pairs (the test's "from carthesian" case) and their names.
DETECTORS = {"A": (0.640856, 0.422618, 0.640856), "-A": (0.640856, -0.422618, 0.640856),
             "B": (0, 0.707, 0.707), "-B": (0, -0.707, 0.707)}
NAMES = {(L45, "A"): "45as25az90", (L45, "-A"): "45as25az-90", (L45, "B"): "45as60az125.3",
         (L45, "-B"): "45as60az-125.3", (L15, "A"): "15as38.3az43", (L15, "-A"): "15as38.3az-43",
         (L15, "B"): "15as46.9az104.5", (L15, "-B"): "15as46.9az-104.5"}


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("light, det, angles", PUBLISHED)
def test_published_vectors_give_the_published_angles(light, det, angles):
    got = from_vectors(light, det)
    np.testing.assert_allclose(got, angles, atol=0.05)   # the published values are rounded (to 1° or 0.1°)
    # and the angles give back the detector direction (to the rounding of the published angles)
    cos = float(view_vector(*angles) @ _unit(det))
    assert np.degrees(np.arccos(min(cos, 1.0))) < 0.1


@pytest.mark.parametrize("which", list(NAMES))
def test_detector_names(which):
    light, d = which
    th, asp, az = from_vectors(light, DETECTORS[d])
    assert label((round(th, 1), round(asp, 1), round(az, 1))) == NAMES[which]


def test_the_out_of_plane_set_is_the_two_detector_pairs_under_both_illuminators():
    """Each named geometry of the set points at one of the published detectors (to 0.1°, the names' rounding),
    and the same detector is named under both illuminators."""
    by_name = {label(g): g for g in OUT_OF_PLANE_GEOMETRIES}
    assert set(by_name) == set(NAMES.values())
    for (light, d), name in NAMES.items():
        v = view_vector(*by_name[name])
        assert np.degrees(np.arccos(min(float(v @ _unit(DETECTORS[d])), 1.0))) < 0.1, name
        assert np.isclose(by_name[name][0], 45.0 if light == L45 else 15.0)
    assert XRITE19_GEOMETRIES[:11] == tuple(g + (0.0,) for g in E2539_GEOMETRIES)
    assert GEOMETRY_SETS["xrite19"] == XRITE19_GEOMETRIES and len(resolve(geometry_set="xrite19").geometries) == 19


def test_in_plane_geometries_are_the_e2194_directions_with_or_without_an_azimuth():
    g2 = np.asarray(E2539_GEOMETRIES)
    mu_i, mu_o, phi_d, tv = directions(g2)
    ref = np.array([multiangle_geometry(a, i) for i, a in g2])
    np.testing.assert_array_equal(np.stack([mu_i, mu_o, phi_d, tv], 1), ref)
    np.testing.assert_array_equal(np.stack(directions(as_geometry_array(g2)), 1), ref)
    assert compact(as_geometry_array(g2)).shape == g2.shape and key((45, 15, 0)) == key((45, 15)) == (45.0, 15.0)


def test_directions_of_an_out_of_plane_geometry():
    """μ_o and φ_d of the view vector in the frame of flakedb.conventions (propagation directions, the light along
    +x), and both signs of the azimuth the same directions up to the mirror plane (an isotropic BSDF's φ_d ≥ 0)."""
    rng = np.random.default_rng(7)
    th = rng.uniform(0, 80, 50)
    asp = rng.uniform(5, 70, 50)
    az = rng.uniform(-179, 179, 50)
    v = view_vector(th, asp, az)
    keep = v[:, 2] > 0.02
    g = np.stack([th, asp, az], 1)[keep]
    v = v[keep]
    mu_i, mu_o, phi_d, tv = directions(g)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, rtol=1e-15)
    np.testing.assert_allclose(mu_o, -v[:, 2], rtol=1e-15)
    np.testing.assert_allclose(np.cos(phi_d), v[:, 0] / np.hypot(v[:, 0], v[:, 1]), atol=1e-12)
    np.testing.assert_allclose(mu_i, np.cos(np.radians(g[:, 0])), rtol=1e-15)
    # γ is the angle to the specular direction
    s = np.stack([np.sin(np.radians(g[:, 0])), 0 * g[:, 0], np.cos(np.radians(g[:, 0]))], 1)
    np.testing.assert_allclose(np.degrees(np.arccos(np.clip(np.sum(v * s, 1), -1, 1))), g[:, 1], atol=1e-6)
    mirrored = g * [1, 1, -1]
    np.testing.assert_allclose(np.stack(directions(mirrored)), np.stack(directions(g)), atol=1e-14)
    # round trip through the vectors
    back = np.array([from_vectors((np.sin(np.radians(t)), 0, -np.cos(np.radians(t))), vv) for t, vv in zip(g[:, 0], v)])
    np.testing.assert_allclose(back, g, atol=1e-8)


def test_the_azimuth_tends_to_the_other_side_of_the_specular():
    """X-Rite's notation measures the azimuth from the in-plane direction away from the illuminator: az → 0 is the
    in-plane −γ, ±180° the in-plane +γ (module docstring)."""
    np.testing.assert_allclose(view_vector(45, 25, 1e-9), view_vector(45, -25), atol=1e-9)
    np.testing.assert_allclose(view_vector(45, 25, 180.0), view_vector(45, 25), atol=1e-12)


@pytest.mark.parametrize("geometry, message", [
    ((45, 100, 90), "puts the detector at 97.05° from the normal"),
    ((45, 140), "puts the detector at -95° from the normal"),
    ((45, 0, 90), "specular direction"),
    ((90, 15), "illumination_deg 90 must be in"),
    ((45, 25, 200), "azimuth_deg 200 must be in"),
])
def test_unmeasurable_geometries_are_named(geometry, message):
    assert message in problem(geometry)
    with pytest.raises(ValueError, match=label(geometry)):
        directions([geometry])


def test_measurable_set_geometries_pass():
    assert all(problem(g) is None for g in XRITE19_GEOMETRIES)
