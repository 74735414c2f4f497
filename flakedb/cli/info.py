"""`flakedb info FILE`: what a file holds, for a person (text) or a machine (``--json``).

Three kinds, recognised by their first bytes (not by the extension): a Fourier ``.bsdf`` (``SCATFUN``),
a flakedb HDF5 BSDF (``.h5``, the full-precision result) and a Mitsuba 3 ``measured`` tensor file
(``tensor_file``, what ``flakedb export-mitsuba`` writes, ``NAME.measured.tensor``).  For the two
Fourier files the checks are stated in words: energy (the directional albedo at every incident
node, with the smooth coat's mirror term, is ≤ 1), colour (no negative channel in the order-0
coefficients or the albedo; the RGB working space and its gamut mapping), and, for an ``.h5``, the
solver's convergence in the same words compose printed (:func:`flakedb.solve.pipeline.solver_warnings`).
"""

import json
import math
import re
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

import click
import numpy as np

from flakedb.bsdf import BSDFFileError, open_bsdf
from flakedb.bsdf.dispatch import file_kind as dispatch_file_kind
from flakedb.bsdf.table import ENERGY_SLACK, energy_albedo
from flakedb.cli.errors import FlakedbError
from flakedb.colour.colorimetry import XYZ_to_Lab, reflectance_to_XYZ, white_XYZ
from flakedb.solve.pipeline import solver_warnings
from flakedb.export.materialx import read_mtlx_fit
from flakedb.render.mitsuba import read_tensor_file
from flakedb.safeio import read_head, read_limited

#: Incident zenith angles [deg] (light arriving from above) at which the albedo is listed.
INFO_THETA_DEG = (0.0, 30.0, 45.0, 60.0, 75.0, 85.0)



def file_kind(path) -> str:
    """'fourier' (a .bsdf or .h5), 'tensor', 'materialx', 'gltf' (JSON or binary) or 'usda', from the one
    file-kind registry (:data:`flakedb.bsdf.dispatch.FILE_KINDS`; unknown kinds raise BSDFFileError there).

    >>> import tempfile
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "paint.bsdf"
    >>> _ = path.write_bytes(b"SCATFUN" + bytes(57))
    >>> file_kind(path)
    'fourier'
    """
    return {"bsdf": "fourier", "h5": "fourier", "glb": "gltf"}.get(dispatch_file_kind(path), dispatch_file_kind(path))


#: Largest scene file ``flakedb info`` reads whole (a flakedb sphere export is ~0.3-1 MB).
SCENE_MAX_BYTES = 64 << 20


def _read_scene(p: Path) -> bytes:
    try:
        return read_limited(p, SCENE_MAX_BYTES)
    except (OSError, ValueError) as e:       # too large (FileTooLargeError), vanished, unreadable
        raise BSDFFileError(f"{p}: cannot be read as a scene file ({e})") from None


def _gltf_json(p: Path) -> dict:
    data = _read_scene(p)
    try:
        if data.startswith(b"glTF"):
            n_json, kind = struct.unpack("<I4s", data[12:20])
            if kind != b"JSON":
                raise ValueError("the first GLB chunk is not JSON")
            doc = json.loads(data[20:20 + n_json])
        else:
            doc = json.loads(data)
    except (ValueError, struct.error) as e:
        raise BSDFFileError(f"{p}: not a readable glTF 2.0 file ({e})") from None
    if not isinstance(doc, dict) or str(doc.get("asset", {}).get("version", "")) != "2.0":
        raise BSDFFileError(f"{p}: JSON but not a glTF 2.0 document (no asset.version 2.0)")
    return doc


