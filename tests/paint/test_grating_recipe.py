"""Grating (diffractive) flakes in recipes and the catalogue (issue 35 step 2): the ``grating`` of a catalogue flake
and a recipe's grating_period_nm / grating_amplitude_nm reach the solver as flakedb.rt.scattering.grating_flake's
medium; with no grooves the paint is the plain flake's; user errors name the field, the value and the fix; the
store leaves grating flakes to compose."""

import numpy as np
import pytest
import yaml

from flakedb.colour.colorimetry import delta_E_2000
from flakedb.paint.catalog import is_stored, load_catalog
from flakedb.paint.recipe import parse_recipe
from flakedb.paint.recipe_model import RecipeError
from flakedb.pipelines.build import make_request
from flakedb.rt.scattering.grating_flake import GratingFlakeMedium
from flakedb.solve.pipeline import solve_reported

N = 8


def _doc(particle, mode="spectral"):
    return {"flakedb": 1, "name": "grating", "resolution": N,
            "spectral": {"mode": mode, "range_nm": [500, 600], "step_nm": 20},
            "layers": [{"clearcoat": {"thickness_um": 30, "ior": 1.5, "roughness": 0}},
                       {"basecoat": {"thickness_um": 10, "ior": 1.5, "particles": [
                           {"volume_fraction": 0.02, **particle}]}},
                       {"primer": {"albedo": 0.02}}]}


def _recipe(particle, mode="spectral"):
    return parse_recipe(yaml.safe_dump(_doc(particle, mode)), source="<grating>")


def _lab(rep):
    return np.array([[g["L"], g["a"], g["b"]] for g in rep.report["geometries"]])


def test_the_catalogue_grating_flake_reaches_the_solver_and_is_not_stored():
    entry = load_catalog()["particles"]["holographic-aluminium"]
    assert not is_stored(entry) and is_stored(load_catalog()["particles"]["metallic"])
    rep = solve_reported(_recipe({"species": "holographic-aluminium"}), N, verify=False)
    med = next(iter(rep.solved.paint.media.values()))
    assert isinstance(med, GratingFlakeMedium)
    assert (med.period_nm, med.amplitude_nm) == (690.0, 50.0)
    np.testing.assert_array_equal(med.wavelength_nm, [500.0, 520.0, 540.0, 560.0, 580.0, 600.0])
    with pytest.raises(ValueError, match="with a grating is computed directly by compose"):
        make_request(species=["holographic-aluminium"], n=16)


@pytest.mark.slow
def test_without_grooves_the_paint_is_the_plain_flakes_and_the_grooves_colour_it():
    # amplitude 0: every order but the mirror carries nothing, the kernel is kernel_Ergun's (tests/rt): the same
    # paint as the species with no grating, through the same solver (f to the projection's tolerance 1e-5)
    plain = solve_reported(_recipe({"species": "aluminium-vmp"}), N, verify=False)
    flat = solve_reported(_recipe({"species": "aluminium-vmp", "grating_period_nm": 690,
                                   "grating_amplitude_nm": 0}), N, verify=False)
    phi = np.linspace(0, np.pi, 5)
    fp, ff = plain.solved.stack.eval_nodes(phi), flat.solved.stack.eval_nodes(phi)
    assert float(np.abs(ff - fp).max() / np.abs(fp).max()) < 1e-4
    assert float(delta_E_2000(_lab(flat), _lab(plain)).max()) < 0.01
    grooved = solve_reported(_recipe({"species": "aluminium-vmp", "grating_period_nm": 690,
                                      "grating_amplitude_nm": 50}), N, verify=False)
    assert float(delta_E_2000(_lab(grooved), _lab(plain)).max()) > 5.0


@pytest.mark.parametrize("particle,mode,needle", [
    ({"species": "metallic", "grating_period_nm": 690}, "spectral",
     "grating_amplitude_nm: missing; 'metallic' has no grating, so embossing it needs both"),
    ({"species": "holographic-aluminium"}, "rgb", "grating (diffractive) flake"),
    ({"species": "titanium-white", "grating_period_nm": 690, "grating_amplitude_nm": 40}, "spectral",
     "grating_period_nm: 'titanium-white' is a pigment"),
    ({"species": "metallic", "grating_period_nm": 100, "grating_amplitude_nm": 40}, "spectral",
     "grating_period_nm"),
    ({"species": "metallic", "grating_period_nm": 690, "grating_amplitude_nm": 500}, "spectral",
     "grating_amplitude_nm"),
])
def test_recipe_errors_name_the_field_and_the_fix(particle, mode, needle):
    with pytest.raises(RecipeError) as exc:
        _recipe(particle, mode)
    text = str(exc.value)
    assert needle in text, text
    assert "layers[1].basecoat.particles[0]" in text


def test_a_recipe_field_overrides_the_catalogue_grating():
    r = _recipe({"species": "holographic-aluminium", "grating_period_nm": 574})
    p = next(p for _, p in r.particles())
    assert p.entry["grating"]["period_nm"]["value"] == 574.0 and p.entry["grating"]["amplitude_nm"]["value"] == 50
    assert p.grating_overrides == {"grating_period_nm": 574}
