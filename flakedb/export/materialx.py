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
from flakedb.safeio import FileTooLargeError, read_limited

#: MaterialX version of the written document (open_pbr_surface is in its standard library).
MTLX_VERSION = "1.39"


#: The colour table's 16-bit value q = round(65535 p) is carried in two 8-bit planes, q = 256 hi + lo, so that
#: an 8-bit loader (MaterialX's StbImageLoader reads a 16-bit PNG's high byte only) reads all 16 bits; a texture
#: read returns hi / 255 and lo / 255, and p = PLANE_WEIGHTS[0] hi/255 + PLANE_WEIGHTS[1] lo/255 exactly: linear,
#: so a bilinear filter of the planes is the filter of p
#: (:func:`flakedb.export.cpa.table_planes`).
PLANE_WEIGHTS = (256.0 * 255.0 / 65535.0, 255.0 / 65535.0)


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
    kind, fit = read_mtlx_fit(path)
    if kind != "openpbr":
        raise ValueError(f"{path}: a flakedb {kind} MaterialX document, not an export-openpbr fit")
    return fit


#: Root attribute of a flakedb MaterialX document -> the export that writes it.
FIT_ATTRIBUTES = {"flakedb_fit": "openpbr", "flakedb_cpa": "cpa"}
#: Largest MaterialX document :func:`read_mtlx_fit` reads (export-cpa's, glint layer included, are ~30 kB).
MTLX_MAX_BYTES = 4 << 20


def _refuse_constant(name):
    """json.loads' hook for NaN / Infinity, which flakedb never writes into a fit."""
    raise ValueError(f"{name} is not a number a fit holds")


def read_mtlx_fit(path) -> tuple[str, dict]:
    """(kind, fit JSON) of a ``.mtlx`` written by ``flakedb export-openpbr`` (kind ``"openpbr"``, :func:`write_mtlx`)
    or ``flakedb export-cpa`` (``"cpa"``, :func:`cpa_mtlx_text`); ValueError naming the file otherwise.

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "x.cpa.mtlx"
    >>> _ = path.write_text(cpa_mtlx_text("x.cpa.png", [1.0, 1.0], [0.2], 1.5, 8, "x", '{"alphas": [0.2]}'))
    >>> read_mtlx_fit(path)
    ('cpa', {'alphas': [0.2]})
    """
    try:
        root = ET.fromstring(read_limited(path, MTLX_MAX_BYTES))
    except FileTooLargeError:
        raise ValueError(f"{path}: larger than the {MTLX_MAX_BYTES} bytes a flakedb MaterialX document can be "
                         f"(export-cpa's are ~30 kB): not one flakedb wrote") from None
    except ET.ParseError as e:
        raise ValueError(f"{path}: not well-formed XML ({e}): a truncated or damaged file; export it again") from None
    if root.tag != "materialx":
        raise ValueError(f"{path}: not a MaterialX document (root <{root.tag}>)")
    for attribute, kind in FIT_ATTRIBUTES.items():
        s = root.get(attribute)
        if s is not None:
            try:
                fit = json.loads(s, parse_constant=_refuse_constant)
            except (ValueError, RecursionError) as e:    # RecursionError: nesting deeper than the parser's stack
                raise ValueError(f"{path}: its {attribute} attribute is not valid JSON ({str(e)[:120]}): a damaged "
                                 f"file; export it again") from None
            if not isinstance(fit, dict):
                raise ValueError(f"{path}: its {attribute} attribute is not a JSON object (a {type(fit).__name__}): "
                                 f"not flakedb's fit; export it again")
            return kind, fit
    raise ValueError(f"{path}: a MaterialX document without flakedb's fit (not written by flakedb export-openpbr "
                     f"or export-cpa)")


