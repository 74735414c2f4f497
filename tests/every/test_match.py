"""Every catalogue species as a free parameter of `flakedb match` (issue #35): its loading (and an interference
flake's film thicknesses, which the catalogue says are fittable) fitted to a target made from the same recipe at
another loading.  The Jacobian match takes is finite, no parameter is reported undetermined, the fit's first steps
lower the worst ΔE00, and the reported sensitivities (forward differences, 1e-3 in ln p) agree with central
differences of independent predict calls to 2 % of their largest entry: the truncation of a forward difference
is (h/2)·p·f''/f', measured ≤ 0.72 % (colour-shift-cr-mgf2-al's MgF2 spacer); a flake table re-adapted between
evaluations (noise at its 1e-4 tolerance, divided by the 1e-3 step) would be far outside.

Guards against: a species that match cannot vary (a tinter or an override the prediction drops), a NaN in the
prediction at some geometry, a film thickness whose table jumps as it moves (a Jacobian the fit cannot use).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from flakedb.match.fit import match, predict, recipe_from_doc, substitute
from flakedb.match.targets import Target
from tests.every.cases import SLOW_SPECIES, SPECIES, SWEEP_MEMBERS, coatings, document, particle, species_params

#: E2194-like in-plane geometries at 45° illumination (aspecular −15°, 15°, 45°, 110°).
GEOMETRIES = np.array([[45.0, -15.0], [45.0, 15.0], [45.0, 45.0], [45.0, 110.0]])
START, TRUE = 0.02, 0.03
#: Forward against central differences (module docstring).
FD_REL = 0.02


def _base(species, films):
    doc = document([particle(species)], name=f"every-match-{species}")
    target_doc = copy.deepcopy(doc)
    target_doc["layers"][1]["basecoat"]["particles"][0]["volume_fraction"] = TRUE
    target = Target(geometries=GEOMETRIES, lab=predict(recipe_from_doc(target_doc), GEOMETRIES).lab())
    p = doc["layers"][1]["basecoat"]["particles"][0]
    p["volume_fraction"] = {"fit": [0.005, 0.05], "start": START}
    if films:
        p["coating_thickness_nm"] = [{"fit": [0.8 * float(c["thickness_nm"]["value"]),
                                              1.2 * float(c["thickness_nm"]["value"])]} for c in coatings(species)]
    return doc, target


def _check(species, films):
    doc, target = _base(species, films)
    res = match(doc, target, max_nfev=2, de_tol=0)
    S = res.sensitivities
    assert S.shape == (len(GEOMETRIES), 3, 1 + (len(coatings(species)) if films else 0))
    assert np.all(np.isfinite(S)) and np.all(np.isfinite(res.lab_fit))
    assert res.undetermined == []
    assert res.de_fit.max() < res.de_start.max()
    for j, p in enumerate(res.params):
        h = 1e-3 * res.values[j] if p.log else 1e-3 * (p.hi - p.lo)
        lab = []
        for s in (1.0, -1.0):
            v = res.values.copy()
            v[j] += s * h
            lab.append(predict(recipe_from_doc(substitute(doc, res.params, v)), GEOMETRIES, n=res.n).lab())
        central = (lab[0] - lab[1]) / (2 * h)
        err = np.abs(central - S[:, :, j]).max() / np.abs(central).max()
        assert err <= FD_REL, (p.name, err)


@pytest.mark.parametrize("species", species_params())
def test_every_species_loading_is_a_free_parameter(species):
    _check(species, films=False)


@pytest.mark.slow
@pytest.mark.parametrize("species", [s for s in SPECIES if coatings(s) and s not in SWEEP_MEMBERS])
def test_every_film_thickness_is_a_free_parameter(species):
    """Every catalogue film structure; a sweep member (the base's films at another thickness) is its base's case."""
    _check(species, films=True)


def test_film_thickness_is_a_free_parameter_fast():
    """The fast tier's film case: the first catalogue flake with two films (the slow sweep takes every one)."""
    _check(next(s for s in SPECIES if len(coatings(s)) >= 2 and s not in SLOW_SPECIES), films=True)
