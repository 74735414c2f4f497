"""A recipe against its JSON Schema (schemas/recipe.schema.json): the validator and its messages in words
(field path, value, allowed range, a hint).
"""

from __future__ import annotations

import difflib
import json
from pathlib import Path

import jsonschema

from flakedb.paint.recipe_model import FORMAT_VERSION
from flakedb.resources import PACKAGE_DIR, SCHEMAS_DIR


def repo_root() -> Path:
    """The package folder (holds ``catalog/`` and ``schemas/``, see :mod:`flakedb.resources`)."""
    return PACKAGE_DIR


def schema_path() -> Path:
    return SCHEMAS_DIR / "recipe.schema.json"


_SCHEMA = None


def _schema():
    global _SCHEMA
    if _SCHEMA is None:
        with open(schema_path(), encoding="utf-8") as f:
            _SCHEMA = json.load(f)
    return _SCHEMA


def fmt_path(parts) -> str:
    """``['layers', 1, 'basecoat', 'particles', 0]`` → ``layers[1].basecoat.particles[0]``.

    >>> fmt_path(["layers", 1, "basecoat", "particles", 0]), fmt_path([])
    ('layers[1].basecoat.particles[0]', '(top level)')
    """
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


def _range_text(schema) -> str | None:
    lo = hi = None
    if "minimum" in schema:
        lo = f"{schema['minimum']:g} ≤ value"
    if "exclusiveMinimum" in schema:
        lo = f"{schema['exclusiveMinimum']:g} < value"
    if "maximum" in schema:
        hi = f"value ≤ {schema['maximum']:g}"
    if "exclusiveMaximum" in schema:
        hi = f"value < {schema['exclusiveMaximum']:g}"
    if lo and hi:
        return lo + hi[len("value"):]
    return lo or hi


def json_short(v) -> str:
    s = json.dumps(v, default=str)
    return s if len(s) <= 60 else s[:57] + "..."


def _looks_numeric(text) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _describe_error(err) -> str:
    path = fmt_path(err.absolute_path)
    v = err.validator
    hint = err.schema.get("description") if isinstance(err.schema, dict) else None
    if v in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
        msg = f"value {err.instance!r} is outside the allowed range {_range_text(err.schema)}"
    elif v == "additionalProperties":
        allowed = sorted((err.schema.get("properties") or {}).keys())
        extra = sorted(set(err.instance) - set(allowed)) if isinstance(err.instance, dict) else []
        parts = []
        for k in extra:
            close = difflib.get_close_matches(str(k), allowed, n=1)
            parts.append(f"unknown key {k!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        msg = "; ".join(parts) + f"; allowed keys: {', '.join(allowed)}"
    elif v == "required":
        msg = err.message.replace("is a required property", "is missing (required)")
    elif v == "enum":
        msg = f"value {json_short(err.instance)} is not one of {', '.join(map(str, err.validator_value))}"
    elif v == "const":
        if path == "flakedb" and str(err.instance).strip() == str(FORMAT_VERSION):
            msg = (f"recipe format version {json_short(err.instance)} is a {type(err.instance).__name__}, not "
                   f"the number {FORMAT_VERSION} (write `flakedb: {FORMAT_VERSION}` without quotes)")
        elif path == "flakedb":
            msg = (f"recipe format version {json_short(err.instance)} is not supported; this flakedb reads "
                   f"version {FORMAT_VERSION} (write `flakedb: {FORMAT_VERSION}` as the first line)")
        else:
            msg = f"value {json_short(err.instance)} must be {json_short(err.validator_value)}"
    elif v == "type":
        msg = f"value {json_short(err.instance)} has the wrong type; expected {err.validator_value}"
        if isinstance(err.instance, str) and _looks_numeric(err.instance):
            msg += " (YAML reads a number without a '.' before its exponent, like 1e-3, as text: write 1.0e-3)"
    elif v == "multipleOf":
        msg = f"value {err.instance!r} must be a multiple of {err.validator_value:g}"
    elif v in ("minProperties", "maxProperties"):
        allowed = sorted((err.schema.get("properties") or {}).keys())
        msg = f"{json_short(err.instance)} must have exactly one of the keys {', '.join(allowed)}"
    elif v == "pattern":
        msg = f"value {json_short(err.instance)} does not match the pattern {err.validator_value}"
    elif v in ("minItems", "maxItems"):
        n = len(err.instance) if isinstance(err.instance, (list, dict, str)) else "?"
        bound = "at least" if v == "minItems" else "at most"
        msg = f"{n} entries; the allowed range is {bound} {err.validator_value} entries"
    elif v in ("minLength", "maxLength"):
        n = len(err.instance) if isinstance(err.instance, str) else "?"
        bound = "at least" if v == "minLength" else "at most"
        msg = f"value {json_short(err.instance)} has {n} characters; the allowed length is {bound} {err.validator_value}"
    else:
        text = err.message if len(err.message) <= 200 else err.message[:197] + "..."
        msg = f"{json_short(err.instance)}: {text}"
    return f"{path}: {msg}" + (f" (hint: {hint})" if hint else "")


def schema_problems(doc) -> list[str]:
    """Every schema violation of a parsed recipe document as ``path: message (hint: …)``."""
    schema = _schema()
    validator = jsonschema.Draft202012Validator(schema)

    out = []
    errors = sorted(validator.iter_errors(doc), key=lambda e: [str(p) for p in e.absolute_path])
    for err in errors:
        if err.validator in ("oneOf", "anyOf") and err.context:
            # the branch that got furthest (deepest path), else a summary naming the alternatives
            best = max(err.context, key=lambda e: (len(e.absolute_path), e.validator != "type"))
            if len(best.absolute_path) > len(err.absolute_path):
                out.append(_describe_error(best))
                continue
            hint = err.schema.get("description") if isinstance(err.schema, dict) else None
            what = "is not valid"
            if isinstance(err.instance, str) and _looks_numeric(err.instance):  # a number or a spectrum, given text
                what = ("has the wrong type; expected a number (YAML reads a number without a '.' before its "
                        "exponent, like 1e-3, as text: write 1.0e-3)")
            out.append(f"{fmt_path(err.absolute_path)}: value {json_short(err.instance)} {what}"
                       + (f" (hint: {hint})" if hint else ""))
            continue
        out.append(_describe_error(err))
    # one error per path and message
    seen, uniq = set(), []
    for p in out:
        if p not in seen:
            seen.add(p)
            uniq.append(p)
    return uniq