def cpa_mtlx_text(image_file: str, scales, alphas, coat_ior: float, n_table: int, name: str, fit_json: str = "{}",
                  sparkle: dict | None = None, retro_alphas=(), tilted=()) -> str:
    """The angle-indexed material of :mod:`flakedb.export.cpa` as a MaterialX 1.39 graph of standard
    nodes: μ_v = -``normal``·``viewdirection`` (world space), x = clip(μ_v, 0, 1) (n − 1), j = min(⌊x⌋, n − 2),
    t = x − j; texels j and j + 1 of ``image_file`` (the colour table's 16 bits in two 8-bit planes,
    :func:`flakedb.export.cpa.table_planes`, ``lin_rec709``) read at their centres ``((j + 0.5) / n, (k + 0.5) /
    (2 rows))``, ``(…, (rows + k + 0.5) / (2 rows))`` with ``closest`` filtering, each recombined ``hi w_hi +
    lo w_lo`` (:data:`PLANE_WEIGHTS`) and mixed by t in the shader's float arithmetic (the texture filter's
    fixed-point weights are not used: :func:`flakedb.export.cpa.hat_weights` exactly), each row times its
    ``scales[k]``; row 0 colours an
    ``oren_nayar_diffuse_bsdf`` of roughness 0 (Lambert), row k a ``generalized_schlick_bsdf`` (GGX,
    ``color0 = color90`` = the row's colour: no Fresnel variation) of roughness α_k (MaterialX's
    ``roughness`` is α itself), the rows after the K lobes the same BSDF with ``normal`` = −``viewdirection``
    (the backscatter lobes of :func:`flakedb.export.cpa.retro_lobe`, α = ``retro_alphas``), the rows after
    those the same BSDF with ``normal`` = normalize(N (1 + k μ_v²) + k μ_v ``viewdirection``) (the tilted lobes of
    :func:`flakedb.export.cpa.tilted_lobe`, (α, k) = ``tilted``; ``viewdirection`` points at the surface), all summed by
    ``add`` with the coat's mirror, a smooth
    ``dielectric_bsdf`` of index ``coat_ior`` in reflection only; a ``surface`` and a
    ``surfacematerial``.  The sum is ``add``, not ``layer``: the table already holds the coat's
    transmission.  Plain XML (no MaterialX needed to write); the fit as JSON in ``flakedb_cpa``.

    ``sparkle`` (:func:`flakedb.export.sparkle.node_inputs`): lobe k's colour is split into (1 − β) on the smooth
    lobe and the glint layer of :mod:`flakedb.export.sparkle` (:func:`_sparkle_nodes`)."""
    n = safe_name(name)
    rows = len(scales)
    if rows != 1 + len(alphas) + len(retro_alphas) + len(tilted):
        raise ValueError(f"cpa_mtlx_text: {rows} table rows, not 1 + {len(alphas)} lobes + {len(retro_alphas)} "
                         f"backscatter lobes + {len(tilted)} tilted lobes")
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
    # x = clip(μ_v, 0, 1) (n - 1), j = min(floor x, n - 2), t = x - j: texels j and j + 1 read at their centres
    # (u = (j + 0.5) / n, (j + 1.5) / n) and mixed by t in float (cpa.hat_weights), not by the texture filter
    node("multiply", "x_raw", "float", in1=("float", ("node", "NdotI")), in2=("float", f"{-(n_table - 1):.9g}"))
    node("clamp", "x", "float", **{"in": ("float", ("node", "x_raw"))}, low=("float", "0"), high=("float", f"{n_table - 1:.9g}"))
    node("floor", "x_floor", "float", **{"in": ("float", ("node", "x"))})
    node("min", "j", "float", in1=("float", ("node", "x_floor")), in2=("float", f"{n_table - 2:.9g}"))
    node("subtract", "t", "float", in1=("float", ("node", "x")), in2=("float", ("node", "j")))
    node("add", "j_centre", "float", in1=("float", ("node", "j")), in2=("float", "0.5"))
    node("divide", "u0", "float", in1=("float", ("node", "j_centre")), in2=("float", f"{n_table:.9g}"))
    node("add", "u1", "float", in1=("float", ("node", "u0")), in2=("float", f"{1.0 / n_table:.17g}"))
    if retro_alphas:
        node("multiply", "V_back", "vector3", in1=("vector3", ("node", "V_world")), in2=("float", "-1"))
    if tilted:     # N' = normalize(N (1 + k μ_v²) + k μ_v V_world): cpa.tilted_cosines
        node("multiply", "mu_v", "float", in1=("float", ("node", "NdotI")), in2=("float", "-1"))
        node("multiply", "mu_v2", "float", in1=("float", ("node", "mu_v")), in2=("float", ("node", "mu_v")))
    for i, (_, k_tilt) in enumerate(tilted):
        kt = f"{float(k_tilt):.17g}"
        node("multiply", f"tilt_kmu2_{i}", "float", in1=("float", ("node", "mu_v2")), in2=("float", kt))
        node("add", f"tilt_a_{i}", "float", in1=("float", ("node", f"tilt_kmu2_{i}")), in2=("float", "1"))
        node("multiply", f"tilt_b_{i}", "float", in1=("float", ("node", "mu_v")), in2=("float", kt))
        node("multiply", f"tilt_nN_{i}", "vector3", in1=("vector3", ("node", "N_world")), in2=("float", ("node", f"tilt_a_{i}")))
        node("multiply", f"tilt_nV_{i}", "vector3", in1=("vector3", ("node", "V_world")), in2=("float", ("node", f"tilt_b_{i}")))
        node("add", f"tilt_sum_{i}", "vector3", in1=("vector3", ("node", f"tilt_nN_{i}")), in2=("vector3", ("node", f"tilt_nV_{i}")))
        node("normalize", f"N_tilt_{i}", "vector3", **{"in": ("vector3", ("node", f"tilt_sum_{i}"))})
    total = None
    for k in range(rows):
        for e in (0, 1):
            for plane, row, weight in (("hi", k, PLANE_WEIGHTS[0]), ("lo", rows + k, PLANE_WEIGHTS[1])):
                node("combine2", f"uv_{plane}{e}_{k}", "vector2", in1=("float", ("node", f"u{e}")),
                     in2=("float", f"{(row + 0.5) / (2 * rows):.9g}"))
                img = node("image", f"plane_{plane}{e}_{k}", "color3", texcoord=("vector2", ("node", f"uv_{plane}{e}_{k}")),
                           filtertype=("string", "closest"), uaddressmode=("string", "clamp"),
                           vaddressmode=("string", "clamp"))
                ET.SubElement(img, "input", {"name": "file", "type": "filename", "value": image_file,
                                             "colorspace": "lin_rec709"})
                node("multiply", f"{plane}{e}_{k}", "color3", in1=("color3", ("node", f"plane_{plane}{e}_{k}")),
                     in2=("float", f"{weight:.17g}"))
            node("add", f"table{e}_{k}", "color3", in1=("color3", ("node", f"hi{e}_{k}")), in2=("color3", ("node", f"lo{e}_{k}")))
        node("mix", f"table_{k}", "color3", bg=("color3", ("node", f"table0_{k}")), fg=("color3", ("node", f"table1_{k}")),
             mix=("float", ("node", "t")))
        node("multiply", f"colour_{k}", "color3", in1=("color3", ("node", f"table_{k}")), in2=("float", f"{float(scales[k]):.9g}"))
        if sparkle is not None and k == sparkle["lobe"]:
            glint = _sparkle_nodes(node, f"colour_{k}", sparkle)
            node("multiply", f"colour_{k}_smooth", "color3", in1=("color3", ("node", f"colour_{k}")),
                 in2=("float", f"{1.0 - float(sparkle['share']):.9g}"))
            node("generalized_schlick_bsdf", "glints", "BSDF", color0=("color3", ("node", glint)),
                 color90=("color3", ("node", glint)),
                 roughness=("vector2", f"{sparkle['glint_alpha']:.9g}, {sparkle['glint_alpha']:.9g}"),
                 normal=("vector3", ("node", "sp_m")), distribution=("string", "ggx"))
            node("add", "sum_glints", "BSDF", in1=("BSDF", ("node", total)), in2=("BSDF", ("node", "glints")))
            total = "sum_glints"
        if k == 0:
            node("oren_nayar_diffuse_bsdf", "lobe_0", "BSDF", color=("color3", ("node", "colour_0")), roughness=("float", "0"))
        elif k <= len(alphas):
            a = float(alphas[k - 1])
            ck = f"colour_{k}_smooth" if sparkle is not None and k == sparkle["lobe"] else f"colour_{k}"
            node("generalized_schlick_bsdf", f"lobe_{k}", "BSDF", color0=("color3", ("node", ck)),
                 color90=("color3", ("node", ck)), roughness=("vector2", f"{a:.9g}, {a:.9g}"),
                 distribution=("string", "ggx"))
        elif k <= len(alphas) + len(retro_alphas):
            a = float(retro_alphas[k - 1 - len(alphas)])
            node("generalized_schlick_bsdf", f"lobe_{k}", "BSDF", color0=("color3", ("node", f"colour_{k}")),
                 color90=("color3", ("node", f"colour_{k}")), roughness=("vector2", f"{a:.9g}, {a:.9g}"),
                 normal=("vector3", ("node", "V_back")), distribution=("string", "ggx"))
        else:
            i = k - 1 - len(alphas) - len(retro_alphas)
            a = float(tilted[i][0])
            node("generalized_schlick_bsdf", f"lobe_{k}", "BSDF", color0=("color3", ("node", f"colour_{k}")),
                 color90=("color3", ("node", f"colour_{k}")), roughness=("vector2", f"{a:.9g}, {a:.9g}"),
                 normal=("vector3", ("node", f"N_tilt_{i}")), distribution=("string", "ggx"))
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