def describe_gltf(path):
    """A JSON-able summary of a glTF 2.0 file (``.gltf`` / ``.glb``): its materials (the fitted
    metallic-roughness parameters and extensions, the fit's error from ``extras.flakedb_fit``) and its
    meshes' vertex attributes, with a check that the mesh carries UVs and tangents (what a normal- or
    flake-map needs)."""
    p = Path(path)
    doc = _gltf_json(p)
    mats = []
    for m in doc.get("materials", []):
        pbr = m.get("pbrMetallicRoughness", {})
        mats.append({"name": m.get("name"), "baseColorFactor": pbr.get("baseColorFactor"),
                     "metallicFactor": pbr.get("metallicFactor"), "roughnessFactor": pbr.get("roughnessFactor"),
                     "extensions": sorted(m.get("extensions", {})),
                     "fit_error": (m.get("extras", {}).get("flakedb_fit") or {}).get("error")})
    attrs = [sorted(prim.get("attributes", {})) for mesh in doc.get("meshes", []) for prim in mesh.get("primitives", [])]
    uv_ok = bool(attrs) and all("TEXCOORD_0" in a and "TANGENT" in a for a in attrs)
    return {"kind": "gltf", "file": str(p), "size_bytes": p.stat().st_size,
            "format": f"glTF 2.0 {'binary (.glb)' if read_head(p, 4) == b'glTF' else 'JSON (.gltf)'}",
            "generator": doc.get("asset", {}).get("generator"), "extensionsUsed": doc.get("extensionsUsed", []),
            "materials": mats, "primitive_attributes": attrs,
            "checks": [{"check": "uv", "ok": uv_ok,
                        "text": ("every primitive has TEXCOORD_0 and TANGENT" if uv_ok else
                                 "a primitive without TEXCOORD_0 / TANGENT: no texture or normal map can be placed")}]}


def describe_usda(path):
    """A JSON-able summary of a USD text layer (``.usda``): its default prim, the shaders (``info:id``)
    with their inputs, and the fit flakedb stored in ``customLayerData``."""
    p = Path(path)
    try:
        text = _read_scene(p).decode("utf-8")
    except UnicodeDecodeError as e:
        raise BSDFFileError(f"{p}: a .usda that is not UTF-8 text (byte {e.start})") from None
    prim = re.search(r'defaultPrim\s*=\s*"([^"]*)"', text)
    shaders = []
    for block in re.split(r"\bdef Shader\b", text)[1:]:
        sid = re.search(r'info:id\s*=\s*"([^"]*)"', block)
        inputs = dict(re.findall(r"\binputs:(\w+)\s*=\s*([^\n]+)", block.split("def ", 1)[0]))
        shaders.append({"id": sid.group(1) if sid else None, "inputs": inputs})
    fit = None
    line = next((ln for ln in text.splitlines() if "string flakedb_fit = " in ln), None)
    if line is not None:
        try:
            fit = json.loads(json.loads(line.split(" = ", 1)[1]))
        except ValueError:
            fit = None
    return {"kind": "usda", "file": str(p), "size_bytes": p.stat().st_size, "format": "USD text layer (.usda)",
            "default_prim": prim.group(1) if prim else None, "shaders": shaders,
            "fit_error": (fit or {}).get("error"), "checks": []}


def _print_scene(d):
    echo = click.echo
    echo(f"file:          {d['file']} ({d['size_bytes'] / 1e3:.1f} kB): {d['format']}")
    if d["kind"] == "gltf":
        echo(f"generator:     {d.get('generator')}; extensions {', '.join(d['extensionsUsed']) or 'none'}")
        for m in d["materials"]:
            echo(f"material:      {m['name']}: baseColor {m['baseColorFactor']}, metallic {m['metallicFactor']}, "
                 f"roughness {m['roughnessFactor']}; {', '.join(m['extensions'])}")
        for a in d["primitive_attributes"]:
            echo(f"mesh:          attributes {', '.join(a)}")
    else:
        echo(f"default prim:  {d['default_prim']}")
        for sh in d["shaders"]:
            echo(f"shader:        {sh['id']}: " + ", ".join(f"{k} = {v.strip()}" for k, v in sh["inputs"].items()))
    err = d.get("fit_error") or next((m["fit_error"] for m in d.get("materials", []) if m.get("fit_error")), None)
    if err:
        echo(f"fit error:     worst ΔE00 {err.get('worst_dE00_E2194', float('nan')):.2f} at the E2194 geometries "
             "(the fit's own error against the exact BSDF, not what a renderer makes of it)")
    if d["checks"]:
        echo("checks:")
        for c in d["checks"]:
            echo(f"  [{'ok  ' if c['ok'] else 'FAIL'}] {c['text']}")


