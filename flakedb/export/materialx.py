"""The fitted material as a MaterialX document: an ``open_pbr_surface`` node (MaterialX 1.39 standard
library, OpenPBR Surface 1.1) and a ``surfacematerial``.  Written as plain XML (no MaterialX needed to
write); the tests validate it with the ``materialx`` package.  The fit (parameters and error,
:class:`flakedb.export.openpbr.OpenPBRFit`) is stored as JSON in the document's ``flakedb_fit``
attribute, which ``flakedb info`` reads."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from flakedb.atomic import atomic_path
from flakedb.export.openpbr import OpenPBRFit

#: MaterialX version of the written document (open_pbr_surface is in its standard library).
MTLX_VERSION = "1.39"


def safe_name(name: str) -> str:
    """A MaterialX / USD identifier from a file stem: letters, digits and ``_``, not starting with a digit."""
    s = re.sub(r"[^A-Za-z0-9_]", "_", str(name)) or "paint"
    return s if not s[0].isdigit() else "_" + s


def openpbr_inputs(fit: OpenPBRFit) -> list:
    """(name, type, value) of the ``open_pbr_surface`` inputs the fit sets (the rest keep their defaults)."""
    c = fit.base_color
    return [
        ("base_weight", "float", 1.0),
        ("base_color", "color3", f"{c[0]:.6g}, {c[1]:.6g}, {c[2]:.6g}"),
        ("base_metalness", "float", fit.base_metalness),
        ("specular_weight", "float", 1.0),
        ("specular_color", "color3", ", ".join(f"{x:.6g}" for x in fit.specular_color)),
        ("specular_roughness", "float", fit.specular_roughness),
        ("specular_ior", "float", fit.specular_ior),       # relative to the coat: specular_ior_relative
        ("coat_weight", "float", 1.0 if fit.coat_ior > 1.0 else 0.0),
        ("coat_roughness", "float", fit.coat_roughness),
        ("coat_ior", "float", fit.coat_ior),
        ("coat_color", "color3", "1, 1, 1"),
        # no darkening: the fitted base already holds the paint's interreflections under the coat, and
        # the fit's model has none (OpenPBR 1.1, Coat / Darkening: at 0 the base is only albedo-scaled;
        # MaterialX's open_pbr_surface otherwise multiplies it by (1 - K) / (1 - E_base K))
        ("coat_darkening", "float", 0.0),
        ("thin_film_weight", "float", 1.0 if fit.thin_film_thickness_nm > 0 else 0.0),
        ("thin_film_thickness", "float", fit.thin_film_thickness_nm / 1000.0),   # micrometres
        ("thin_film_ior", "float", fit.thin_film_ior),
    ]


def mtlx_text(fit: OpenPBRFit, name: str) -> str:
    """The ``.mtlx`` document of ``fit`` (module docstring)."""
    n = safe_name(name)
    root = ET.Element("materialx", {"version": MTLX_VERSION, "colorspace": "lin_rec709",
                                    "flakedb_fit": json.dumps(fit.to_dict(), separators=(",", ":"))})
    sh = ET.SubElement(root, "open_pbr_surface", {"name": f"SR_{n}", "type": "surfaceshader"})
    for k, t, v in openpbr_inputs(fit):
        ET.SubElement(sh, "input", {"name": k, "type": t, "value": v if isinstance(v, str) else f"{float(v):.6g}"})
    m = ET.SubElement(root, "surfacematerial", {"name": f"M_{n}", "type": "material"})
    ET.SubElement(m, "input", {"name": "surfaceshader", "type": "surfaceshader", "nodename": f"SR_{n}"})
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_mtlx(path, fit: OpenPBRFit, name: str) -> Path:
    path = Path(path)
    with atomic_path(path, suffix="") as tmp:
        Path(tmp).write_text(mtlx_text(fit, name), encoding="utf-8")
    return path


def read_fit(path) -> dict:
    """The fit JSON stored in a ``.mtlx`` written by :func:`write_mtlx` (ValueError if absent).

    A round trip through a file (plain XML: no ``materialx`` package needed):

    >>> import tempfile
    >>> fit = OpenPBRFit((0.8, 0.5, 0.2), 1.0, 0.3, 1.5, 0.0, thin_film_thickness_nm=300.0, thin_film_ior=2.0)
    >>> path = write_mtlx(Path(tempfile.mkdtemp()) / "silver.mtlx", fit, "1 silver")
    >>> OpenPBRFit.from_dict(read_fit(path)) == fit, ET.parse(path).getroot().find("open_pbr_surface").get("name")
    (True, 'SR__1_silver')
    """
    root = ET.parse(path).getroot()
    if root.tag != "materialx":
        raise ValueError(f"{path}: not a MaterialX document (root <{root.tag}>)")
    s = root.get("flakedb_fit")
    if s is None:
        raise ValueError(f"{path}: a MaterialX document without flakedb's fit (not written by flakedb export-openpbr)")
    return json.loads(s)
