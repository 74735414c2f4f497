"""Multi-angle colour targets from CxF3 files (ISO 17972-1 / X-Rite CxF 3.0 core schema).

What is read (docs/colour-matching.md, section "CxF3"; the element names are the schema's,
``CxF3_Core.xsd`` 3.0.018, namespace ``http://colorexchangeformat.com/CxF3-core``)
---------------------------------------------------------------------------------------------
* ``Resources/ColorSpecificationCollection/ColorSpecification[@Id]``: its
  ``MeasurementSpec/GeometryChoice/MultiAngle/BRDFAngle[@Notation]`` elements give the geometries
  (``IlluminationAngle``, ``Aspecular`` and, out of plane, a non-zero ``Azimuth``, read in X-Rite's
  notation, e.g. ``45as25az90``: :mod:`flakedb.colour.geometry`), ``MeasurementSpec/WavelengthRange[@StartWL, @Increment]`` the
  spectral grid, and ``TristimulusSpec/Illuminant`` / ``Observer`` (``2_Degree`` / ``10_Degree``)
  the conditions of any CIELab values.
* ``Resources/ObjectCollection/Object``: its ``ColorValues`` hold ``ReflectanceSpectrum`` (a
  whitespace-separated list, 1.0 = 100 %, from ``@StartWL`` or the specification's, at its
  ``@Increment``) and/or ``ColorCIELab`` (``L``, ``A``, ``B``), each naming its
  ``@ColorSpecification``.
* **Which geometry a value belongs to.**  The schema ties a value to a colour specification, not
  to one of several ``BRDFAngle`` elements inside it.  flakedb therefore reads (a) a specification
  with one ``BRDFAngle``: every value naming it is at that geometry; (b) a specification with
  several: a value's ``@Name`` must equal one ``BRDFAngle/@Notation`` (e.g. ``45as15``).  Anything
  else is refused with a message, not guessed.
* **Sign of the aspecular angle**: the schema does not state one; the angle is read with ASTM
  E2194's sign (positive towards the illuminator, as in the ``45as110`` notation), the sign of the
  CSV layout (:mod:`flakedb.match.targets`).

One object is one target: the object named by ``object_name`` (its ``@Name`` or ``@Id``), or the
only object that has multi-angle values.  Spectra, when every geometry has one, are what is
compared (any observer and illuminant); CIELab values are used only when there are no spectra.
**Observer and illuminant**: the conditions a spectral target is compared under are the caller's
when given, else those its specifications' ``TristimulusSpec`` state (a 10° file is compared at
10°), else the defaults of :mod:`flakedb.colour.settings` (recorded in ``notes['assumed']``).
The result is the same :class:`flakedb.match.targets.Target` the CSV reader returns.

Parsing uses the standard library's expat parser (no DTD loading, no external entities; expat
≥ 2.4 refuses entity-expansion bombs), after a size check (:data:`MAX_BYTES`).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from flakedb.colour.geometry import compact
from flakedb.colour.geometry import key as geometry_key
from flakedb.colour.geometry import label as geometry_label
from flakedb.colour.settings import DEFAULT_ILLUMINANT, DEFAULT_OBSERVER
from flakedb.colour.tolerance import illuminant_name, observer_name, reflectance_to_Lab
from flakedb.match.targets import Target, TargetError, check_measured, read_target, validate_geometries
from flakedb.safeio import FileTooLargeError, read_limited

#: The CxF3 core namespace.
NS = "http://colorexchangeformat.com/CxF3-core"
#: Largest CxF file read (bytes); multi-angle targets are a few hundred kB at most.
MAX_BYTES = 64 * 1024 * 1024
#: CxF3 observer names → flakedb's.
OBSERVERS = {"2_Degree": "2", "10_Degree": "10"}
#: CxF3 ``reflectance_list`` increments allowed by the schema (nm).
INCREMENTS = (1, 2, 5, 10, 20)


def _q(tag: str) -> str:
    return f"{{{NS}}}{tag}"


def _float(text, what, where) -> float:
    try:
        v = float(str(text).strip())
    except (TypeError, ValueError):
        raise TargetError(f"{where}: {what} {text!r} is not a number") from None
    if not np.isfinite(v):
        raise TargetError(f"{where}: {what} {text!r} is not a finite number")
    return v


def _short(text, limit=80) -> str:
    """``repr(text)`` cut to ``limit`` characters (a name in a message, never a 900 kB one)."""
    r = repr(text)
    return r if len(r) <= limit else r[:limit - 4] + "...'"


def _specifications(root, where) -> dict:
    """Id → {'angles': {notation: (illum, aspec[, azimuth])}, 'start', 'increment', 'observer', 'illuminant'}."""
    specs = {}
    for cs in root.iter(_q("ColorSpecification")):
        sid = cs.get("Id")
        if sid is None:
            continue  # a ColorSpecification *reference* element elsewhere has no Id
        w = f"{where}: ColorSpecification {sid}"
        if sid in specs:
            raise TargetError(f"{w}: two ColorSpecifications have Id {_short(sid)}; an Id names one "
                              f"specification (the schema's xs:ID), so a value naming it is ambiguous: give each "
                              f"its own Id")
        angles = {}
        for b in cs.iter(_q("BRDFAngle")):
            notation = b.get("Notation")
            if notation is None:
                raise TargetError(f"{w}: a BRDFAngle has no Notation attribute (the schema requires one)")
            az = 0.0
            if b.find(_q("Azimuth")) is not None:
                az = _float(b.findtext(_q("Azimuth")), f"BRDFAngle {notation} Azimuth", w)
            th = _float(b.findtext(_q("IlluminationAngle")), f"BRDFAngle {notation} IlluminationAngle", w)
            asp = _float(b.findtext(_q("Aspecular")), f"BRDFAngle {notation} Aspecular", w)
            angles[notation] = geometry_key((th, asp, az))   # (th, asp) in plane, (th, asp, az) out of plane
        wr = cs.find(f"{_q('MeasurementSpec')}/{_q('WavelengthRange')}")
        start = inc = None
        if wr is not None:
            start = _float(wr.get("StartWL"), "WavelengthRange StartWL", w)
            inc = _float(wr.get("Increment"), "WavelengthRange Increment", w)
        ts = cs.find(_q("TristimulusSpec"))
        obs = ill = None
        if ts is not None:
            o = (ts.findtext(_q("Observer")) or "").strip()
            obs = OBSERVERS.get(o, o or None)
            ill = (ts.findtext(_q("Illuminant")) or "").strip() or None
        specs[sid] = {"angles": angles, "start": start, "increment": inc, "observer": obs, "illuminant": ill}
    return specs


def _geometry(value, spec, sid, where):
    angles = spec["angles"]
    if len(angles) == 1:
        return next(iter(angles.values()))
    name = value.get("Name")
    if name in angles:
        return angles[name]
    raise TargetError(f"{where}: a {value.tag.split('}')[1]} names ColorSpecification {sid}, which lists "
                      f"{len(angles)} BRDFAngles ({', '.join(angles)}), but its Name {name!r} is none of their "
                      f"Notations; give the value Name=\"<Notation>\" (or one BRDFAngle per ColorSpecification)")


def read_cxf_target(path_or_bytes, object_name=None, observer=None, illuminant=None, source=None) -> Target:
    """Read one object's multi-angle colour from a CxF3 file (module docstring) as a :class:`Target`.

    ``path_or_bytes``: a path, or the file's bytes.  ``object_name``: the object's Name or Id (needed
    when several objects have multi-angle values).  ``observer`` / ``illuminant``: the conditions a
    spectral target is compared under (as :func:`flakedb.match.targets.read_target`).

    What is not CxF3 is refused in one line:

    >>> read_cxf_target(b"<root/>")
    Traceback (most recent call last):
    ...
    flakedb.match.targets.TargetError: <cxf>: the root element is 'root', not CxF in the CxF3 namespace http://colorexchangeformat.com/CxF3-core (CxF/X-4 and CxF3 files only)
    >>> read_cxf_target(b"<x")
    Traceback (most recent call last):
    ...
    flakedb.match.targets.TargetError: <cxf>: not a readable CxF3 (XML) file: ...
    """
    if isinstance(path_or_bytes, (bytes, bytearray)):
        data, where = bytes(path_or_bytes), source or "<cxf>"
    else:
        p = Path(path_or_bytes)
        where = source or str(p)
        try:   # a regular file only (no FIFO / device), never more than the limit read
            data = read_limited(p, MAX_BYTES)
        except FileNotFoundError:
            raise TargetError(f"{where}: no such file") from None
        except FileTooLargeError as exc:
            raise TargetError(f"{where}: {exc.size:,} bytes is more than the limit of {MAX_BYTES:,} for a CxF "
                              f"target") from None
        except OSError as exc:
            raise TargetError(f"{where}: cannot read the file ({exc.strerror or exc})") from None
    if len(data) > MAX_BYTES:
        raise TargetError(f"{where}: {len(data):,} bytes is more than the limit of {MAX_BYTES:,} for a CxF target")
    if re.search(rb"<!(DOCTYPE|ENTITY)", data, re.IGNORECASE):
        raise TargetError(f"{where}: has a DOCTYPE / ENTITY declaration; CxF3 files have none and flakedb refuses "
                          f"them (entity expansion, external entities)")
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise TargetError(f"{where}: not a readable CxF3 (XML) file: {exc}") from None
    if root.tag != _q("CxF"):
        raise TargetError(f"{where}: the root element is {root.tag!r}, not CxF in the CxF3 namespace {NS} "
                          f"(CxF/X-4 and CxF3 files only)")
    specs = _specifications(root, where)
    multi = {sid for sid, s in specs.items() if s["angles"]}
    candidates = []
    for obj in root.iter(_q("Object")):
        cv = obj.find(_q("ColorValues"))
        values = [] if cv is None else [v for v in cv if v.get("ColorSpecification") in multi
                                        and v.tag in (_q("ReflectanceSpectrum"), _q("ColorCIELab"))]
        if values:
            candidates.append((obj, values))
    ids = [o.get("Id") for o in root.iter(_q("Object")) if o.get("Id") is not None]
    seen_ids = set()
    dup = next((i for i in ids if i in seen_ids or seen_ids.add(i)), None)
    if dup is not None:
        raise TargetError(f"{where}: two Objects have Id {_short(dup)}; an Id names one object (the schema's xs:ID): "
                          f"give each its own Id")
    if not candidates:
        raise TargetError(f"{where}: no object has ReflectanceSpectrum or ColorCIELab values under a multi-angle "
                          f"ColorSpecification (MeasurementSpec/GeometryChoice/MultiAngle)")
    if object_name is None:
        if len(candidates) > 1:
            names = ", ".join(_short(o.get("Name") or o.get("Id")) for o, _ in candidates[:8])
            raise TargetError(f"{where}: {len(candidates)} objects have multi-angle values ({names}); choose one "
                              f"with --cxf-object NAME")
        obj, values = candidates[0]
    else:
        hits = [(o, v) for o, v in candidates if object_name == o.get("Id")]
        hits = hits or [(o, v) for o, v in candidates if object_name == o.get("Name")]
        if not hits:
            names = ", ".join(_short(o.get("Name") or o.get("Id")) for o, _ in candidates[:8])
            raise TargetError(f"{where}: no object named {_short(object_name)} with multi-angle values (have: {names})")
        if len(hits) > 1:
            ids_ = ", ".join(_short(o.get("Id")) for o, _ in hits[:8])
            raise TargetError(f"{where}: {len(hits)} objects are named {_short(object_name)} (Ids {ids_}); "
                              f"choose one by its Id with --cxf-object ID")
        obj, values = hits[0]
    oname = obj.get("Name") or obj.get("Id") or ""
    w = f"{where}: object {oname!r}"
    spectra, labs, lab_cond = {}, {}, set()
    grids = set()
    for v in values:
        sid = v.get("ColorSpecification")
        spec = specs[sid]
        g = _geometry(v, spec, sid, w)
        if v.tag == _q("ReflectanceSpectrum"):
            start = v.get("StartWL")
            start = _float(start, "ReflectanceSpectrum StartWL", w) if start is not None else spec["start"]
            inc = spec["increment"]
            if start is None or inc is None:
                raise TargetError(f"{w}: ColorSpecification {sid} has no MeasurementSpec/WavelengthRange "
                                  f"(StartWL, Increment): the spectrum's wavelengths are unknown")
            if inc not in INCREMENTS:
                raise TargetError(f"{w}: WavelengthRange Increment {inc:g} nm; the schema allows 1, 2, 5, 10 or 20")
            try:
                r = np.array([float(x) for x in (v.text or "").split()])
            except ValueError:
                raise TargetError(f"{w}: a ReflectanceSpectrum value is not a number") from None
            if r.size < 2 or not np.all(np.isfinite(r)):
                raise TargetError(f"{w}: a ReflectanceSpectrum needs ≥ 2 finite values (got {r.size})")
            if g in spectra:
                raise TargetError(f"{w}: two spectra at geometry {geometry_label(g)}")
            spectra[g] = r
            grids.add((start, inc, r.size))
        else:
            lab = [_float(v.findtext(_q(k)), k, w) for k in ("L", "A", "B")]
            if g in labs:
                raise TargetError(f"{w}: two CIELab values at geometry {geometry_label(g)}")
            labs[g] = lab
            lab_cond.add((spec["observer"], spec["illuminant"]))
    if spectra:
        if len(grids) != 1:
            raise TargetError(f"{w}: the spectra are on {len(grids)} different wavelength grids; one grid is needed")
        geoms = list(spectra)
        start, inc, nw = grids.pop()
        wl = start + inc * np.arange(nw)
        R = np.stack([spectra[g] for g in geoms])
        # the file's TristimulusSpec (of the spectra's specifications) is honoured unless the caller chooses
        spec_cond = {(specs[v.get("ColorSpecification")]["observer"], specs[v.get("ColorSpecification")]["illuminant"])
                     for v in values if v.tag == _q("ReflectanceSpectrum")}
        f_obs = {o for o, _ in spec_cond if o is not None}
        f_ill = {i for _, i in spec_cond if i is not None}
        if observer is None and len(f_obs) > 1 or illuminant is None and len(f_ill) > 1:
            raise TargetError(f"{w}: the spectra's ColorSpecifications state different observers / illuminants "
                              f"({sorted(f_obs)} / {sorted(f_ill)}); choose one with --observer / --illuminant")
        obs = str(observer) if observer is not None else (f_obs.pop() if f_obs else DEFAULT_OBSERVER)
        ill = str(illuminant) if illuminant is not None else (f_ill.pop() if f_ill else DEFAULT_ILLUMINANT)
        notes = {"cxf_object": oname}
        if observer is None and not spec_cond - {(None, None)}:
            notes["assumed"] = (f"observer {obs} deg / illuminant {ill} (no TristimulusSpec in the file: the "
                                f"defaults, flakedb.colour.settings)")
        if labs:
            notes["cxf_lab"] = "CIELab values in the file not used (the spectra are)"
    else:
        if len(lab_cond) != 1:
            raise TargetError(f"{w}: the CIELab values use {len(lab_cond)} different TristimulusSpecs; one is needed")
        obs, ill = lab_cond.pop()
        if obs is None or ill is None:
            raise TargetError(f"{w}: CIELab values without TristimulusSpec Observer and Illuminant (their conditions "
                              f"are unknown); add them, or give spectra")
        geoms, R, wl = list(labs), None, None
        notes = {"cxf_object": oname}
    try:
        observer_name(obs), illuminant_name(ill)
    except ValueError as exc:
        raise TargetError(f"{w}: {exc}") from None
    g_arr = compact([tuple(g) + (0.0,) * (3 - len(g)) for g in geoms])
    validate_geometries(g_arr, w)
    t = Target(geometries=g_arr, observer=obs, illuminant=ill, name=oname, notes=notes, source=where)
    if R is not None:
        try:
            reflectance_to_Lab(R[:1], wl, obs, ill)
        except ValueError as exc:
            raise TargetError(f"{w}: reflectance grid: {exc}") from None
        check_measured(f"{w} ReflectanceSpectrum", g_arr, reflectance=R, wavelength_nm=wl)
        t.reflectance, t.wavelength_nm = R, wl
    else:
        t.lab = np.asarray([labs[g] for g in geoms], float)
        check_measured(f"{w} ColorCIELab", g_arr, lab=t.lab)
    return t


def load_target(path, observer=None, illuminant=None, object_name=None) -> Target:
    """A target from a CSV (:func:`flakedb.match.targets.read_target`) or, for ``*.cxf``, a CxF3 file."""
    if str(path).lower().endswith(".cxf"):
        return read_cxf_target(path, object_name, observer, illuminant)
    if object_name is not None:
        raise TargetError(f"--cxf-object {object_name}: only a .cxf target has objects ({path} is read as CSV)")
    return read_target(Path(path), observer, illuminant)   # a Path: never taken for CSV text (a name with a newline)