def _short(v):
    """A metadata value for people: scalars and short strings as they are, long things summarised."""
    if isinstance(v, str):
        first = v.strip().split("\n")[0]
        return first if len(first) <= 100 and "\n" not in v.strip() else f"{first[:80]}… ({len(v)} characters)"
    if isinstance(v, (list, tuple)):
        return json.dumps(v) if len(json.dumps(v)) <= 80 else f"[{len(v)} values]"
    if isinstance(v, dict):
        return json.dumps(v) if len(json.dumps(v)) <= 80 else f"{{{len(v)} entries: {', '.join(list(v)[:5])}…}}"
    return v


def _checks(b):
    """Energy and colour checks of a Fourier file, in words: list of {check, ok, text}."""
    t = b.to_table()
    h = t.n // 2
    alb = t.albedo()[:, h:]                                      # (C, h) table albedo per channel
    tot = energy_albedo(t)                                       # + the mirror term: compose's check too
    # order 0 of light from above; a reflection-only table (an opaque paint's .h5) holds only its quadrant, the
    # transmission beside it is 0 (densifying it was 4x the memory: 4.3 GB for a 41-band rough coat at n = 200)
    a0 = np.concatenate([t.stored[..., 0], np.zeros((t.n_channels, h, 1))], axis=2) if t.reflection_only \
        else t.coeffs[:, h:, :, 0]
    out = []
    hi = float(tot.max())
    ok = hi <= 1.0 + ENERGY_SLACK
    out.append({"check": "energy", "ok": ok, "max_albedo": hi,
                "text": (f"energy conserved: the albedo (reflected + transmitted{' + mirror term' if b.delta else ''}) "
                         f"is at most {hi:.4f} over the {h} incident nodes and {t.n_channels} channel(s)" if ok else
                         f"ENERGY NOT CONSERVED: the albedo reaches {hi:.4f} > 1 at an incident node")})
    neg_a0 = float(a0.min())
    neg_alb = float(alb.min())
    scale = max(float(np.abs(a0).max()), 1e-300)
    ok = neg_alb >= 0 and neg_a0 >= -1e-6 * scale
    out.append({"check": "colour", "ok": ok, "min_order0": neg_a0, "min_albedo": neg_alb,
                "text": ("no negative channel: every order-0 coefficient and every channel's albedo is >= 0" if ok else
                         f"NEGATIVE CHANNELS: order-0 coefficient down to {neg_a0:.3g}, albedo down to {neg_alb:.3g} "
                         f"(renderers clamp these: out-of-gamut colour not mapped; recompose with this flakedb)")})
    md = b.metadata or {}
    if "rgb_space" in md:
        out.append({"check": "gamut", "ok": True,
                    "text": (f"RGB space {md['rgb_space']}; gamut mapping desaturated {md.get('gamut_pairs_mapped')} "
                             f"node pair(s), largest ΔE00 {md.get('gamut_max_dE00')}")})
    elif b.n_channels == 3 and b.kind == "bsdf":
        out.append({"check": "gamut", "ok": None,
                    "text": "RGB space not recorded: readers assume white-normalised linear sRGB"})
    return out, tot


def describe(path):
    """A JSON-able summary of the file at ``path`` by its kind (:data:`INFO_ROUTES`; raises BSDFFileError when
    unreadable or of no known kind)."""
    return INFO_ROUTES[dispatch_file_kind(path)][0](path)