def _sparkle_nodes(node, colour: str, sp: dict) -> str:
    """The glint layer of :mod:`flakedb.export.sparkle` in MaterialX standard nodes, term for term as the
    Blender node group (:data:`flakedb.export.blender._CPA_BUILD`): cell = floor(``texcoord`` × cells per UV
    unit); u₁, u₂, u₃ = ``cellnoise3d`` of (cell, 0 | 1 | 2) (MaterialX's hash, not Blender's: the same
    statistics, another layout); the normal m (node ``sp_m``) in the world-space ``tangent`` frame; the weight W,
    the occupancy test and the share.  Returns the name of the glint colour node (color3)."""
    count = [0]

    def f(kind, typ="float", **inputs):
        count[0] += 1
        nm = f"sp_{count[0]}"
        node(kind, nm, typ, **{k: ((t, ("node", v)) if isinstance(v, str) and v.startswith("sp_") or v in ("N_world", "V_world", colour) else (t, v))
                               for k, (t, v) in inputs.items()})
        return nm

    def num(x):
        return f"{float(x):.9g}"

    node("texcoord", "sp_uv", "vector2", index=("integer", "0"))
    cell = f("floor", "vector2", **{"in": ("vector2", f("multiply", "vector2", in1=("vector2", "sp_uv"),
                                                        in2=("float", num(sp["cells_per_uv"]))))})
    cx = f("extract", "float", **{"in": ("vector2", cell)}, index=("integer", "0"))
    cy = f("extract", "float", **{"in": ("vector2", cell)}, index=("integer", "1"))
    u1, u2, u3 = (f("cellnoise3d", "float", position=("vector3", f("combine3", "vector3", in1=("float", cx), in2=("float", cy),
                                                                   in3=("float", num(i))))) for i in range(3))
    t = f("multiply", in1=("float", f("sqrt", **{"in": ("float", f("divide", in1=("float", u1),
                                                                        in2=("float", f("subtract", in1=("float", "1"), in2=("float", u1)))))})),
          in2=("float", num(sp["lobe_alpha"])))
    c = f("divide", in1=("float", "1"), in2=("float", f("sqrt", **{"in": ("float", f("add", in1=("float", f("multiply", in1=("float", t), in2=("float", t))),
                                                                                     in2=("float", "1")))})))
    s = f("multiply", in1=("float", t), in2=("float", c))
    phi = f("multiply", in1=("float", u2), in2=("float", num(2.0 * 3.141592653589793)))
    node("tangent", "sp_T0", "vector3", space=("string", "world"))
    tn = f("dotproduct", in1=("vector3", "sp_T0"), in2=("vector3", "N_world"))
    tt = f("normalize", "vector3", **{"in": ("vector3", f("subtract", "vector3", in1=("vector3", "sp_T0"),
                                                           in2=("vector3", f("multiply", "vector3", in1=("vector3", "N_world"), in2=("float", tn)))))})
    bb = f("crossproduct", "vector3", in1=("vector3", "N_world"), in2=("vector3", tt))
    mx = f("multiply", "vector3", in1=("vector3", tt), in2=("float", f("multiply", in1=("float", s), in2=("float", f("cos", **{"in": ("float", phi)})))))
    my = f("multiply", "vector3", in1=("vector3", bb), in2=("float", f("multiply", in1=("float", s), in2=("float", f("sin", **{"in": ("float", phi)})))))
    mz = f("multiply", "vector3", in1=("vector3", "N_world"), in2=("float", c))
    node("add", "sp_m", "vector3", in1=("vector3", ("node", f("add", "vector3", in1=("vector3", mx), in2=("vector3", my)))),
         in2=("vector3", ("node", mz)))
    v = f("multiply", "vector3", in1=("vector3", "V_world"), in2=("float", "-1"))      # towards the viewer
    mv = f("dotproduct", in1=("vector3", "sp_m"), in2=("vector3", v))
    nv = f("max", in1=("float", f("dotproduct", in1=("vector3", "N_world"), in2=("vector3", v))), in2=("float", "0.0001"))
    mu_l = f("subtract", in1=("float", f("multiply", in1=("float", f("multiply", in1=("float", mv), in2=("float", c))), in2=("float", "2"))),
             in2=("float", nv))

    def lam(a2, mu):  # GGX Smith Λ(μ) = (sqrt(1 + α² (1/μ² − 1)) − 1) / 2
        mu = f("max", in1=("float", mu), in2=("float", "0.0001"))
        x = f("subtract", in1=("float", f("divide", in1=("float", "1"), in2=("float", f("multiply", in1=("float", mu), in2=("float", mu))))),
              in2=("float", "1"))
        r = f("sqrt", **{"in": ("float", f("add", in1=("float", f("multiply", in1=("float", x), in2=("float", num(a2)))), in2=("float", "1")))})
        return f("multiply", in1=("float", f("subtract", in1=("float", r), in2=("float", "1"))), in2=("float", "0.5"))

    a2k, a2g = float(sp["lobe_alpha"]) ** 2, float(sp["glint_alpha"]) ** 2
    g2k = f("divide", in1=("float", "1"), in2=("float", f("add", in1=("float", f("add", in1=("float", lam(a2k, nv)), in2=("float", lam(a2k, mu_l)))),
                                                           in2=("float", "1"))))
    g2g = f("divide", in1=("float", "1"), in2=("float", f("add", in1=("float", f("multiply", in1=("float", lam(a2g, mv)), in2=("float", "2"))),
                                                           in2=("float", "1"))))
    cmax = f("max", in1=("float", c), in2=("float", "0.0001"))
    den = f("multiply", in1=("float", f("multiply", in1=("float", cmax), in2=("float", nv))), in2=("float", g2g))
    w = f("divide", in1=("float", f("multiply", in1=("float", g2k), in2=("float", mv))), in2=("float", den))
    ok_v = f("ifgreater", value1=("float", mv), value2=("float", "0"), in1=("float", "1"), in2=("float", "0"))
    ok_l = f("ifgreater", value1=("float", mu_l), value2=("float", "0"), in1=("float", ok_v), in2=("float", "0"))
    ok = f("ifgreater", value1=("float", num(sp["occupancy"])), value2=("float", u3), in1=("float", ok_l), in2=("float", "0"))
    gain = f("multiply", in1=("float", f("multiply", in1=("float", w), in2=("float", ok))),
             in2=("float", num(float(sp["share"]) / float(sp["occupancy"]))))
    return f("multiply", "color3", in1=("color3", colour), in2=("float", gain))


def write_cpa_mtlx(path, image_file: str, scales, alphas, coat_ior: float, n_table: int, name: str,
                   fit_json: str = "{}", retro_alphas=(), tilted=()) -> Path:
    path = Path(path)
    with atomic_path(path, suffix="") as tmp:
        Path(tmp).write_text(cpa_mtlx_text(image_file, scales, alphas, coat_ior, n_table, name, fit_json,
                                           retro_alphas=retro_alphas, tilted=tilted), encoding="utf-8")
    return path
