"""Many recipes against many targets in one table (docs/batches-and-plots.md).

:func:`compare_batch` composes each recipe **once** (:func:`flakedb.match.fit.predict` at the union
of the geometries of the targets it is paired with) and compares it with every paired target, so
10 recipes against 10 targets cost 10 composes, not 100.  Pairing: every recipe with every target
(``pairs=None``), or an explicit list of (recipe index, target index).  Without targets it is a
table of predicted colours at a geometry set (the batch form of ``compare --write-csv``).

The results are :class:`Comparison` records; :func:`long_rows` flattens them to one row per
(recipe, target, geometry) and :func:`summary_rows` to one row per pair; :func:`to_dataframe`
returns the long table as a pandas DataFrame (pandas is an optional dependency: ``pip install
flakedb[dataframe]``).  Colour conditions: the caller's, else each target's, else the defaults
(:func:`flakedb.colour.settings.resolve`), per pair.

A target with texture columns (:mod:`flakedb.match.texture`) is also compared on them: the
comparison's ``texture`` rows (predicted, target, difference, tolerance, passed per index) count in
``passed``, the summary's ``texture_failed``, and :func:`write_table` writes them beside the long table
as ``<table>-texture.csv`` (:data:`TEXTURE_COLUMNS`).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_write_text
from flakedb.colour.geometry import compact
from flakedb.colour.geometry import key as geometry_key
from flakedb.colour.geometry import label as geometry_label
from flakedb.colour.settings import DEFAULT_MAX_DE00, GEOMETRY_SETS, for_target, resolve
from flakedb.colour.tolerance import PerAngleLimits, lab_differences, lch, shade_words
from flakedb.match.fit import Prediction, compare_texture, predict
from flakedb.match.texture import DEFAULT_TEXTURE_TOLERANCE
from flakedb.safeio import FileTooLargeError, read_limited


@dataclass
class Comparison:
    """One recipe against one target (or, with ``target`` None, the recipe's predicted colours)."""

    recipe: str
    target: str | None
    geometries: np.ndarray          # (G, 2)
    lab_pred: np.ndarray            # (G, 3)
    lab_target: np.ndarray | None   # (G, 3)
    observer: str
    illuminant: str
    evaluation: dict | None         # the tolerance scheme's evaluate()
    differences: dict | None        # flakedb.colour.tolerance.lab_differences
    prediction: Prediction          # reflectance factors at these geometries
    target_reflectance: np.ndarray | None = None
    target_wavelength_nm: np.ndarray | None = None
    texture: list = field(default_factory=list)   # flakedb.match.texture.evaluate_texture rows ([]: none)
    sparkle: bool | None = None                   # the recipe's flakes sparkle (None: no texture columns)

    @property
    def passed(self) -> bool | None:
        if self.evaluation is None:
            return None
        return bool(self.evaluation["passed_all"]) and all(r["passed"] for r in self.texture)

    @property
    def max_de(self) -> float | None:
        return None if self.differences is None else float(np.max(self.differences["dE00"]))


def _key(g) -> tuple:
    return geometry_key(g)


def compare_batch(recipes, targets=(), pairs=None, observer=None, illuminant=None, tolerance=None,
                  geometry_set=None, n=None, catalog=None, store_for=None, raw=False, log=None,
                  texture_tolerance=DEFAULT_TEXTURE_TOLERANCE) -> list:
    """Compare every paired (recipe, target) (module docstring); returns a list of :class:`Comparison`.

    ``recipes``: :class:`flakedb.paint.recipe.Recipe` objects; ``targets``: :class:`flakedb.match.targets.Target`
    objects; ``tolerance``: a scheme with ``evaluate`` (default ΔE00 ≤ :data:`DEFAULT_MAX_DE00`);
    ``store_for``: None or a callable recipe → open store version (or None); ``log``: one line per compose;
    ``texture_tolerance``: the relative tolerance of targets' texture columns (:mod:`flakedb.match.texture`).
    """
    log = log or (lambda s: None)
    targets = list(targets)
    scheme = tolerance if tolerance is not None else PerAngleLimits(default=DEFAULT_MAX_DE00)
    if targets:
        pairs = [(i, j) for i in range(len(recipes)) for j in range(len(targets))] if pairs is None else list(pairs)
    else:
        pairs = [(i, None) for i in range(len(recipes))]
    out = []
    for i, rec in enumerate(recipes):
        mine = [j for ii, j in pairs if ii == i]
        if not mine:
            continue
        if targets:
            union = {}   # insertion-ordered set: linear in the number of points (a set rebuilt per point was quadratic)
            for j in mine:
                for g in targets[j].geometries:
                    union.setdefault(_key(g), None)
            geoms = compact([k + (0.0,) * (3 - len(k)) for k in union])
        else:
            geoms = compact(GEOMETRY_SETS[resolve(geometry_set=geometry_set).geometry_set])
        version = store_for(rec) if store_for is not None else None
        pred = predict(rec, geoms, n, catalog, version, raw)
        log(f"composed {rec.name} ({pred.mode}, n = {pred.n}) [{i + 1}/{len(recipes)}]")
        index = {_key(g): k for k, g in enumerate(geoms)}
        for j in mine:
            t = None if j is None else targets[j]
            if t is None:
                cs = resolve(observer, illuminant, geometry_set, pred.mode)
                lab = pred.lab(cs.observer, cs.illuminant)
                out.append(Comparison(rec.name, None, geoms, lab, None, cs.observer, cs.illuminant, None, None, pred))
                continue
            cs = for_target(pred.mode, t, observer, illuminant)
            rows = [index[_key(g)] for g in t.geometries]
            sub = Prediction(t.geometries, pred.rf[rows], pred.mode, pred.wavelength_nm, pred.n)
            lab = sub.lab(cs.observer, cs.illuminant)
            lab_t = t.lab_under(cs.observer, cs.illuminant)
            tex, sparkle = compare_texture(rec, pred, t, texture_tolerance)
            out.append(Comparison(rec.name, t.label, compact(t.geometries), lab, lab_t,
                                  cs.observer, cs.illuminant, scheme.evaluate(t.geometries, lab_t, lab),
                                  lab_differences(lab_t, lab), sub, t.reflectance, t.wavelength_nm, tex, sparkle))
    return out


LONG_COLUMNS = ("recipe", "target", "illumination_deg", "aspecular_deg", "azimuth_deg", "observer", "illuminant",
                "L_target", "a_target", "b_target", "L", "a", "b", "dL", "dC", "dH", "dE00", "limit", "passed",
                "C_target", "h_target", "C", "h", "formula", "dE", "shade")
SUMMARY_COLUMNS = ("recipe", "target", "geometries", "max_dE00", "worst_geometry", "failed", "texture_failed", "passed",
                   "formula", "max_dE")
TEXTURE_COLUMNS = ("recipe", "target", "index", "unit", "predicted", "target_value", "difference", "tolerance",
                   "passed")


def long_rows(comparisons) -> list:
    """One dict per (recipe, target, geometry), keys :data:`LONG_COLUMNS` (None where not applicable)."""
    rows = []
    for c in comparisons:
        for k, g in enumerate(c.geometries):
            r = {"recipe": c.recipe, "target": c.target, "illumination_deg": float(g[0]), "aspecular_deg": float(g[1]),
                 "azimuth_deg": float(g[2]) if len(g) > 2 else 0.0,
                 "observer": c.observer, "illuminant": c.illuminant,
                 "L": float(c.lab_pred[k, 0]), "a": float(c.lab_pred[k, 1]), "b": float(c.lab_pred[k, 2]),
                 "C": float(lch(c.lab_pred[k])[1]), "h": float(lch(c.lab_pred[k])[2])}
            if c.lab_target is not None:
                d, ev = c.differences, c.evaluation
                r.update({"L_target": float(c.lab_target[k, 0]), "a_target": float(c.lab_target[k, 1]),
                          "b_target": float(c.lab_target[k, 2]), "dL": float(d["dL"][k]), "dC": float(d["dC"][k]),
                          "dH": float(d["dH"][k]), "dE00": float(d["dE00"][k]), "limit": float(ev["limit"][k]),
                          "passed": bool(ev["passed"][k]), "C_target": float(lch(c.lab_target[k])[1]),
                          "h_target": float(lch(c.lab_target[k])[2]), "formula": ev.get("formula", "dE00"),
                          "dE": float(ev["value"][k]), "shade": shade_words(c.lab_target[k], c.lab_pred[k])[0]})
            rows.append({col: r.get(col) for col in LONG_COLUMNS})
    return rows


def summary_rows(comparisons) -> list:
    """One dict per compared pair, keys :data:`SUMMARY_COLUMNS`."""
    rows = []
    for c in comparisons:
        if c.differences is None:
            continue
        de = c.differences["dE00"]
        w = int(np.argmax(de))
        rows.append({"recipe": c.recipe, "target": c.target, "geometries": int(len(de)), "max_dE00": float(de[w]),
                     "worst_geometry": geometry_label(c.geometries[w]),
                     "failed": int(np.sum(~c.evaluation["passed"])),
                     "texture_failed": sum(not r["passed"] for r in c.texture) if c.texture else None,
                     "passed": c.passed, "formula": c.evaluation.get("formula", "dE00"),
                     "max_dE": float(np.max(c.evaluation["value"]))})
    return rows


def texture_rows(comparisons) -> list:
    """One dict per (recipe, target, texture index), keys :data:`TEXTURE_COLUMNS`."""
    return [{"recipe": c.recipe, "target": c.target, "index": r["index"], "unit": r["unit"],
             "predicted": r["predicted"], "target_value": r["target"], "difference": r["difference"],
             "tolerance": r["tolerance"], "passed": r["passed"]} for c in comparisons for r in c.texture]


def texture_table_path(path) -> Path:
    """Where :func:`write_table` puts the texture rows of the long table ``path``: ``<stem>-texture.csv``."""
    p = Path(path)
    return p.with_name(f"{p.stem}-texture{p.suffix or '.csv'}")


def to_dataframe(comparisons, summary=False):
    """The long (or, with ``summary``, the per-pair) table as a pandas DataFrame."""
    import pandas as pd  # lazy: optional dependency (flakedb[dataframe]), only the DataFrame API needs it

    if summary:
        return pd.DataFrame(summary_rows(comparisons), columns=list(SUMMARY_COLUMNS))
    return pd.DataFrame(long_rows(comparisons), columns=list(LONG_COLUMNS))


def format_rows(rows, columns) -> str:
    """CSV text of rows (floats to 4 decimals; texture values, which span decades, to 6 significant digits).

    >>> print(format_rows([{"recipe": "a", "dE00": 0.123456, "note": None}], ["recipe", "dE00", "note"]), end="")
    recipe,dE00,note
    a,0.1235,
    """
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(columns)
    for r in rows:
        w.writerow(["" if r[c] is None else (_fmt(c, r[c]) if isinstance(r[c], float) else r[c]) for c in columns])
    return out.getvalue()


def _fmt(column, v) -> str:
    return f"{v:.6g}" if column in ("predicted", "target_value", "difference", "tolerance") else f"{v:.4f}"


def write_table(path, comparisons, summary=False) -> str:
    """Write the long (or summary) table as CSV, atomically; returns the path.  The long table's texture
    rows, when a target has texture columns, go to :func:`texture_table_path` beside it."""
    rows, cols = (summary_rows(comparisons), SUMMARY_COLUMNS) if summary else (long_rows(comparisons), LONG_COLUMNS)
    atomic_write_text(Path(path), format_rows(rows, cols))
    tex = texture_rows(comparisons)
    if tex and not summary:
        atomic_write_text(texture_table_path(path), format_rows(tex, TEXTURE_COLUMNS))
    return str(path)


def expand_paths(items, suffixes) -> list:
    """Files named by ``items``: a file itself, or a folder's files with one of ``suffixes`` (sorted)."""
    out = []
    for it in items:
        p = Path(it)
        if p.is_dir():
            found = sorted(q for q in p.iterdir() if q.is_file() and q.suffix.lower() in suffixes)
            if not found:
                raise ValueError(f"{p}: no {' / '.join(suffixes)} file in this folder")
            out += found
        else:
            out.append(p)
    return out


#: Largest --pairs list read [bytes], and most pairs in it.
MAX_PAIR_LIST_BYTES = 10_000_000
MAX_PAIRS = 100_000


def read_pair_list(path) -> list:
    """(recipe path, target path, cxf object or None) from a CSV with header ``recipe,target[,cxf_object]``;
    relative paths are relative to the list's folder."""
    p = Path(path)
    try:   # a regular file only (a FIFO blocked forever, /dev/zero never ended), at most MAX_PAIR_LIST_BYTES
        text = read_limited(p, MAX_PAIR_LIST_BYTES).decode("utf-8-sig")
    except FileNotFoundError:
        raise ValueError(f"{p}: no such file") from None
    except FileTooLargeError as exc:
        raise ValueError(f"{p}: {exc.size:,} bytes or more; the limit is {MAX_PAIR_LIST_BYTES:,} bytes for a --pairs "
                         f"list ({MAX_PAIRS:,} pairs at most)") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{p}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except OSError as exc:
        raise ValueError(f"{p}: cannot read the file ({exc.strerror or exc})") from None
    rows = [r for r in csv.reader(io.StringIO(text)) if r and not r[0].lstrip().startswith("#")]
    if not rows or [h.strip() for h in rows[0][:2]] != ["recipe", "target"]:
        raise ValueError(f"{p}: the first line must be the header recipe,target[,cxf_object]")
    out = []
    for ln, r in enumerate(rows[1:], 2):
        if len(r) < 2 or not r[0].strip() or not r[1].strip():
            raise ValueError(f"{p} row {ln}: give a recipe and a target")
        obj = r[2].strip() if len(r) > 2 and r[2].strip() else None
        out.append((p.parent / r[0].strip(), p.parent / r[1].strip(), obj))
    if not out:
        raise ValueError(f"{p}: no rows after the header")
    if len(out) > MAX_PAIRS:
        raise ValueError(f"{p}: {len(out):,} pairs; the limit is {MAX_PAIRS:,} (each pair is a comparison)")
    return out