def describe_fourier(path):
    """The summary of a Fourier .bsdf or a flakedb .h5: format, paint, channels, the mirror term, checks."""
    b = open_bsdf(path)
    size = b.path.stat().st_size
    mu = np.cos(np.radians(INFO_THETA_DEG))
    albedo = b.albedo(mu)
    if b.kind == "bsdf":
        stored = "Y, R, B" if b.n_channels == 3 else "mono"
        full = b.n_nodes * b.n_nodes * b.n_channels * max(b.max_order, 1)
        fmt = f"Fourier .bsdf (layerlab / Mitsuba 0.6 / pbrt-v3), version {b.header['version']}, flags {b.header['flags']}"
    else:
        stored = ", ".join(b.channels)
        full = b.n_coeffs
        fmt = f"flakedb HDF5 BSDF, format version {b.metadata.get('h5_format_version')}"
    checks, _ = _checks(b)
    md = b.metadata or {}
    solver = []
    if b.kind == "h5" and isinstance(md.get("solver_info"), dict):
        n = md.get("n_nodes", b.n_nodes - 2)
        solver = solver_warnings(md["solver_info"], n)
        orders = md["solver_info"].get("orders")
        conv = md["solver_info"].get("order_converged")
        head = (f"Fourier orders: {orders} kept" + ("" if conv is None else
                (f", order tail {md['solver_info'].get('order_tail', 0):.1e} within tolerance "
                 f"{md['solver_info'].get('order_tol', 0):.0e}" if conv else ", NOT converged")))
        checks.append({"check": "solver", "ok": not solver, "text": head + (
            "; no convergence warnings" if not solver else f"; {len(solver)} warning(s) (below)")})
    d = {
        "kind": b.kind,
        "file": str(b.path),
        "format": fmt,
        "size_bytes": size,
        "nodes": b.n_nodes,
        "quadrature_nodes": b.n_nodes - 2,
        "channels": b.n_channels,
        "stored_channels": stored,
        "eval_channels": list(b.channels),
        "max_order": b.max_order,
        "coefficients": b.n_coeffs,
        "coefficients_untruncated": full,
        "eta": b.eta,
        "alpha": list(b.alpha),
        "delta": b.delta,
        "metadata": b.metadata,
        "albedo": [{"theta_i_deg": t, "mu_i": float(m), "albedo": [float(x) for x in a]}
                   for t, m, a in zip(INFO_THETA_DEG, mu, albedo)],
        "albedo_sampling_channel_range": [float(np.min(b.albedo_nodes()[b.nodes != 0])),
                                          float(np.max(b.albedo_nodes()[b.nodes != 0]))],
        "checks": checks,
        "warnings": list(dict.fromkeys(list(md.get("warnings") or []) + solver)),
    }
    if b.kind == "h5" and md.get("wavelength_nm") and len(md["wavelength_nm"]) == b.n_channels:
        wl = np.asarray(md["wavelength_nm"], float)
        try:
            XYZ = reflectance_to_XYZ(albedo, wl)
            lab = XYZ_to_Lab(XYZ, white=white_XYZ(wl))
        except ValueError as e:   # a grid the colorimetry does not take (step, range): no CIELAB rows
            d["checks"].append({"check": "cielab", "ok": None, "text": f"no CIELAB of the albedo: {e}"})
            return d
        for row, x, c in zip(d["albedo"], XYZ, lab):
            row["albedo_Y"] = float(x[1])
            row["albedo_Lab"] = [float(v) for v in c]
    return d


def describe_tensor(path):
    """A JSON-able summary of a Mitsuba 3 ``measured`` tensor file."""
    p = Path(path)
    try:
        f = read_tensor_file(p)
    except (ValueError, KeyError, IndexError, struct.error) as e:  # a damaged file
        raise BSDFFileError(f"{p}: a tensor file that cannot be read ({e})") from None
    data_key = "rgb" if "rgb" in f else ("spectra" if "spectra" in f else None)
    desc = bytes(np.asarray(f.get("description", np.zeros(0, np.uint8)))).decode("utf-8", "replace")
    d = {"kind": "mitsuba-measured", "file": str(p), "size_bytes": p.stat().st_size,
         "format": "Mitsuba 3 `measured` tensor file (RGL; Dupuy & Jakob 2018)",
         "fields": {k: list(np.shape(v)) for k, v in f.items()}, "description": desc,
         "variant": {"rgb": "rgb", "spectra": "spectral"}.get(data_key)}
    if data_key is None:
        d["checks"] = [{"check": "data", "ok": False, "text": "no rgb or spectra field: not a measured BSDF"}]
        return d
    d.update(_tensor_use(p, desc))
    data = np.asarray(f[data_key], float)
    th = np.degrees(np.asarray(f.get("theta_i", []), float))
    d["theta_i_deg"] = [float(th.min()), float(th.max()), int(th.size)] if th.size else None
    d["resolution"] = list(data.shape[-2:])
    if "wavelengths" in f:
        wl = np.asarray(f["wavelengths"], float)
        d["wavelengths_nm"] = [float(wl.min()), float(wl.max()), int(wl.size)]
    mn = float(data.min())
    d["checks"] = [
        {"check": "colour", "ok": mn >= 0, "min_value": mn,
         "text": ("no negative value in the tabulated f·cos" if mn >= 0 else f"NEGATIVE values down to {mn:.3g}")},
        {"check": "content", "ok": True,
         "text": "front-side reflection only; a smooth coat's mirror term is not in this format (see the description)"},
    ]
    return d


