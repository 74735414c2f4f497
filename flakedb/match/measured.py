"""Measured BRDF files -> multi-angle targets: the one registry of the formats flakedb reads (docs/validation.md).

Each format knows its reader, how it is read at in-plane instrument geometries and what its licence lets
a user do with the numbers; :func:`measured_target` dispatches on the file's suffix, so every tool that
turns a measurement into a target (``tools/merl_target.py``, ``tools/validate_measured.py``) asks here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from flakedb.match.merl import MerlError, merl_target, read_merl
from flakedb.match.rgl import RglError, read_rgl, rgl_target

__all__ = ["MEASURED_FORMATS", "MeasuredError", "MeasuredFormat", "measured_format", "measured_target"]


class MeasuredError(ValueError):
    """A measured file flakedb cannot read (names the file, what is wrong and which suffixes are known)."""


@dataclass(frozen=True)
class MeasuredFormat:
    suffix: str
    what: str
    read: Callable          # path -> in-memory measurement
    target: Callable        # (measurement, geometries (G, 2) [deg]) -> (R (G, 3) linear sRGB, L*a*b* D65 / 2°)
    source: str
    licence: str
    redistributable: bool


MEASURED_FORMATS = {
    ".binary": MeasuredFormat(
        ".binary", "MERL BRDF database file", read_merl, merl_target,
        source="MERL BRDF database (Matusik, Pfister, Brand, McMillan, ACM TOG 22(3) 759-769, 2003); in-plane "
               "nearest-bin lookup, R = pi f_r, RGB read as linear sRGB (flakedb.match.merl)",
        licence="MERL database terms: research use, no redistribution; do not commit this file",
        redistributable=False),
    ".bsdf": MeasuredFormat(
        ".bsdf", "RGL material database file (tensor_file, RGB version)", read_rgl, rgl_target,
        source="RGL material database, EPFL (Dupuy & Jakob, ACM TOG 37(6) 274, 2018); evaluated as the reference "
               "powitacq BRDF::eval at in-plane geometries, R = pi f_r, linear sRGB (flakedb.match.rgl)",
        licence="CC0 1.0 (rgl.epfl.ch/pages/lab/material-database: 'Unless otherwise noted, all material data is "
                "licensed under the Creative Commons Zero (CC0) license')",
        redistributable=True),
}


def measured_format(path) -> MeasuredFormat:
    """The :class:`MeasuredFormat` of ``path`` by its suffix, or :class:`MeasuredError` listing the known ones."""
    suffix = Path(path).suffix.lower()
    if suffix not in MEASURED_FORMATS:
        known = ", ".join(f"{k} ({v.what})" for k, v in MEASURED_FORMATS.items())
        raise MeasuredError(f"{path}: unknown measured-BRDF suffix {suffix!r}; flakedb reads {known}")
    return MEASURED_FORMATS[suffix]


def measured_target(path, geometries_deg):
    """(R (G, 3), L*a*b* (G, 3) under D65 / 2°, notes {source, licence}) of the measured file at ``path`` at
    in-plane geometries (G, 2) (θ_i, aspecular) [deg]; :class:`MeasuredError` for a file that cannot be read
    or has no measured value at a geometry (named)."""
    fmt = measured_format(path)
    try:
        R, lab = fmt.target(fmt.read(path), np.asarray(geometries_deg, float))
    except (MerlError, RglError) as e:
        raise MeasuredError(str(e)) from None
    g = np.asarray(geometries_deg, float).reshape(-1, 2)
    if np.isnan(lab).any():
        bad = [f"{a:g}as{b:g}" for a, b in g[np.isnan(lab).any(axis=1)]]
        raise MeasuredError(f"{path}: no measured value at geometries {bad}")
    return R, lab, {"source": f"{fmt.source}; file {Path(path).name}", "licence": fmt.licence}
