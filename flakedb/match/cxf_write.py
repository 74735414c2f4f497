"""Multi-angle predictions written as CxF3 files (ISO 17972-1 / X-Rite CxF 3.0 core schema).

Usage: ``format_cxf(geometries, lab, reflectance, wavelength_nm, observer, illuminant, name)`` → bytes;
:func:`write_cxf` writes them atomically (:func:`flakedb.atomic.atomic_write`).  ``flakedb compare
RECIPE --write-cxf FILE`` is the command (docs/colour-matching.md, "CxF3 output").

The layout is the one :mod:`flakedb.match.cxf` reads without ambiguity, in the element order of the
schema's sequences (``CxF3_Core.xsd`` 3.0.018):

* ``FileInformation`` (``Creator``, ``CreationDate``, ``Description``);
* one ``Object`` (``ObjectType="Standard"``, ``Name`` the recipe's name) whose ``ColorValues`` hold, per
  geometry, a ``ReflectanceSpectrum`` (spectral predictions; 1.0 = 100 %, every value written with 17
  significant digits so it reads back bit for bit) and a ``ColorCIELab``, each with ``Name`` = the
  geometry's notation (``45as15``) and naming that geometry's colour specification;
* one ``ColorSpecification`` per geometry (``Id`` ``MA_45as15``): ``TristimulusSpec`` (the conditions of
  the CIELab values: ``Illuminant``, ``Observer`` ``2_Degree`` / ``10_Degree``, ``Method`` ``E308_1nm``,
  the closest of the schema's choices to flakedb's CIE 15:2004 sum on ≤ 1 nm nodes after Sprague
  interpolation), ``MeasurementSpec`` (``MeasurementType`` ``Spectrum_Reflectance``, or
  ``Colorimetric_Reflectance`` for an RGB-mode paint, which has no spectrum; ``GeometryChoice/MultiAngle``
  with one ``BRDFAngle`` of ``IlluminationAngle`` and ``Aspecular`` in ASTM E2194's sign, and an ``Azimuth``
  for an out-of-plane geometry (X-Rite's notation, :mod:`flakedb.colour.geometry`), as read;
  ``WavelengthRange`` ``StartWL`` / ``Increment``).

What the schema cannot hold is refused (ValueError naming the value and the limit), never written
out of range: a grid starting outside 360–400 nm or not on whole nm (``StartWLType``), a step other
than 1, 2, 5, 10 or 20 nm (``reflectance_list``), a reflectance factor outside (−0.1, 3)
(``ReflectanceDataType``), an L* < 0, an illuminant outside the schema's ``EIlluminantType``.
"""

from __future__ import annotations

import datetime as _dt
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from flakedb import __version__
from flakedb.atomic import atomic_write
from flakedb.colour.geometry import as_geometry_array
from flakedb.colour.geometry import label as geometry_label
from flakedb.colour.tolerance import observer_name
from flakedb.match.cxf import INCREMENTS, NS

#: flakedb observer → CxF3 ``EObserverType``.
OBSERVERS = {"2": "2_Degree", "10": "10_Degree"}
#: CxF3 ``EIlluminantType`` values that name a CIE illuminant colour-science tabulates.
ILLUMINANTS = ("A", "B", "C", "D50", "D55", "D60", "D65", "D75", "E", "F2", "F3", "F7", "F9", "F10", "F11", "F12")
#: ``ReflectanceDataType``: minExclusive −0.1, maxExclusive 3.0.
REFLECTANCE_RANGE = (-0.1, 3.0)
#: ``StartWLType``: a short between 360 and 400 inclusive.
START_WL_RANGE = (360, 400)


def _q(tag: str) -> str:
    return f"{{{NS}}}{tag}"


def notation(geometry) -> str:
    """``45as15``, ``15as-45``, ``45as25az90`` (the multi-angle notation of the reader and the CSV layout).

    >>> notation((45.0, 15.0)), notation((15, -45)), notation((45.0, 110.0)), notation((45.0, 60.0, -125.3))
    ('45as15', '15as-45', '45as110', '45as60az-125.3')
    """
    return geometry_label(geometry)


def _cxf_illuminant(illuminant) -> str:
    name = str(illuminant).strip().upper()
    name = "F" + name[2:] if name.startswith("FL") else name
    if name not in ILLUMINANTS:
        raise ValueError(f"illuminant {illuminant!r} has no CxF3 Illuminant value (the schema's are "
                         f"{', '.join(ILLUMINANTS)}): compare under one of them (--illuminant D65)")
    return name


def _observer(observer) -> str:
    observer_name(observer)   # the one check of an observer's name (ValueError with the choices)
    key = str(observer).strip().lower().replace("deg", "").replace("°", "").strip()
    return OBSERVERS[key[:-2] if key.endswith(".0") else key]


def _num(v) -> str:
    return format(float(v), ".17g")