def _tensor_use(p: Path, desc: str) -> dict:
    """How to use a ``measured`` tensor: ``scale`` (the factor its values carry: 2 for the coated route's
    half of a ``blendbsdf``, :mod:`flakedb.render.mitsuba.coated`, read from the description it writes) and
    ``use`` (the Mitsuba 3 BSDF to load: the tensor alone only at scale 1)."""
    m = re.search(r"coated-route export .*? at scale ([0-9.eE+-]+)", desc)
    scale = float(m.group(1)) if m else 1.0
    if scale == 1.0:
        return {"scale": 1.0, "use": {"type": "measured", "filename": str(p.resolve())}}
    side = p.with_name(p.name + ".json")
    use = {"bsdf_json": str(side.resolve()), "bsdf_xml": str(p.with_name(p.name + ".xml").resolve()),
           "json_present": side.exists()}
    return {"scale": scale, "use": use,
            "use_text": (f"the values are the paint's table x{scale:g} (one half of the coated route's blendbsdf): "
                         f"alone it renders {scale:g} times too bright.  Use the BSDF in {side} (mi.load_dict) or "
                         f"its .xml, which blend it with the coat's mirror at weight 1/{scale:g}"
                         + ("" if side.exists() else "; that file is missing here: re-run `flakedb export-mitsuba` "
                            "(it writes all three), or `--no-coat` for a tensor at x1 without the coat"))}


#: kind of flakedb MaterialX document (:data:`flakedb.export.materialx.FIT_ATTRIBUTES`) -> (summary kind, format).
MTLX_FORMATS = {
    "openpbr": ("materialx-fit", "MaterialX document, open_pbr_surface fitted by flakedb export-openpbr"),
    "cpa": ("materialx-cpa", "MaterialX document, angle-indexed colour table and lobes (flakedb export-cpa)"),
}


def describe_fit(path):
    """A JSON-able summary of a MaterialX document written by ``flakedb export-openpbr`` (the fitted
    parameters, :mod:`flakedb.export.openpbr`) or ``flakedb export-cpa`` (the lobes and the table,
    :mod:`flakedb.export.cpa`), with the fit's error."""
    try:
        mtlx_kind, fit = read_mtlx_fit(path)
    except (ValueError, ET.ParseError) as e:
        raise BSDFFileError(str(e)) from None
    for where, f in ([("", fit), ("materialx.", fit.get("materialx"))] if "materialx" in fit else [("", fit)]):
        _check_fit_fields(path, f, FIT_FIELDS[mtlx_kind], where)
    p = Path(path)
    kind, fmt = MTLX_FORMATS[mtlx_kind]
    return {"kind": kind, "file": str(p), "size_bytes": p.stat().st_size, "format": fmt, "fit": fit}


#: The fit fields the summary prints, per kind of document: name -> (what it must be, required).  A list holds at
#: most MAX_FIT_LIST entries (export-cpa writes a few lobes; a longer one is not flakedb's).
_ERROR_FIELDS = {"worst_dE00_E2194": ("number", True), "worst_dE00_E2539": ("number", True),
                 "cosine_weighted_difference": ("number", True)}
