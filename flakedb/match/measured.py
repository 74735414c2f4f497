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
from flakedb.match.rgl import RglError, read_rgl, rgl_spectral_target, rgl_target

__all__ = ["MEASURED_FORMATS", "MeasuredError", "MeasuredFormat", "MeasuredTarget", "measured_format",
           "measured_target"]


class MeasuredError(ValueError):
    """A measured file flakedb cannot read (names the file, what is wrong and which suffixes are known)."""


@dataclass(frozen=True)
class MeasuredTarget:
    """A measurement read at geometries: L*a*b* (D65 / 2°) for an RGB measurement, or spectral reflectance
    factors (G, W) on ``wavelength_nm`` for a spectral one (the target is then compared under any observer and
    illuminant); ``notes`` {source, licence} go into the target file."""

    lab: np.ndarray | None
    reflectance: np.ndarray | None
    wavelength_nm: np.ndarray | None
    notes: dict


def _rgl_read_at(brdf, geometries):
    """An RGB file gives L*a*b*; a spectral file, spectra (flakedb.match.rgl)."""
    if brdf.wavelengths_nm is None:
        return MeasuredTarget(rgl_target(brdf, geometries)[1], None, None, {})
    R, wl = rgl_spectral_target(brdf, geometries)
    return MeasuredTarget(None, R, wl, {})


def _merl_read_at(table, geometries):
    return MeasuredTarget(merl_target(table, geometries)[1], None, None, {})


@dataclass(frozen=True)
class MeasuredFormat:
    suffix: str
    what: str
    read: Callable          # path -> in-memory measurement
    read_at: Callable       # (measurement, geometries (G, 2) [deg]) -> MeasuredTarget
    source: str
    licence: str
    redistributable: bool


MEASURED_FORMATS = {
    ".binary": MeasuredFormat(
        ".binary", "MERL BRDF database file", read_merl, _merl_read_at,
        source="MERL BRDF database (Matusik, Pfister, Brand, McMillan, ACM TOG 22(3) 759-769, 2003); in-plane "
               "nearest-bin lookup, R = pi f_r, RGB read as linear sRGB (flakedb.match.merl)",
        licence="MERL database terms: research use, no redistribution; do not commit this file",
        redistributable=False),
    ".bsdf": MeasuredFormat(
        ".bsdf", "RGL material database file (tensor_file, RGB or spectral version)", read_rgl, _rgl_read_at,
        source="RGL material database, EPFL (Dupuy & Jakob, ACM TOG 37(6) 274, 2018); evaluated as the reference "
               "powitacq BRDF::eval at in-plane geometries, R = pi f_r, linear sRGB or spectra (flakedb.match.rgl)",
        licence="CC0 1.0 (rgl.epfl.ch/pages/lab/material-database: 'Unless otherwise noted, all material data is "
                "licensed under the Creative Commons Zero (CC0) license')",
        redistributable=True),
}


def measured_format(path) -> MeasuredFormat:
    """The :class:`MeasuredFormat` of ``path`` by its suffix, or :class:`MeasuredError` listing the known ones.

    >>> sorted(MEASURED_FORMATS) == sorted({measured_format("a" + k) is MEASURED_FORMATS[k] and k for k in MEASURED_FORMATS})
    True
    >>> try:
    ...     measured_format("paint.txt")
    ... except MeasuredError as e:
    ...     print(str(e).split(";")[0])
    paint.txt: unknown measured-BRDF suffix '.txt'
    """
    suffix = Path(path).suffix.lower()
    if suffix not in MEASURED_FORMATS:
        known = ", ".join(f"{k} ({v.what})" for k, v in MEASURED_FORMATS.items())
        raise MeasuredError(f"{path}: unknown measured-BRDF suffix {suffix!r}; flakedb reads {known}")
    return MEASURED_FORMATS[suffix]


def measured_target(path, geometries_deg) -> MeasuredTarget:
    """The measured file at ``path`` read at in-plane geometries (G, 2) (θ_i, aspecular) [deg] as a
    :class:`MeasuredTarget` with its source and licence; :class:`MeasuredError` for a file that cannot be read
    or has no measured value at a geometry (named)."""
    fmt = measured_format(path)
    g = np.asarray(geometries_deg, float).reshape(-1, 2)
    try:
        m = fmt.read_at(fmt.read(path), g)
    except (MerlError, RglError) as e:
        raise MeasuredError(str(e)) from None
    vals = m.lab if m.lab is not None else m.reflectance
    if np.isnan(vals).any():
        bad = [f"{a:g}as{b:g}" for a, b in g[np.isnan(vals).any(axis=1)]]
        raise MeasuredError(f"{path}: no measured value at geometries {bad}")
    return MeasuredTarget(m.lab, m.reflectance, m.wavelength_nm,
                          {"source": f"{fmt.source}; file {Path(path).name}", "licence": fmt.licence})
