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


def cpa_mtlx_text(image_file: str, scales, alphas, coat_ior: float, n_table: int, name: str, fit_json: str = "{}") -> str:
    """The angle-indexed material of :mod:`flakedb.export.cpa` as a MaterialX 1.39 graph of standard
    nodes: μ_v = -``normal``·``viewdirection`` (world space), texture coordinate
    ``(μ_v (n - 1) / n + 0.5 / n, (k + 0.5) / rows)`` into ``image_file`` (the colour table, 16-bit
    PNG, ``lin_rec709``, linear filtering, clamped), each row times its ``scales[k]``; row 0 colours an
    ``oren_nayar_diffuse_bsdf`` of roughness 0 (Lambert), row k a ``generalized_schlick_bsdf`` (GGX,
    ``color0 = color90`` = the row's colour: no Fresnel variation) of roughness α_k (MaterialX's
    ``roughness`` is α itself), all summed by ``add`` with the coat's mirror, a smooth
    ``dielectric_bsdf`` of index ``coat_ior`` in reflection only; a ``surface`` and a
    ``surfacematerial``.  The sum is ``add``, not ``layer``: the table already holds the coat's
    transmission.  Plain XML (no MaterialX needed to write); the fit as JSON in ``flakedb_cpa``."""
    n = safe_name(name)
    rows = len(scales)
    root = ET.Element("materialx", {"version": MTLX_VERSION, "colorspace": "lin_rec709", "flakedb_cpa": fit_json})

    def node(kind, nname, typ, **inputs):
        e = ET.SubElement(root, kind, {"name": nname, "type": typ})
        for k, (t, v) in inputs.items():
            if isinstance(v, tuple) and v[0] == "node":
                ET.SubElement(e, "input", {"name": k, "type": t, "nodename": v[1]})
            else:
                ET.SubElement(e, "input", {"name": k, "type": t, "value": v})
        return e

    node("normal", "N_world", "vector3", space=("string", "world"))
    node("viewdirection", "V_world", "vector3", space=("string", "world"))
    node("dotproduct", "NdotI", "float", in1=("vector3", ("node", "N_world")), in2=("vector3", ("node", "V_world")))
    node("multiply", "u_scaled", "float", in1=("float", ("node", "NdotI")), in2=("float", f"{-(n_table - 1) / n_table:.9g}"))
    node("add", "u", "float", in1=("float", ("node", "u_scaled")), in2=("float", f"{0.5 / n_table:.9g}"))
    total = None
    for k in range(rows):
        node("combine2", f"uv_{k}", "vector2", in1=("float", ("node", "u")), in2=("float", f"{(k + 0.5) / rows:.9g}"))
        img = node("image", f"table_{k}", "color3", texcoord=("vector2", ("node", f"uv_{k}")),
                   filtertype=("string", "linear"), uaddressmode=("string", "clamp"), vaddressmode=("string", "clamp"))
        f = ET.SubElement(img, "input", {"name": "file", "type": "filename", "value": image_file,
                                         "colorspace": "lin_rec709"})
        del f
        node("multiply", f"colour_{k}", "color3", in1=("color3", ("node", f"table_{k}")), in2=("float", f"{float(scales[k]):.9g}"))
        if k == 0:
            node("oren_nayar_diffuse_bsdf", "lobe_0", "BSDF", color=("color3", ("node", "colour_0")), roughness=("float", "0"))
        else:
            a = float(alphas[k - 1])
            node("generalized_schlick_bsdf", f"lobe_{k}", "BSDF", color0=("color3", ("node", f"colour_{k}")),
                 color90=("color3", ("node", f"colour_{k}")), roughness=("vector2", f"{a:.9g}, {a:.9g}"),
                 distribution=("string", "ggx"))
        if total is None:
            total = f"lobe_{k}"
        else:
            node("add", f"sum_{k}", "BSDF", in1=("BSDF", ("node", total)), in2=("BSDF", ("node", f"lobe_{k}")))
            total = f"sum_{k}"
    if coat_ior > 1.0:
        node("dielectric_bsdf", "coat", "BSDF", ior=("float", f"{float(coat_ior):.9g}"), roughness=("vector2", "0, 0"),
             scatter_mode=("string", "R"))
        node("add", "sum_coat", "BSDF", in1=("BSDF", ("node", total)), in2=("BSDF", ("node", "coat")))
        total = "sum_coat"
    node("surface", f"SR_{n}", "surfaceshader", bsdf=("BSDF", ("node", total)))
    m = ET.SubElement(root, "surfacematerial", {"name": f"M_{n}", "type": "material"})
    ET.SubElement(m, "input", {"name": "surfaceshader", "type": "surfaceshader", "nodename": f"SR_{n}"})
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def write_cpa_mtlx(path, image_file: str, scales, alphas, coat_ior: float, n_table: int, name: str,
                   fit_json: str = "{}") -> Path:
    path = Path(path)
    with atomic_path(path, suffix="") as tmp:
        Path(tmp).write_text(cpa_mtlx_text(image_file, scales, alphas, coat_ior, n_table, name, fit_json), encoding="utf-8")
    return path