FIT_FIELDS = {
    "cpa": {"alphas": ("numbers", False), "retro_alphas": ("numbers", False), "tilted": ("pairs", False),
            "coat_ior": ("number", False), "n_table": ("integer", False), "distribution": ("text", False),
            "source": ("text", False), "error": (_ERROR_FIELDS, False)},
    "openpbr": {"base_color": ("rgb", True), "base_metalness": ("number", True), "specular_roughness": ("number", True),
                "coat_ior": ("number", True), "coat_roughness": ("number", True), "specular_color": ("rgb", False),
                "specular_ior": ("number", False), "thin_film_thickness_nm": ("number", False),
                "thin_film_ior": ("number", False), "source": ("text", False), "error": (_ERROR_FIELDS, False)},
}
MAX_FIT_LIST = 64
_FIT_VALUE_TEXT = {"number": "a finite number", "integer": "an integer", "text": "printable text of ≤ 4096 characters",
                   "rgb": "three finite numbers", "numbers": f"a list of ≤ {MAX_FIT_LIST} finite numbers",
                   "pairs": f"a list of ≤ {MAX_FIT_LIST} [α, k] pairs of finite numbers"}


def _fit_value_ok(v, what) -> bool:
    def num(x):
        return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)

    if what == "number":
        return num(v)
    if what == "integer":
        return isinstance(v, int) and not isinstance(v, bool)
    if what == "text":
        return isinstance(v, str) and len(v) <= 4096 and v.isprintable()
    if what == "rgb":
        return isinstance(v, list) and len(v) == 3 and all(num(x) for x in v)
    if not isinstance(v, list) or len(v) > MAX_FIT_LIST:
        return False
    if what == "numbers":
        return all(num(x) for x in v)
    return all(isinstance(x, list) and len(x) == 2 and all(num(y) for y in x) for x in v)   # "pairs"


def _check_fit_fields(path, fit, fields, where=""):
    """BSDFFileError naming ``path`` and the field where the fit of a flakedb MaterialX document lacks a field
    :data:`FIT_FIELDS` requires or holds one of another kind (a damaged or foreign file), before anything is
    printed."""
    if not isinstance(fit, dict):
        raise BSDFFileError(f"{path}: its fit's {where.rstrip('.')} is not a JSON object: a damaged file; export it again")
    for name, (what, required) in fields.items():
        if name not in fit:
            if required:
                raise BSDFFileError(f"{path}: its fit has no {where}{name}: a damaged file; export it again")
            continue
        if isinstance(what, dict):
            if fit[name] != {}:           # an empty error block: no error was measured
                _check_fit_fields(path, fit[name], what, f"{where}{name}.")
        elif not _fit_value_ok(fit[name], what):
            shown = json.dumps(fit[name])
            raise BSDFFileError(f"{path}: its fit's {where}{name} is {shown[:60]}{'…' if len(shown) > 60 else ''}, "
                                f"not {_FIT_VALUE_TEXT[what]}: a damaged file; export it again")


def _print_fit(d):
    if d["kind"] == "materialx-cpa":
        return _print_cpa(d)
    echo = click.echo
    f = d["fit"]
    e = f.get("error", {})
    echo(f"file:          {d['file']} ({d['size_bytes'] / 1e3:.1f} kB): {d['format']}")
    echo(f"fitted to:     {f.get('source', '?')}")
    echo(f"parameters:    base_color ({', '.join(f'{x:.4f}' for x in f['base_color'])}), metalness "
         f"{f['base_metalness']:.3f}, specular_roughness {f['specular_roughness']:.3f}, coat_ior {f['coat_ior']:.4g}, "
         f"coat_roughness {f['coat_roughness']:.3f}")
    if "specular_color" in f:
        film = (f"thin film {f.get('thin_film_thickness_nm', 0.0):g} nm / {f.get('thin_film_ior', 1.5):g}"
                if f.get("thin_film_thickness_nm", 0.0) > 0 else "no thin film")
        echo(f"               specular_color ({', '.join(f'{x:.4f}' for x in f['specular_color'])}) (the dielectric "
             f"lobe's tint and the metal's F82 edge tint), specular_ior {f.get('specular_ior', 1.0):.4g}, {film}")
    if e:
        echo(f"fit error:     worst ΔE00 {e['worst_dE00_E2194']:.2f} (E2194 geometries), {e['worst_dE00_E2539']:.2f} "
             f"(with E2539's); cosine-weighted BSDF difference {100 * e['cosine_weighted_difference']:.1f} %")
        for g in e.get("dE00_E2539", []):
            echo(f"  illumination {g['illumination_deg']:4g} deg, aspecular {g['aspecular_deg']:5g} deg: "
                 f"ΔE00 {g['dE00']:.2f}")