def format_cxf(geometries, lab, reflectance=None, wavelength_nm=None, observer="10", illuminant="D65", name="",
               description="", created=None) -> bytes:
    """The CxF3 document (UTF-8 bytes) of one object's multi-angle colour (module docstring).

    ``geometries`` (G, 2): (illumination_deg, aspecular_deg), or (G, 3) with an azimuth; ``lab`` (G, 3): CIELAB under ``observer`` /
    ``illuminant``; ``reflectance`` (G, W) reflectance factors on ``wavelength_nm`` (W,) nm, or None (an
    RGB-mode paint: CIELab only).  ``created``: a timezone-aware datetime (default: now, UTC).
    Raises ValueError for what the schema cannot hold (module docstring).
    """
    g = as_geometry_array(geometries)
    lab = np.asarray(lab, float).reshape(-1, 3)
    if lab.shape[0] != g.shape[0]:
        raise ValueError(f"{g.shape[0]} geometries but {lab.shape[0]} CIELab values")
    if np.any(lab[:, 0] < 0) or not np.all(np.isfinite(lab)):
        raise ValueError("CIELab values must be finite with L* >= 0 (CxF3 ColorCIELab)")
    obs, ill = _observer(observer), _cxf_illuminant(illuminant)
    R = None
    if reflectance is not None:
        R = np.asarray(reflectance, float).reshape(g.shape[0], -1)
        wl = np.asarray(wavelength_nm, float)
        step = (wl[-1] - wl[0]) / (wl.size - 1) if wl.size > 1 else 0.0
        start = wl[0]
        if start != round(start) or not START_WL_RANGE[0] <= start <= START_WL_RANGE[1]:
            raise ValueError(f"the spectral grid starts at {start:g} nm; a CxF3 WavelengthRange starts on a whole nm "
                             f"from {START_WL_RANGE[0]} to {START_WL_RANGE[1]} (spectral: range_nm: [400, ...] in the "
                             f"recipe)")
        if wl.size != R.shape[1] or step not in INCREMENTS or not np.allclose(np.diff(wl), step, rtol=0, atol=1e-9):
            raise ValueError(f"the spectral grid's step is {step:g} nm; CxF3 reflectance lists are at 1, 2, 5, 10 or "
                             f"20 nm (spectral: step_nm in the recipe)")
        lo, hi = REFLECTANCE_RANGE
        bad = np.argwhere(~((R > lo) & (R < hi)))
        if bad.size:
            i, j = bad[0]
            raise ValueError(f"reflectance factor {R[i, j]:.4g} at {notation(g[i])}, {wl[j]:g} nm is outside CxF3's "
                             f"range ({lo:g}, {hi:g}) (ReflectanceDataType): not written")
    ET.register_namespace("cc", NS)
    root = ET.Element(_q("CxF"))
    info = ET.SubElement(root, _q("FileInformation"))
    ET.SubElement(info, _q("Creator")).text = f"flakedb {__version__}"
    created = created or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0)
    ET.SubElement(info, _q("CreationDate")).text = created.isoformat()
    if description:
        ET.SubElement(info, _q("Description")).text = str(description)
    res = ET.SubElement(root, _q("Resources"))
    objects = ET.SubElement(res, _q("ObjectCollection"))
    obj = ET.SubElement(objects, _q("Object"), {"ObjectType": "Standard", "Name": str(name or "prediction"),
                                                  "Id": "flakedb-prediction"})
    ET.SubElement(obj, _q("CreationDate")).text = created.isoformat()
    values = ET.SubElement(obj, _q("ColorValues"))
    specs = ET.SubElement(res, _q("ColorSpecificationCollection"))
    for i, geo in enumerate(g):
        nt = notation(geo)
        sid = f"MA_{nt}"
        if R is not None:
            ET.SubElement(values, _q("ReflectanceSpectrum"), {"Name": nt, "StartWL": str(int(start)),
                                                              "ColorSpecification": sid}).text = \
                " ".join(_num(v) for v in R[i])
        cl = ET.SubElement(values, _q("ColorCIELab"), {"Name": nt, "ColorSpecification": sid})
        for k, v in zip(("L", "A", "B"), lab[i]):
            ET.SubElement(cl, _q(k)).text = _num(v)
        cs = ET.SubElement(specs, _q("ColorSpecification"), {"Id": sid})
        ts = ET.SubElement(cs, _q("TristimulusSpec"))
        ET.SubElement(ts, _q("Illuminant")).text = ill
        ET.SubElement(ts, _q("Observer")).text = obs
        ET.SubElement(ts, _q("Method")).text = "E308_1nm"
        ms = ET.SubElement(cs, _q("MeasurementSpec"))
        ET.SubElement(ms, _q("MeasurementType")).text = ("Spectrum_Reflectance" if R is not None
                                                         else "Colorimetric_Reflectance")
        ba = ET.SubElement(ET.SubElement(ET.SubElement(ms, _q("GeometryChoice")), _q("MultiAngle")), _q("BRDFAngle"),
                           {"Notation": nt})
        ET.SubElement(ba, _q("IlluminationAngle")).text = _num(geo[0])
        ET.SubElement(ba, _q("Aspecular")).text = _num(geo[1])
        if geo[2] != 0.0:   # out of plane (X-Rite's notation, as read)
            ET.SubElement(ba, _q("Azimuth")).text = _num(geo[2])
        if R is not None:
            ET.SubElement(ms, _q("WavelengthRange"), {"StartWL": str(int(start)), "Increment": f"{step:g}"})
    ET.indent(root)
    return ET.tostring(root, encoding="UTF-8", xml_declaration=True) + b"\n"


def write_cxf(path, *args, **kwargs) -> str:
    """Write :func:`format_cxf`'s document to ``path`` atomically (nothing half-written); returns the path."""
    data = format_cxf(*args, **kwargs)
    atomic_write(Path(path), lambda tmp: Path(tmp).write_bytes(data))
    return str(path)
