"""resolution: auto meets its accuracy targets (issue 12; docs/resolution.md).

Guards against: an auto n that misses the stated albedo accuracy of a rough coat over a scattering
slab; a rough coat whose auto n breaks the white furnace.  Only order 0 is solved (the albedo is
order 0 exactly: the adding method does not mix Fourier orders), which keeps the tests fast.
"""

import numpy as np
import pytest
import yaml
from scipy.interpolate import CubicSpline

from flakedb.paint.mapping import auto_resolution, build_paint, solve_paint
from flakedb.paint.recipe import parse_recipe


def _recipe(alpha, slab=True, primer=0.5):
    layers = [{"clearcoat": {"thickness_um": 40, "ior": 1.5, "roughness": alpha}}]
    if slab:
        layers.append({"basecoat": {"thickness_um": 10, "ior": 1.5, "particles": [
            {"custom": {"kind": "medium", "name": "hg", "albedo": 0.9, "phase": {"hg": 0.7}}, "optical_depth": 1.0}]}})
    layers.append({"primer": {"albedo": primer}})
    return parse_recipe(yaml.safe_dump({"flakedb": 1, "name": "t", "spectral": {"mode": "mono"},
                                        "resolution": "auto", "layers": layers}))


def _albedo(paint, n, mu):
    st = solve_paint(paint, n, max_orders=1)
    return CubicSpline(st.x, st.albedo()[0])(mu)


def test_auto_rough_coat_hg_slab_diffuse_albedo_within_one_percent():
    r = _recipe(0.02)
    n, why = auto_resolution(r)
    assert n <= 512 and "rough coat" in why
    paint = build_paint(r)
    mu = np.cos(np.radians(np.linspace(0.0, 80.0, 17)))
    a, ref = _albedo(paint, n, mu), _albedo(paint, 384 if n < 384 else 512, mu)
    assert np.abs(a / ref - 1.0).max() <= 0.01


@pytest.mark.parametrize("alpha", [0.01, 0.02, 0.05, 0.1, 0.3])
def test_auto_rough_coat_white_furnace(alpha):
    r = _recipe(alpha, slab=False, primer=1.0)
    n, _ = auto_resolution(r)
    st = solve_paint(build_paint(r), n, max_orders=1)
    sel = st.x >= np.cos(np.radians(80.0))
    assert np.abs(st.albedo()[0][sel] - 1.0).max() <= 1e-3
