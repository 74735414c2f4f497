"""The coat kept on the fast route: Mitsuba's ``measured`` table plus the smooth coat's Fresnel mirror.

A Fourier file of a paint with a smooth clear coat holds everything except the first-surface
mirror reflection ``F(θ_i; η) δ(ω_o - mirror(ω_i))`` (docs/renderers.md).  The paint is the **sum**
``f = f_table + F δ``.  Mitsuba 3 has no additive BSDF and no ``coating`` plugin (Mitsuba 0.6 had
one); its ``blendbsdf`` is the convex combination ``(1 - w) f_0 + w f_1`` with a weight that does not
depend on direction.  The sum is exactly ``blendbsdf`` at ``w = 1/2`` of two halves written at
twice their value:

* ``f_0 = 2 f_table``: the ``measured`` tensor at ``scale = 2`` (:func:`flakedb.render.mitsuba.
  measured.measured_tensors`; the sampling map is relative and unchanged);
* ``f_1 = 2 F δ``: Mitsuba's ``roughconductor`` with ``eta = η``, ``k = 0``,
  ``specular_reflectance = 2`` and GGX α = :data:`COAT_ALPHA` = 0.01 (a near-mirror: see
  :data:`COAT_ALPHA` for why not the smooth ``conductor``).  A conductor's Fresnel reflectance at k = 0 is the dielectric one
  (Born & Wolf §1.5.2 / §14.2: the complex formula with an imaginary part 0), with no
  transmission; the ``dielectric`` plugin cannot be used because it also refracts.

``blendbsdf`` samples ``f_0`` or ``f_1`` with probability 1/2 each and weights by 1/(1/2) · 1/2:
unbiased.  The test renders the furnace sphere of both (:mod:`flakedb.render.mitsuba.furnace`) and
checks it against the table's albedo + F.

A rough coat (``alpha > 0``) has no mirror term: its lobe is in the table, and the coated export is
the plain ``measured`` file.

pbrt-v3 has the same two pieces (``Material "mix"`` is ``amount · m1 + (1 - amount) · m2`` over the
BxDFs, ``glass`` with ``Kr = 2``, ``Kt = 0`` is ``2 F δ``, ``fourier`` reads a table written at twice
its value): :func:`pbrt_coated_scene` writes that material (not run: pbrt-v3 is not installable here).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_path
from flakedb.bsdf import open_bsdf, write_bsdf
from flakedb.render.mitsuba.directions import MeasuredExportError, delta_reflectance
from flakedb.render.mitsuba.measured import FLOOR_DEFAULT, N_THETA_DEFAULT, RES_DEFAULT, export_measured

#: The factor each half of the blend is written at (the blend weight is 1 / COAT_BLEND_SCALE).
COAT_BLEND_SCALE = 2.0
#: GGX α of the coat lobe.  Not a delta: Mitsuba 3.9.1's ``blendbsdf`` of a delta ``conductor`` and
#: the glossy ``measured`` renders the furnace sphere 8-17 % dark (measured, path integrator; each
#: half alone and a blend of either with itself are right), while ``roughconductor`` at α = 0.01
#: agrees with albedo + F to 0.2 %.  A sun's highlight is then 0.01 wide instead of a point.
COAT_ALPHA = 0.01


def coated_bsdf_dict(tensor_filename: str, delta) -> dict:
    """The Mitsuba 3 BSDF dict of the coated route for a ``measured`` file written at scale 2 and the
    file's mirror term ``delta`` (``{"kind": "fresnel", "eta": η}`` or None).  Without a mirror term
    the tensor is returned as is (its values are then at scale 1).

    The blend gives each part unit weight: the coat's mirror (weight 1/s × reflectance s) and the body
    ((1 − 1/s) × the file's values at scale s):

    >>> d = coated_bsdf_dict("paint.bsdf", {"kind": "fresnel", "eta": 1.5})
    >>> d["type"], d["weight"] * d["coat"]["specular_reflectance"], (1 - d["weight"]) * COAT_BLEND_SCALE, d["coat"]["eta"]
    ('blendbsdf', 1.000000000000, 1.000000000000, 1.5)
    >>> coated_bsdf_dict("paint.bsdf", None)
    {'type': 'measured', 'filename': 'paint.bsdf'}
    """
    if delta is None:
        return {"type": "measured", "filename": str(tensor_filename)}
    delta_reflectance(delta, 1.0)                       # refuses an unknown kind
    s = COAT_BLEND_SCALE
    return {
        "type": "blendbsdf",
        "weight": 1.0 / s,
        "body": {"type": "measured", "filename": str(tensor_filename)},
        # plain floats: a uniform spectrum in every variant (an "rgb" reflectance > 1 is refused)
        "coat": {"type": "roughconductor", "distribution": "ggx", "alpha": COAT_ALPHA, "eta": float(delta["eta"]),
                 "k": 0.0, "specular_reflectance": s},
    }


def _xml(d: dict, indent: str = "    ") -> str:
    """A Mitsuba 3 XML ``<bsdf>`` element of :func:`coated_bsdf_dict`'s dict (the same plugins)."""
    if d["type"] == "measured":
        return f'{indent}<bsdf type="measured">\n{indent}    <string name="filename" value="{d["filename"]}"/>\n{indent}</bsdf>'
    c = d["coat"]
    eta = c["eta"]
    s = c["specular_reflectance"]
    return "\n".join([
        f'{indent}<bsdf type="blendbsdf">',
        f'{indent}    <float name="weight" value="{d["weight"]:g}"/>',
        f'{indent}    <bsdf type="measured">',
        f'{indent}        <string name="filename" value="{d["body"]["filename"]}"/>',
        f'{indent}    </bsdf>',
        f'{indent}    <bsdf type="roughconductor">',
        f'{indent}        <string name="distribution" value="ggx"/>',
        f'{indent}        <float name="alpha" value="{c["alpha"]:g}"/>',
        f'{indent}        <float name="eta" value="{eta:.9g}"/>',
        f'{indent}        <float name="k" value="0"/>',
        f'{indent}        <float name="specular_reflectance" value="{s:g}"/>',
        f'{indent}    </bsdf>',
        f'{indent}</bsdf>'])


def export_coated(src, out, variant: str = "rgb", res: int = RES_DEFAULT, n_theta: int = N_THETA_DEFAULT,
                  floor: float = FLOOR_DEFAULT) -> dict:
    """Write the coated Mitsuba 3 route of the Fourier file ``src``: ``out`` (the ``measured`` tensor,
    at scale 2 when there is a mirror term), ``out`` + ``.json`` (the BSDF dict for ``mi.load_dict``)
    and ``out`` + ``.xml`` (the same as a Mitsuba 3 XML element).  Returns the export summary of
    :func:`flakedb.render.mitsuba.measured.export_measured` with ``bsdf`` (the dict), ``json``,
    ``xml`` and ``kept`` added; nothing is ``dropped`` but transmission.  The .json and .xml name the
    tensor by its absolute path (they load from any working directory; move the three files together
    and re-export, or edit the path)."""
    b = open_bsdf(src)
    scale = COAT_BLEND_SCALE if b.delta is not None else 1.0
    desc = (f"flakedb coated-route export of {Path(src).name}: front-side reflection of the table at scale "
            f"{scale:g}, to be blended (weight 1/{scale:g}) with a conductor k=0 coat of eta "
            f"{b.delta['eta'] if b.delta else '-'}; see the .json / .xml next to this file")
    s = export_measured(src, out, variant=variant, res=res, n_theta=n_theta, floor=floor, scale=scale,
                        description=desc)
    out = Path(out)
    # the tensor by its absolute path: Mitsuba resolves a relative one against the working directory
    # (mi.load_dict) or the scene file's folder, so a bare name loads from the tensor's folder only
    d = coated_bsdf_dict(str(out.resolve()), b.delta)
    p_json, p_xml = out.with_name(out.name + ".json"), out.with_name(out.name + ".xml")
    with atomic_path(p_json, suffix="") as tmp:
        Path(tmp).write_text(json.dumps(d, indent=2) + "\n", encoding="utf-8")
    with atomic_path(p_xml, suffix="") as tmp:
        Path(tmp).write_text("<!-- flakedb coated route: paste inside a <shape> of a Mitsuba 3 scene -->\n"
                             + _xml(d, "") + "\n", encoding="utf-8")
    dropped = dict(s["dropped"])
    kept = {}
    if b.delta is not None:
        kept = {"delta": dropped.pop("delta"), "delta_albedo": dropped.pop("delta_albedo")}
    s.update({"bsdf": d, "json": str(p_json), "xml": str(p_xml), "kept": kept, "dropped": dropped})
    return s


def pbrt_coated_scene(src, out_bsdf, name: str = "flakedb_paint") -> dict:
    """pbrt-v3 route with the coat: write the RGB table of ``src`` at twice its value to ``out_bsdf``
    (a ``.bsdf``) and ``out_bsdf`` + ``.pbrt``: three ``MakeNamedMaterial`` lines, ``name`` =
    ``mix`` (amount 0.5) of ``glass`` (Kr 2, Kt 0, eta = the file's delta eta) and ``fourier`` (the
    doubled table).  A file without a mirror term gets the ``fourier`` material alone at scale 1.
    Returns {"bsdf", "pbrt", "material"}."""
    b = open_bsdf(src)
    if b.n_channels not in (1, 3) or (b.kind == "h5" and tuple(b.channels) not in (("R", "G", "B"), ("Y",))
                                      and b.n_channels != 1):
        raise MeasuredExportError(f"{src}: pbrt-v3's fourier material reads mono or RGB tables; this file holds "
                                  f"{', '.join(b.channels)} (export the .bsdf that compose wrote instead)")
    t = b.to_table()
    scale = COAT_BLEND_SCALE if b.delta is not None else 1.0
    md = dict(t.metadata or {})
    md["pbrt_mix_scale"] = scale
    t2 = t.replace(stored=np.asarray(t.stored) * scale, metadata=md)
    out_bsdf = Path(out_bsdf)
    write_bsdf(out_bsdf, t2, truncation=0.0)
    if b.delta is None:
        text = f'MakeNamedMaterial "{name}" "string type" "fourier" "string bsdffile" "{out_bsdf.name}"\n'
    else:
        eta = float(b.delta["eta"])
        text = (f'# flakedb: the table at x{scale:g} mixed half-and-half with a smooth dielectric mirror (Kr {scale:g}, '
                f'Kt 0): f = f_table + F(eta {eta:.6g}) delta\n'
                f'MakeNamedMaterial "{name}_body" "string type" "fourier" "string bsdffile" "{out_bsdf.name}"\n'
                f'MakeNamedMaterial "{name}_coat" "string type" "glass" "rgb Kr" [{scale:g} {scale:g} {scale:g}] '
                f'"rgb Kt" [0 0 0] "float eta" {eta:.9g}\n'
                f'MakeNamedMaterial "{name}" "string type" "mix" "string namedmaterial1" "{name}_coat" '
                f'"string namedmaterial2" "{name}_body" "rgb amount" [{1 / scale:g} {1 / scale:g} {1 / scale:g}]\n')
    p = out_bsdf.with_name(out_bsdf.name + ".pbrt")
    with atomic_path(p, suffix="") as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return {"bsdf": str(out_bsdf), "pbrt": str(p), "material": name}
