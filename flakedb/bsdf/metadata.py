"""The metadata text block of a Fourier file: ``key=value`` lines, and the delta-term keys
(docs/bsdf-format.md, "Carrying a smooth clear coat's mirror reflection")."""

from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np

_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_KEY_LINE_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*=")


def check_delta(delta):
    """Refuse a malformed delta-term description (docs/bsdf-format.md, "Carrying a smooth clear coat's
    mirror reflection")."""
    if not isinstance(delta, dict) or "kind" not in delta:
        raise ValueError(f"delta must be None or a dict with a 'kind', e.g. {{'kind': 'fresnel', 'eta': 1.5}}; got {delta!r}")
    if delta["kind"] == "fresnel":
        eta = delta.get("eta")
        if not (isinstance(eta, (int, float)) and math.isfinite(eta) and eta > 0):
            raise ValueError(f"delta {{'kind': 'fresnel'}} needs a positive relative index 'eta', got {eta!r}")
    for k in delta:
        if not _KEY_RE.match(f"delta_{k}"):
            raise ValueError(f"delta field name {k!r} is not a valid metadata key")


# --------------------------------------------------------------------------------------------
# Metadata text
# --------------------------------------------------------------------------------------------
def _format_value(v) -> str:
    if isinstance(v, str) and "\n" not in v and "\r" not in v:
        try:
            json.loads(v)
        except (ValueError, TypeError):
            return v
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, np.ndarray):
        v = v.tolist()
    return json.dumps(v, ensure_ascii=False, separators=(", ", ": "), allow_nan=False)


def _parse_value(s: str):
    try:
        return json.loads(s)
    except ValueError:
        return s


def format_metadata(metadata: dict, delta: dict | None = None) -> str:
    """The ``.bsdf`` metadata text for ``metadata`` and the mirror term ``delta`` (module docstring)."""
    metadata = dict(metadata or {})
    lines = []
    clash = [k for k in metadata if k == "delta" or (isinstance(k, str) and k.startswith("delta_"))]
    if clash:
        raise ValueError(f"metadata keys {clash} are reserved for the mirror term; pass it as table.delta")
    if delta is not None:
        check_delta(delta)
        lines.append(f"delta={_format_value(delta['kind'])}")
        lines += [f"delta_{k}={_format_value(v)}" for k, v in delta.items() if k != "kind"]
    text = metadata.pop("text", None)
    for k, v in metadata.items():
        if not isinstance(k, str) or not _KEY_RE.match(k):
            raise ValueError(f"metadata key {k!r} must match [A-Za-z_][A-Za-z0-9_.-]*")
        lines.append(f"{k}={_format_value(v)}")
    if text is not None:
        if isinstance(text, str) and not any(_KEY_LINE_RE.match(ln) for ln in text.split("\n")):
            lines.append(text)
        else:
            lines.append(f"text={_format_value(text)}")
    return "\n".join(lines)


def parse_metadata(text: str) -> tuple[dict, dict | None]:
    """Inverse of :func:`format_metadata`: ``(metadata, delta)``; free-text lines go to ``"text"``.

    >>> text = format_metadata({"recipe": "silver metallic", "n_nodes": 100, "tag": "1.5"}, {"kind": "fresnel", "eta": 1.5})
    >>> print(text)
    delta=fresnel
    delta_eta=1.5
    recipe=silver metallic
    n_nodes=100
    tag="1.5"
    >>> parse_metadata(text)
    ({'recipe': 'silver metallic', 'n_nodes': 100, 'tag': '1.5'}, {'kind': 'fresnel', 'eta': 1.5})
    """
    md: dict[str, Any] = {}
    free = []
    if text:
        for line in text.split("\n"):
            if _KEY_LINE_RE.match(line):
                k, v = line.split("=", 1)
                md[k] = _parse_value(v)
            else:
                free.append(line)
    if free:
        md["text"] = "\n".join(free) if "text" not in md else md["text"] + "\n" + "\n".join(free)
    delta = None
    if "delta" in md:
        delta = {"kind": md.pop("delta")}
        for k in [k for k in md if k.startswith("delta_")]:
            delta[k[len("delta_"):]] = md.pop(k)
    return md, delta


