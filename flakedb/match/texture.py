"""Texture indices of a target (sparkle and graininess columns) against a recipe's predicted ones.

The columns (docs/texture.md §9, docs/colour-matching.md "Texture columns")
---------------------------------------------------------------------------
A target CSV may carry, beside its colour, the texture indices of the panel as measured by (or
predicted for) an observer of :mod:`flakedb.texture.instruments` (default ``byk-mac-like``; a
``# texture_observer: NAME`` option picks another preset):

* ``sparkle_area_<L>``: the sparkle area fraction at light angle L° (0 ≤ value ≤ 1),
* ``sparkle_intensity_<L>``: the sparkle intensity (a lit spot's mean excess luminance factor),
* ``glints_per_mm2_<L>``: expected glints per mm² of panel,
* ``graininess``: the graininess under a uniform sky (relative to the paint's BSDF luminance factor),

with the definitions of docs/texture.md §3.4 and §4 (the keys of
:func:`flakedb.texture.model.sparkle_indices` and :func:`~flakedb.texture.model.graininess_indices`).
L is any light polar angle in [0, 89)°; the view is the observer's (normal for the presets).  They are
per panel, not per geometry: the value is written on one row (the others left empty) or repeated.

Tolerance and residual
----------------------
An index k is within tolerance when |p_k − t_k| ≤ δ_k with δ_k = max(rel · |t_k|, floor_k): a
relative tolerance ``rel`` (default :data:`DEFAULT_TEXTURE_TOLERANCE`, 10 %) and an absolute floor per
index in its own units (:data:`TEXTURE_FLOORS`), so a target of zero has a usable tolerance.  The
residual is r_k = (p_k − t_k)/δ_k: |r_k| ≤ 1 passes.  These are policies, not visual thresholds:
the CIE preliminary scales (Ferrero et al. 2021) define visual sparkle and graininess from such
quantities through fitted functions that flakedb does not ship, so no published just-noticeable
difference is used (docs/texture.md §9 says why 10 %).

>>> tol = texture_tolerances({"sparkle_area_15": 0.002, "graininess": 0.0}, 0.1)
>>> [round(v, 6) for v in tol.values()]
[0.0002, 0.01]
>>> texture_residuals({"sparkle_area_15": 0.0021, "graininess": 0.005}, {"sparkle_area_15": 0.002, "graininess": 0.0}, 0.1).round(6).tolist()
[0.5, 0.5]
"""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np

from flakedb.paint.texture_inputs import texture_report
from flakedb.texture.instruments import PRESETS

#: Default relative tolerance of a texture index (docs/texture.md §9: the model's own agreement with the
#: discrete-flake simulation is "3σ + 10 %", so a tighter match is not meaningful).
DEFAULT_TEXTURE_TOLERANCE = 0.10
#: The observer preset of texture columns unless ``# texture_observer:`` says otherwise.
DEFAULT_TEXTURE_OBSERVER = "byk-mac-like"
#: Column stem → key of :func:`flakedb.texture.model.sparkle_indices` (per light angle).
SPARKLE_COLUMNS = {"sparkle_area": "sparkle_area_fraction", "sparkle_intensity": "sparkle_intensity",
                   "glints_per_mm2": "glints_per_mm2"}
#: Absolute floor of each index's tolerance, in its units (it matters only for targets near zero): an area
#: fraction of 1e-5 of the spots (about 4 of the 4.4e5 spots of a 1 cm² image of 15 µm spots), an
#: excess luminance factor of 1 (a white diffuser's), 0.01 glints per mm² (one in a 1 cm² image), a
#: graininess of 0.01.
TEXTURE_FLOORS = {"sparkle_area": 1e-5, "sparkle_intensity": 1.0, "glints_per_mm2": 0.01, "graininess": 0.01}
UNITS = {"sparkle_area": "fraction of spots", "sparkle_intensity": "luminance factor",
         "glints_per_mm2": "1/mm²", "graininess": "relative"}
_COLUMN = re.compile(r"^(sparkle_area|sparkle_intensity|glints_per_mm2)_(\d+(?:\.\d+)?)$")


def parse_texture_column(name):
    """(stem, light angle in degrees or None) of a texture column name, or None if it is not one.

    >>> parse_texture_column("sparkle_area_15"), parse_texture_column("graininess"), parse_texture_column("L*")
    (('sparkle_area', 15.0), ('graininess', None), None)
    """
    if name == "graininess":
        return "graininess", None
    m = _COLUMN.match(name)
    return (m.group(1), float(m.group(2))) if m else None


