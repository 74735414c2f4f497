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
