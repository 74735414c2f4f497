"""Shared helpers of the texture tests: recipes with varied flakes, the model's inputs handed to the
independent simulation as plain arrays (data only: the simulation calls no model code)."""

from __future__ import annotations

import numpy as np

from flakedb.paint.recipe import parse_recipe
from flakedb.paint.texture_inputs import texture_stack
from flakedb.texture.instruments import Observer

RECIPE = """
flakedb: 1
name: {name}
spectral: {{mode: spectral, range_nm: [400, 700], step_nm: 20}}
layers:
  - clearcoat: {{thickness_um: 30, ior: 1.5, roughness: 0}}
  - basecoat:
      thickness_um: {d}
      ior: 1.5
      particles:
        - {{species: {species}, volume_fraction: {vf}, orientation_alpha: {alpha}, diameter_um: {D}, diameter_gsd: {gsd}}}
{pigment}  - primer: {{color: gray}}
"""
PIGMENT = "        - {{species: {p}, volume_fraction: {pv}}}\n"


def recipe(name="case", species="metallic", vf=0.02, alpha=0.2, D=20.0, gsd=1.3, d=15.0, pigment=None, pv=0.05,
           distribution=None):
    pig = PIGMENT.format(p=pigment, pv=pv) if pigment else ""
    text = RECIPE.format(name=name, species=species, vf=vf, alpha=alpha, D=D, gsd=gsd, d=d, pigment=pig)
    if distribution:
        text = text.replace(f"diameter_gsd: {gsd}}}", f"diameter_gsd: {gsd}, orientation_distribution: {distribution}}}")
    return parse_recipe(text, source=name)


#: An observer with a wide source and aperture, so that a few mm² of simulated panel hold hundreds of glints.
TEST_OBSERVER = Observer(name="test", spot_um=20.0, aperture_half_angle_rad=float(np.radians(2.0)),
                         source_half_angle_deg=4.0, light_deg=(15.0, 30.0), view_deg=0.0)


def sim_inputs(stack):
    """The model's inputs as the simulation's plain dicts and arrays."""
    species = [dict(z_top_um=f.z_top_um, thickness_um=f.thickness_um, number_density_per_um3=f.number_density_per_um3,
                    diameter_median_um=f.diameter_median_um, diameter_gsd=f.diameter_gsd, alpha=f.alpha,
                    c=np.asarray(f.c), R=np.asarray(f.R), T=np.asarray(f.T)) for f in stack.flakes]
    absorbers = [dict(z_top_um=a.z_top_um, thickness_um=a.thickness_um, sigma_per_um=np.asarray(a.sigma_per_um))
                 for a in stack.absorbers]
    return species, absorbers


def stack_of(**kw):
    return texture_stack(recipe(**kw))[0]