# --------------------------------------------------------------------------------------------
# Types of the metadata fields flakedb's readers use (issue 25)
# --------------------------------------------------------------------------------------------
_TEXT_KEYS = ("recipe", "mode", "store", "generator", "flakedb_version", "rgb_space", "description",
              "gamut_mapping", "channels_from")
_NUMBER_KEYS = ("gamut_pairs_mapped", "gamut_max_dE00")
_SOLVER_NUMBERS = ("order_tail", "order_tol", "tail", "renorm_max_dev")
_SOLVER_INTS = ("orders", "orders_available", "n_phi")
_SOLVER_FLAGS = ("order_converged", "converged")
#: Wavelengths a metadata ``wavelength_nm`` may hold [nm] (far UV to far IR: anything else is corrupt).
WAVELENGTH_RANGE_NM = (100.0, 100_000.0)


def _is_number(v):
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_solver_part(where, d):
    for k in _SOLVER_NUMBERS:
        if k in d and d[k] is not None and not _is_number(d[k]):
            raise ValueError(f"field {where}.{k} = {d[k]!r} must be a finite number")
    for k in _SOLVER_INTS:
        if k in d and d[k] is not None and not (isinstance(d[k], int) and not isinstance(d[k], bool)):
            raise ValueError(f"field {where}.{k} = {d[k]!r} must be an integer")
    for k in _SOLVER_FLAGS:
        if k in d and d[k] is not None and not isinstance(d[k], bool):
            raise ValueError(f"field {where}.{k} = {d[k]!r} must be true, false or null")


def check_known_metadata(md):
    """Refuse (ValueError naming the field) metadata whose fields that flakedb reads (``info``,
    ``render``, the Mitsuba export) have the wrong type: texts, counts, the spectral grid
    ``wavelength_nm`` (finite numbers in :data:`WAVELENGTH_RANGE_NM`), ``warnings`` (a list of texts)
    and the ``solver_info`` record.  Unknown fields are kept as they are."""
    if not isinstance(md, dict):
        raise ValueError(f"must be a mapping of fields, got {type(md).__name__}")
    for k in _TEXT_KEYS:
        if k in md and md[k] is not None and not isinstance(md[k], str):
            raise ValueError(f"field {k} = {md[k]!r:.60} must be text")
    for k in _NUMBER_KEYS:
        if k in md and md[k] is not None and not _is_number(md[k]):
            raise ValueError(f"field {k} = {md[k]!r:.60} must be a finite number")
    if "n_nodes" in md and not (isinstance(md["n_nodes"], int) and not isinstance(md["n_nodes"], bool)
                                and 2 <= md["n_nodes"] <= 4096):
        raise ValueError(f"field n_nodes = {md['n_nodes']!r:.60} must be an integer node count in 2 ≤ n ≤ 4096")
    wl = md.get("wavelength_nm")
    if wl is not None:
        lo, hi = WAVELENGTH_RANGE_NM
        if not (isinstance(wl, list) and all(_is_number(x) and lo <= x <= hi for x in wl)):
            raise ValueError(f"field wavelength_nm must be a list of wavelengths in {lo:g}-{hi:g} nm, got "
                             f"{wl!r:.60}")
    w = md.get("warnings")
    if w is not None and not (isinstance(w, list) and all(isinstance(x, str) for x in w)):
        raise ValueError(f"field warnings must be a list of texts, got {w!r:.60}")
    si = md.get("solver_info")
    if si is not None:
        if not isinstance(si, dict):
            raise ValueError(f"field solver_info must be a mapping, got {type(si).__name__}")
        groups = si.get("groups")
        if groups is not None and not (isinstance(groups, list) and all(isinstance(g, dict) for g in groups)):
            raise ValueError("field solver_info.groups must be a list of mappings")
        for gi, g in enumerate(groups or [si]):
            where = "solver_info" if groups is None else f"solver_info.groups[{gi}]"
            _check_solver_part(where, g)
            for k, sl in g.items():
                if isinstance(k, str) and k.startswith("slab"):
                    if not isinstance(sl, dict) or not k[4:].isdigit():
                        raise ValueError(f"field {where}.{k} must be a mapping named slab<index>")
                    _check_solver_part(f"{where}.{k}", sl)
        if groups is not None:
            _check_solver_part("solver_info", si)