def _print_cpa(d):
    echo = click.echo
    f = d["fit"].get("materialx", d["fit"])   # the graph holds the MaterialX route's own fit where it has one
    echo(f"file:          {d['file']} ({d['size_bytes'] / 1e3:.1f} kB): {d['format']}")
    echo(f"fitted to:     {f.get('source', '?')}"
         + ("; the GGX fit missed the E2194 target, the graph holds the MaterialX route's own fit"
            if "materialx" in d["fit"] else ""))
    lobes = ", ".join(f"{a:.3g}" for a in f.get("alphas", []))
    retro = ", ".join(f"{a:.3g}" for a in f.get("retro_alphas", []))
    tilted = f.get("tilted") or []
    echo(f"lobes:         {f.get('distribution', 'ggx')} α {lobes or 'none'}; backscatter α {retro or 'none'}"
         + (f"; {len(tilted)} tilted lobe(s)" if tilted else "") + f"; coat ior {f.get('coat_ior', '?')}")
    echo(f"colour table:  {f.get('n_table', '?')} view angles (the .cpa.png beside this file)")
    e = f.get("error", {})
    if e:
        echo(f"fit error:     worst ΔE00 {e['worst_dE00_E2194']:.2f} (E2194 geometries), {e['worst_dE00_E2539']:.2f} "
             f"(with E2539's); cosine-weighted BSDF difference {100 * e['cosine_weighted_difference']:.1f} %")


def _print_fourier(d):
    echo = click.echo
    md = d["metadata"] or {}
    what = "full-precision result of flakedb compose" if d["kind"] == "h5" else "renderer file"
    echo(f"file:          {d['file']} ({d['size_bytes'] / 1e6:.2f} MB): {d['format']}, {what}")
    if md.get("recipe"):
        extra = ", ".join(f"{k} {_short(md[k])}" for k in ("mode", "store") if k in md)
        echo(f"paint:         {md['recipe']} ({extra}; {md.get('generator', 'flakedb')} {md.get('flakedb_version', '')})")
    echo(f"nodes:         {d['nodes']} ({d['quadrature_nodes']} quadrature nodes + 2 zero nodes)")
    if d["kind"] == "h5" and md.get("wavelength_nm") and len(md["wavelength_nm"]) == d["channels"]:
        wl = md["wavelength_nm"]
        chans = f"{d['channels']} spectral bands {wl[0]:g}-{wl[-1]:g} nm"
    else:
        chans = f"{d['channels']} (stored {d['stored_channels']}; eval returns {', '.join(d['eval_channels'])})"
        if d["channels"] == 3 and d["kind"] == "bsdf":
            chans += f"; {md.get('rgb_space', 'linear sRGB assumed (not recorded)')}"
    echo(f"channels:      {chans}")
    pct = 100.0 * d["coefficients"] / max(d["coefficients_untruncated"], 1)
    echo(f"max order:     {d['max_order']} ({d['coefficients']} coefficients, {pct:.1f}% of a full table)")
    echo(f"eta:           {d['eta']:g} (eta_below / eta_above); alpha {d['alpha'][0]:g}, {d['alpha'][1]:g}")
    delta = d["delta"]
    if delta is None:
        echo("clear coat:    no mirror term: everything is in the table")
    else:
        fields = ", ".join(f"{k}={v}" for k, v in delta.items() if k != "kind")
        echo(f"clear coat:    smooth ({delta.get('kind')}, {fields}): its mirror reflection is NOT in the table; "
             f"flakedb render and the Mitsuba plugin add it back, pbrt-v3's `fourier` does not")
    echo("checks:")
    for c in d["checks"]:
        mark = {True: "ok  ", False: "warn" if c["check"] == "solver" else "FAIL", None: "note"}[c["ok"]]
        echo(f"  [{mark}] {c['text']}")
    for w in d["warnings"]:
        echo(f"  warning: {w}")
    if d["albedo"] and "albedo_Y" in d["albedo"][0]:
        echo("albedo (table only, light from above): luminance Y and CIELAB of the albedo colour")
        for row in d["albedo"]:
            L, a, b_ = row["albedo_Lab"]
            echo(f"  theta_i = {row['theta_i_deg']:4.0f} deg:  Y {row['albedo_Y']:.4f}   L* {L:6.2f}  a* {a:6.2f}  b* {b_:6.2f}")
    else:
        echo(f"albedo (R + T, table only, light from above), per channel {', '.join(d['eval_channels'])}:")
        for row in d["albedo"]:
            vals = "  ".join(f"{x:.5f}" for x in row["albedo"])
            echo(f"  theta_i = {row['theta_i_deg']:4.0f} deg (mu_i = {row['mu_i']:.4f}):  {vals}")
    short = {k: _short(v) for k, v in md.items() if k not in ("recipe", "mode", "store", "warnings")}
    if short:
        echo("metadata (--json for everything):")
        for k, v in short.items():
            echo(f"  {k}: {v}")