def check_texture_value(name, value) -> str | None:
    """A problem with a texture column's value (None when fine): finite, ≥ 0, an area fraction ≤ 1, a
    light angle in [0, 89)°."""
    stem, angle = parse_texture_column(name)
    if angle is not None and not (0.0 <= angle < 89.0):
        return f"column {name}: the light angle {angle:g}° must be in [0, 89)"
    if not (np.isfinite(value) and value >= 0.0):
        return f"column {name}: {value!r} must be a finite number >= 0"
    if stem == "sparkle_area" and value > 1.0:
        return f"column {name}: {value:g} is a fraction of spots, at most 1"
    return None


def texture_observer(names, preset=DEFAULT_TEXTURE_OBSERVER):
    """The observer that predicts columns ``names``: the preset with the columns' light angles."""
    if preset not in PRESETS:
        raise ValueError(f"texture_observer {preset!r}: use one of {', '.join(sorted(PRESETS))}")
    angles = sorted({a for a in (parse_texture_column(n)[1] for n in names) if a is not None})
    return replace(PRESETS[preset], light_deg=tuple(angles) if angles else PRESETS[preset].light_deg)


def columns_from_report(report, names) -> dict:
    """The values of columns ``names`` from a :func:`flakedb.paint.texture_inputs.texture_report` with
    one observer.  A paint without flakes (``report["sparkle"]`` False) predicts 0 for every index."""
    if not report["sparkle"]:
        return {n: 0.0 for n in names}
    (obs,) = report["observers"]
    by_angle = {float(r["light_deg"]): r for r in obs["directional"]}
    out = {}
    for n in names:
        stem, angle = parse_texture_column(n)
        v = obs["diffuse"]["graininess"] if stem == "graininess" else by_angle[angle][SPARKLE_COLUMNS[stem]]
        out[n] = None if v is None else float(v)   # None: outside the model (flakedb.texture.model.graininess_indices)
    return out


def predict_texture(recipe, names, preset=DEFAULT_TEXTURE_OBSERVER, ground=None):
    """(values of columns ``names``, the texture report) for ``recipe`` (:func:`columns_from_report`);
    ``ground``: the smooth BSDF's luminance factors (:func:`flakedb.appearance.report.texture_ground`), which
    graininess is relative to, as in ``compose``'s report."""
    rep = texture_report(recipe, [texture_observer(names, preset)], ground)
    return columns_from_report(rep, names), rep


def texture_tolerances(target, rel=DEFAULT_TEXTURE_TOLERANCE) -> dict:
    """δ_k = max(rel |t_k|, floor_k) per column of ``target`` (module docstring)."""
    return {n: max(float(rel) * abs(float(t)), TEXTURE_FLOORS[parse_texture_column(n)[0]]) for n, t in target.items()}


def texture_residuals(predicted, target, rel=DEFAULT_TEXTURE_TOLERANCE) -> np.ndarray:
    """r_k = (p_k − t_k)/δ_k in the order of ``target``'s columns."""
    tol = texture_tolerances(target, rel)
    return np.array([(float(predicted[n]) - float(t)) / tol[n] for n, t in target.items()])


def evaluate_texture(predicted, target, rel=DEFAULT_TEXTURE_TOLERANCE) -> list:
    """One dict per column: name, unit, predicted, target, difference, tolerance, residual, passed."""
    tol = texture_tolerances(target, rel)
    rows = []
    for n, t in target.items():
        if predicted[n] is None:  # the model has no number here (graininess of a thick, dense flake layer)
            rows.append({"index": n, "unit": UNITS[parse_texture_column(n)[0]], "predicted": None, "target": float(t),
                         "difference": None, "tolerance": tol[n], "residual": None, "passed": False})
            continue
        p = float(predicted[n])
        r = (p - float(t)) / tol[n]
        rows.append({"index": n, "unit": UNITS[parse_texture_column(n)[0]], "predicted": p, "target": float(t),
                     "difference": p - float(t), "tolerance": tol[n], "residual": r, "passed": bool(abs(r) <= 1.0)})
    return rows


def format_texture_rows(rows, sparkle=True) -> list:
    """The lines compare and match print for :func:`evaluate_texture` rows."""
    lines = [f"{'texture index':<22} {'predicted':>11} {'target':>11} {'difference':>11} {'tolerance':>10}  ok"]
    for r in rows:
        if r["predicted"] is None:
            lines.append(f"{r['index']:<22} {'n/a':>11} {r['target']:11.4g} {'':>11} {r['tolerance']:10.3g}  NO "
                         f"(not predicted: outside the texture model, docs/texture.md §4)")
            continue
        lines.append(f"{r['index']:<22} {r['predicted']:11.4g} {r['target']:11.4g} {r['difference']:+11.4g} "
                     f"{r['tolerance']:10.3g}  {'yes' if r['passed'] else 'NO'}")
    if not sparkle:
        lines.append("the recipe has no flakes the texture model can use (a pigment-only paint, or custom flakes without "
                     "a diameter): zero sparkle and "
                     "graininess predicted against the target's texture columns")
    return lines