def _print_tensor(d):
    echo = click.echo
    echo(f"file:          {d['file']} ({d['size_bytes'] / 1e6:.2f} MB): {d['format']}")
    echo(f"variant:       {d['variant']}")
    if d.get("scale", 1.0) == 1.0:
        echo(f"use:           {json.dumps(d['use'])} in Mitsuba 3 (the values at x1)")
    else:
        echo(f"use:           NOT alone: {d['use_text']}")
    if d.get("theta_i_deg"):
        lo, hi, k = d["theta_i_deg"]
        echo(f"incidence:     {k} elevations {lo:.0f}-{hi:.0f} deg; half-vector grid {d['resolution'][0]} x {d['resolution'][1]}")
    if d.get("wavelengths_nm"):
        lo, hi, k = d["wavelengths_nm"]
        echo(f"wavelengths:   {k} from {lo:g} to {hi:g} nm")
    echo(f"description:   {d['description']}")
    echo("checks:")
    for c in d["checks"]:
        echo(f"  [{ {True: 'ok  ', False: 'FAIL', None: 'note'}[c['ok']] }] {c['text']}")


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON (everything, for machines).")
def info(file, as_json):
    """Describe a Fourier .bsdf, a flakedb .h5 or a Mitsuba 3 `measured` export: what paint, which
    channels and colour space, the smooth coat's mirror term, energy / colour / convergence checks in
    words, and the albedo at a few incident angles.  Exit status 1 when an energy, colour or data
    check fails."""
    try:
        d = describe(file)
    except BSDFFileError as e:
        raise FlakedbError(f"{e}\nflakedb info reads Fourier .bsdf files (SCATFUN), flakedb HDF5 BSDF files, "
                           f"Mitsuba 3 `measured` tensor files and the MaterialX, glTF and USD files flakedb "
                           f"exports.") from None
    if as_json:
        click.echo(json.dumps(d, indent=2, default=str))
    else:
        INFO_ROUTES[dispatch_file_kind(file)][1](d)
    failed = [c["check"] for c in d.get("checks", []) if c["ok"] is False and c["check"] != "solver"]
    if failed:  # a FAIL is an exit status, not only a word (issue 25); solver warnings stay warnings
        click.echo(f"flakedb info: {file}: check(s) failed: {', '.join(failed)}", err=True)
        raise SystemExit(1)


#: file kind (a key of :data:`flakedb.bsdf.dispatch.FILE_KINDS`) -> (describe(path) -> dict, print(dict)): the
#: one dispatch of ``flakedb info``; every kind of the registry has a route (tests/cli/test_info_render.py).
INFO_ROUTES = {
    "bsdf": (describe_fourier, _print_fourier),
    "h5": (describe_fourier, _print_fourier),
    "tensor": (describe_tensor, _print_tensor),
    "materialx": (describe_fit, _print_fit),
    "glb": (describe_gltf, _print_scene),
    "gltf": (describe_gltf, _print_scene),
    "usda": (describe_usda, _print_scene),
}

