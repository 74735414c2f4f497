"""Multi-angle colour targets: the CSV layout, its reader and writer, and the standard geometries.

The CSV layout (docs/colour-matching.md has an example)
-------------------------------------------------------
UTF-8 text.  Lines starting with ``#`` are comments; a comment of the form ``# key: value`` sets an
option (keys: ``observer`` 2 or 10, ``illuminant`` D65 / A / F11 / …, ``reflectance`` fraction or
percent, ``name``; unknown keys are kept as notes).  The first other line is the header, then one
row per geometry::

    # observer: 10
    # illuminant: D65
    illumination_deg,aspecular_deg,L*,a*,b*
    45,-15,92.31,-1.20,3.05
    45,15,80.02,-0.95,2.71
    …

Columns: ``illumination_deg`` (angle of the illuminator from the normal) and ``aspecular_deg``
(the detector's angle from the specular direction, positive towards the illuminator: ASTM
E2194's sign, so the detector looks from θ_v = illumination − aspecular off the normal, on the
illuminator's side when negative; :func:`flakedb.report.multiangle_geometry`), then either

* ``L*``, ``a*``, ``b*`` (``L``, ``a``, ``b`` also accepted): CIELAB under the observer and
  illuminant of the options (default D65 / 10°, :mod:`flakedb.colour.settings`;
  said so in the target), or
* ``R_380``, ``R_390``, …: spectral reflectance factors (fraction, 1 = perfect white diffuser, or
  percent with ``# reflectance: percent``) on any uniform nm grid of step 1–20 nm; then the target's
  L*a*b* can be computed for any observer and illuminant the grid allows.

An optional third column ``azimuth_deg`` makes a geometry out of plane (0: in plane): X-Rite's notation,
``45as25az90`` is ``45,25,90`` (:mod:`flakedb.colour.geometry`; the set ``xrite19`` of
:mod:`flakedb.colour.settings` has eight such geometries).

Texture columns (optional; :mod:`flakedb.match.texture`, docs/texture.md §9): ``sparkle_area_<L>``,
``sparkle_intensity_<L>``, ``glints_per_mm2_<L>`` (light at L°) and ``graininess``, the panel's texture
indices for the observer ``# texture_observer: NAME`` (default ``byk-mac-like``).  A texture value
belongs to the panel, not to a geometry: it is written on one row, the other rows' cells left empty
(or all rows give the same value).

A file may carry both (the writer writes both for a spectral prediction); the spectra are then
what is compared, and the L*a*b* columns are checked against them under the stated observer and
illuminant (to 0.01 ΔE00) so a file whose two halves disagree is refused.

Geometries
----------
The sets are defined in :mod:`flakedb.colour.settings` (with the other defaults) and re-exported here.

* :data:`E2194_GEOMETRIES`: the 45° set of multi-angle instruments (X-Rite MA-T / MA98 class):
  illumination 45°, aspecular −15°, 15°, 25°, 45°, 75°, 110° (the set the colour report has always
  used).  ASTM E2194 itself (metal flake) asks for three aspecular angles (its public scope page:
  "requires three angles of measurement"); the −15° geometry, beyond the specular, is one of the
  additions of ASTM E2539 (see below), kept in this set because the instruments measure it with
  the 45° illuminator.
* :data:`E2539_EXTRA`: illumination at 15°, aspecular −45°, −15°, 15°, 45°, 80° (detectors at 60°,
  30°, 0°, −30°, −65° from the normal: the same detectors as the 45° set).  What public sources
  confirm (docs/colour-matching.md, "Geometries"): E2539 (interference pigments, 2008) adds a second
  illumination angle at 15° and an aspecular angle on the far side of the specular (W. R. Cramer,
  "Modern measurement of effect pigments – useful and useless geometries", European Coatings
  Show Conference 2019, abstract); these five are the 15° geometries X-Rite names 15as-45, 15as-15,
  15as15, 15as45, 15as80 in its instrument data.  Not verified: that E2539's table lists exactly
  these five aspecular angles at 15° (the standard's text is paid and was not available); check it
  before relying on the set for acceptance testing.
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flakedb.atomic import atomic_write_text
from flakedb.colour.geometry import as_geometry_array, compact
from flakedb.colour.geometry import key as geometry_key
from flakedb.colour.geometry import label as geometry_label
from flakedb.colour.geometry import problem as geometry_problem
from flakedb.colour.settings import (  # the geometry sets live with the other defaults
    DEFAULT_ILLUMINANT,
    DEFAULT_OBSERVER,
    E2194_GEOMETRIES,
    E2539_EXTRA,
    E2539_GEOMETRIES,
    GEOMETRY_SETS,
)
from flakedb.colour.tolerance import (
    delta_E_2000,
    illuminant_name,
    observer_name,
    reflectance_to_Lab,
)
from flakedb.match.texture import (
    DEFAULT_TEXTURE_OBSERVER,
    check_texture_value,
    parse_texture_column,
)
from flakedb.safeio import FileTooLargeError, read_limited
from flakedb.texture.instruments import PRESETS as TEXTURE_PRESETS

#: Largest target CSV read [bytes]: 200 geometries × 1000 reflectance columns of 8 characters.
MAX_TARGET_BYTES = 2_000_000
#: Most geometries of a target: multi-angle instruments measure 5–20 (E2194 5, E2539 11), and each
#: geometry costs a BSDF evaluation in every fit iteration, so more is a mistake, not a measurement.
MAX_TARGET_GEOMETRIES = 200
#: Most R_<nm> columns (1 nm steps from 300 to 1200 nm are 901).
MAX_TARGET_BANDS = 1000
#: Measured reflectance factors (fraction) accepted: [REFLECTANCE_MIN, REFLECTANCE_MAX].  Below 0: an instrument's
#: zero noise on a black panel, at most 2 % of the white standard (a factor of -0.3 is a sign or unit mistake).
#: Above 1 (the perfect white diffuser): an effect paint near the specular, whose reflectance factor is pi times its
#: BRDF and reaches 3-5 at 15as15 for bright aluminium (L* 140-180); 20 (L* 300.6) leaves a wide margin for
#: smoother flakes and still refuses a percent file read as fractions (R = 50, 80, ...).
REFLECTANCE_MIN, REFLECTANCE_MAX = -0.02, 20.0
#: L* of a reflectance factor of :data:`REFLECTANCE_MAX` (116 Y^(1/3) - 16); L* below 0 is no colour.
LSTAR_MAX = 116.0 * REFLECTANCE_MAX ** (1.0 / 3.0) - 16.0
#: |a*|, |b*| accepted: the most saturated real surface colours reach about 130 (the spectrum locus of a
#: reflectance of 20 reaches about 500 at the extremes).
ABSTAR_MAX = 500.0

__all__ = ["E2194_GEOMETRIES", "E2539_EXTRA", "E2539_GEOMETRIES", "GEOMETRY_SETS", "Target", "TargetError",
           "check_measured", "format_target", "read_target", "validate_geometries", "write_target"]

_LAB_COLUMNS = (("L*", "a*", "b*"), ("L", "a", "b"))
_R_COLUMN = re.compile(r"^R_(\d+(?:\.\d+)?)$")


class TargetError(ValueError):
    """A target file that cannot be read (the message names the line and what to fix)."""


@dataclass
class Target:
    """A multi-angle colour target.

    ``geometries`` (G, 2): illumination and aspecular angles in degrees, or (G, 3) with an azimuth when a
    geometry is out of plane (:mod:`flakedb.colour.geometry`).  ``lab`` (G, 3) or None;
    ``reflectance`` (G, W) reflectance factors (fraction) on ``wavelength_nm`` (W,) or None.
    ``observer`` / ``illuminant``: the conditions of ``lab``.
    """

    geometries: np.ndarray
    lab: np.ndarray | None = None
    reflectance: np.ndarray | None = None
    wavelength_nm: np.ndarray | None = None
    observer: str = DEFAULT_OBSERVER
    illuminant: str = DEFAULT_ILLUMINANT
    name: str = ""
    notes: dict = field(default_factory=dict)
    source: str = ""
    #: texture columns {name: value} (module docstring); empty: a colour-only target
    texture: dict = field(default_factory=dict)
    texture_observer: str = DEFAULT_TEXTURE_OBSERVER

    @property
    def spectral(self) -> bool:
        return self.reflectance is not None

    @property
    def label(self) -> str:
        """What tables and figures call the target: its ``# name:``, else its file's stem (never the
        folder path it was read from), else "target" (also for a target read from text, whose source is the
        placeholder ``<target>``).

        >>> Target(np.zeros((1, 2)), source="/lab/2026/panels/A-17.csv").label, Target(np.zeros((1, 2)), name="A").label
        ('A-17', 'A')
        >>> Target(np.zeros((1, 2)), source="<target>").label
        'target'
        """
        if self.name:
            return self.name
        stem = Path(str(self.source)).stem if self.source else ""
        return "target" if not stem or (stem.startswith("<") and stem.endswith(">")) else stem

    def lab_under(self, observer=None, illuminant=None) -> np.ndarray:
        """L*a*b* (G, 3) under ``observer`` / ``illuminant`` (default: the target's own).

        A spectral target is integrated under any conditions its grid allows; an L*a*b* target only
        under its own (anything else raises TargetError: the spectra are needed).
        """
        obs = self.observer if observer is None else str(observer)
        ill = self.illuminant if illuminant is None else str(illuminant)
        if self.spectral:
            return reflectance_to_Lab(self.reflectance, self.wavelength_nm, obs, ill)
        if observer_name(obs) != observer_name(self.observer) or illuminant_name(ill) != illuminant_name(self.illuminant):
            raise TargetError(f"{self.source or 'target'}: its L*a*b* are for {self.observer}° / {self.illuminant}; "
                              f"{obs}° / {ill} needs spectral reflectance factors (R_… columns)")
        return np.asarray(self.lab, float)


def _validate_geometries(geoms, where):
    if len(geoms) > MAX_TARGET_GEOMETRIES:
        raise TargetError(f"{where}: {len(geoms):,} geometries; the limit is {MAX_TARGET_GEOMETRIES} (a multi-angle "
                          f"instrument measures 5-20, and each costs a BSDF evaluation in every fit iteration)")
    for i, g in enumerate(as_geometry_array(geoms)):
        p = geometry_problem(g)   # the one statement of what flakedb can measure (flakedb.colour.geometry)
        if p:
            raise TargetError(f"{where} row {i + 1}: {p}")


def check_measured(where, geometries, lab=None, reflectance=None, wavelength_nm=None) -> None:
    """Refuse measured values that no panel can have (TargetError naming ``where``, the row or geometry and the
    column): a reflectance factor outside [:data:`REFLECTANCE_MIN`, :data:`REFLECTANCE_MAX`], L* outside
    [0, :data:`LSTAR_MAX`], |a*| or |b*| above :data:`ABSTAR_MAX`.

    >>> check_measured("t.csv", [[45, 15]], reflectance=[[0.5, -0.3]], wavelength_nm=[500, 510])
    Traceback (most recent call last):
    ...
    flakedb.match.targets.TargetError: t.csv geometry 45as15 (row 1): R_510 = -0.3 is outside [-0.02, 20] (a reflectance factor, fraction of the perfect white diffuser; a percent file needs '# reflectance: percent')
    """
    g = as_geometry_array(geometries)

    def at(i):
        return f"{where} geometry {geometry_label(g[i])} (row {i + 1})"

    if reflectance is not None:
        R = np.asarray(reflectance, float)
        wl = np.asarray(wavelength_nm, float)
        bad = np.argwhere(~((R >= REFLECTANCE_MIN) & (R <= REFLECTANCE_MAX)))
        if bad.size:
            i, j = bad[0]
            raise TargetError(f"{at(i)}: R_{wl[j]:g} = {R[i, j]:.6g} is outside [{REFLECTANCE_MIN:g}, "
                              f"{REFLECTANCE_MAX:g}] (a reflectance factor, fraction of the perfect white diffuser; "
                              f"a percent file needs '# reflectance: percent')")
    if lab is not None:
        L = np.asarray(lab, float).reshape(-1, 3)
        for k, (col, lo, hi) in enumerate((("L*", 0.0, LSTAR_MAX), ("a*", -ABSTAR_MAX, ABSTAR_MAX),
                                           ("b*", -ABSTAR_MAX, ABSTAR_MAX))):
            bad = np.flatnonzero(~((L[:, k] >= lo) & (L[:, k] <= hi)))
            if bad.size:
                i = bad[0]
                raise TargetError(f"{at(i)}: {col} = {L[i, k]:.6g} is outside [{lo:g}, {hi:.4g}] (CIELAB of a "
                                  f"reflectance factor in [0, {REFLECTANCE_MAX:g}])")


def validate_geometries(geoms, where) -> None:
    """Refuse geometries flakedb cannot predict (TargetError naming ``where`` and the row); for other readers."""
    _validate_geometries(geoms, where)


def read_target(path_or_text, observer=None, illuminant=None, source=None) -> Target:
    """Read a target CSV (module docstring) from a path, or from text when it contains a newline.

    ``observer`` / ``illuminant``: the conditions the target is compared under.  A spectral target
    is integrated under them (they override the file's options).  An L*a*b*-only file's stated
    conditions are facts about its numbers and are kept (comparing under others then raises, see
    :meth:`Target.lab_under`); the call fills in only conditions the file does not state, and if
    neither says, 2° / D65 is assumed and recorded in ``notes['assumed']``.  L*a*b* columns beside R_ columns are always
    checked under the file's own conditions.

    A round trip of a spectral grey target: reflectance 0.5 everywhere is L* = 116 · 0.5^{1/3} − 16 = 76.0693
    under any observer and illuminant, a* = b* = 0:

    >>> import tempfile
    >>> wl = np.arange(400.0, 701.0, 20.0)
    >>> path = Path(tempfile.mkdtemp()) / "grey.csv"
    >>> _ = write_target(path, E2194_GEOMETRIES[:2], reflectance=np.full((2, wl.size), 0.5), wavelength_nm=wl, name="grey")
    >>> t = read_target(path)
    >>> t.name, t.spectral, t.geometries.tolist()
    ('grey', True, [[45.0, -15.0], [45.0, 15.0]])
    >>> (np.round(t.lab_under(observer="10", illuminant="A"), 4) + 0.0).tolist()
    [[76.0693, 0.0, 0.0], [76.0693, 0.0, 0.0]]
    """
    if isinstance(path_or_text, str) and "\n" in path_or_text:
        text, where = path_or_text, source or "<target>"
    else:
        p = Path(path_or_text)
        where = source or str(p)
        try:   # a regular file only (no FIFO / device), never more than the limit read
            text = read_limited(p, MAX_TARGET_BYTES).decode("utf-8-sig")
        except FileNotFoundError:
            raise TargetError(f"{where}: no such file") from None
        except FileTooLargeError as exc:
            raise TargetError(f"{where}: {exc.size:,} bytes or more; the limit is {MAX_TARGET_BYTES:,} bytes for a "
                              f"target CSV ({MAX_TARGET_GEOMETRIES} geometries at most)") from None
        except UnicodeDecodeError as exc:
            raise TargetError(f"{where}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
        except OSError as exc:
            raise TargetError(f"{where}: cannot read the file ({exc.strerror or exc})") from None
    if len(text) > MAX_TARGET_BYTES:
        raise TargetError(f"{where}: {len(text):,} characters; the limit is {MAX_TARGET_BYTES:,} for a target CSV")
    opts, notes, rows = {}, {}, []
    for ln, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            m = re.match(r"#\s*([A-Za-z_][\w ]*?)\s*:\s*(.*)$", s)
            if m:
                k, v = m.group(1).strip().lower(), m.group(2).strip()
                (opts if k in ("observer", "illuminant", "reflectance", "name", "texture_observer") else notes)[k] = v
            continue
        rows.append((ln, s))
    if not rows:
        raise TargetError(f"{where}: no header line (illumination_deg,aspecular_deg,L*,a*,b* or …,R_380,…)")
    hdr_ln, hdr = rows[0]
    if len(rows) - 1 > MAX_TARGET_GEOMETRIES:
        raise TargetError(f"{where}: {len(rows) - 1:,} geometry rows; the limit is {MAX_TARGET_GEOMETRIES} (a "
                          f"multi-angle instrument measures 5-20 geometries, and each costs a BSDF evaluation in "
                          f"every fit iteration)")
    try:
        header = [h.strip() for h in next(csv.reader(io.StringIO(hdr)))]
    except csv.Error as exc:
        raise TargetError(f"{where} line {hdr_ln}: not a CSV line ({exc})") from None
    if header[:2] != ["illumination_deg", "aspecular_deg"]:
        raise TargetError(f"{where} line {hdr_ln}: the header must start with illumination_deg,aspecular_deg; "
                          f"got {','.join(header[:2])}")
    n_geo = 3 if len(header) > 2 and header[2] == "azimuth_deg" else 2   # out-of-plane geometries
    lab_idx = None
    for names in _LAB_COLUMNS:
        if all(n in header for n in names):
            lab_idx = [header.index(n) for n in names]
    r_cols = [(i, float(_R_COLUMN.match(h).group(1))) for i, h in enumerate(header) if _R_COLUMN.match(h)]
    if len(r_cols) > MAX_TARGET_BANDS:
        raise TargetError(f"{where} line {hdr_ln}: {len(r_cols)} R_ columns; the limit is {MAX_TARGET_BANDS} "
                          f"(1 nm steps over 300-1200 nm)")
    if len(set(header)) != len(header):
        raise TargetError(f"{where} line {hdr_ln}: a column name appears twice")
    tex_idx = [(i, h) for i, h in enumerate(header) if parse_texture_column(h) is not None]
    known = set(range(n_geo)) | set(lab_idx or []) | {i for i, _ in r_cols} | {i for i, _ in tex_idx}
    unknown = [h for i, h in enumerate(header) if i not in known]
    if unknown:
        raise TargetError(f"{where} line {hdr_ln}: unknown column(s) {', '.join(unknown)} (allowed: azimuth_deg "
                          f"third, L*,a*,b*, "
                          f"R_<nm> reflectance factors, and the texture columns sparkle_area_<deg>, "
                          f"sparkle_intensity_<deg>, glints_per_mm2_<deg>, graininess)")
    if lab_idx is None and not r_cols:
        raise TargetError(f"{where} line {hdr_ln}: no colour columns: give L*,a*,b* or R_380,R_390,… (any uniform grid)")
    data, tex_cells = [], {h: [] for _, h in tex_idx}
    tex_pos = {i for i, _ in tex_idx}
    for ln, s in rows[1:]:
        try:
            cells = [c.strip() for c in next(csv.reader(io.StringIO(s)))]
        except csv.Error as exc:
            raise TargetError(f"{where} line {ln}: not a CSV line ({exc})") from None
        if len(cells) != len(header):
            raise TargetError(f"{where} line {ln}: {len(cells)} values, the header has {len(header)} columns")
        try:
            data.append([float(c) for i, c in enumerate(cells) if i not in tex_pos])
            for i, h in tex_idx:  # a panel's value: on one row, empty (or the same) on the others
                if cells[i]:
                    tex_cells[h].append((ln, float(cells[i])))
        except ValueError:
            raise TargetError(f"{where} line {ln}: a value is not a number: {s[:80]}") from None
    if not data:
        raise TargetError(f"{where}: no geometry rows after the header")
    a = np.asarray(data, float)
    if not np.all(np.isfinite(a)):
        raise TargetError(f"{where}: values must be finite numbers")
    texture = {}
    for _, h in tex_idx:
        vals = tex_cells[h]
        if not vals:
            raise TargetError(f"{where}: column {h} has no value (write the panel's value on one row)")
        if len({v for _, v in vals}) > 1:
            raise TargetError(f"{where} line {vals[1][0]}: column {h} is a value of the panel, given once; the rows "
                              f"disagree ({vals[0][1]:g} on line {vals[0][0]}, {vals[1][1]:g} here)")
        problem = check_texture_value(h, vals[0][1])
        if problem:
            raise TargetError(f"{where} line {vals[0][0]}: {problem}")
        texture[h] = vals[0][1]
    tex_obs = opts.get("texture_observer", DEFAULT_TEXTURE_OBSERVER)
    if tex_obs not in TEXTURE_PRESETS:
        raise TargetError(f"{where}: '# texture_observer: {tex_obs}': use one of {', '.join(sorted(TEXTURE_PRESETS))}")
    col = {i: k for k, i in enumerate(i for i in range(len(header)) if i not in tex_pos)}  # header → data column
    geoms = compact(a[:, :n_geo])   # (G, 2) when every azimuth is 0
    _validate_geometries(geoms, where)
    keys = [geometry_key(g) for g in geoms.tolist()]
    if len(set(keys)) != len(keys):
        raise TargetError(f"{where}: a geometry is listed twice")
    if not r_cols:  # L*a*b* only: the file's stated conditions are facts; a call fills in only what it omits
        obs = str(opts.get("observer", observer if observer is not None else DEFAULT_OBSERVER))
        ill = str(opts.get("illuminant", illuminant if illuminant is not None else DEFAULT_ILLUMINANT))
    else:
        obs = str(observer if observer is not None else opts.get("observer", DEFAULT_OBSERVER))
        ill = str(illuminant if illuminant is not None else opts.get("illuminant", DEFAULT_ILLUMINANT))
    try:
        observer_name(obs), illuminant_name(ill)
    except ValueError as exc:
        raise TargetError(f"{where}: {exc}") from None
    if lab_idx is not None and not r_cols and "observer" not in opts and observer is None:
        notes["assumed"] = (f"observer {obs} deg / illuminant {ill} (not stated in the file: the defaults, "
                            f"flakedb.colour.settings)")
    t = Target(geometries=geoms, observer=obs, illuminant=ill, name=opts.get("name", ""), notes=notes, source=where,
               texture=texture, texture_observer=tex_obs)
    if lab_idx is not None:
        t.lab = a[:, [col[i] for i in lab_idx]]
        check_measured(where, geoms, lab=t.lab)
    if r_cols:
        wl = np.array([w for _, w in r_cols])
        R = a[:, [col[i] for i, _ in r_cols]]
        unit = opts.get("reflectance", "fraction").lower()
        if unit not in ("fraction", "percent"):
            raise TargetError(f"{where}: '# reflectance: {unit}': use fraction or percent")
        if unit == "percent":
            R = R / 100.0
        check_measured(where, geoms, reflectance=R, wavelength_nm=wl)
        try:
            reflectance_to_Lab(R[:1], wl, obs, ill)
        except ValueError as exc:
            raise TargetError(f"{where}: reflectance grid: {exc}") from None
        t.reflectance, t.wavelength_nm = R, wl
        if t.lab is not None:  # the L*a*b* columns are under the file's own conditions
            f_obs = opts.get("observer", DEFAULT_OBSERVER)
            f_ill = opts.get("illuminant", DEFAULT_ILLUMINANT)
            de = delta_E_2000(t.lab, reflectance_to_Lab(R, wl, f_obs, f_ill))
            if np.max(de) > 0.01:
                raise TargetError(f"{where}: the L*a*b* columns disagree with the R_ columns under {f_obs}° / {f_ill} "
                                  f"(max ΔE00 {np.max(de):.3g}); fix one, or drop the L*a*b* columns")
    return t


def format_target(geometries, lab=None, reflectance=None, wavelength_nm=None, observer=DEFAULT_OBSERVER,
                  illuminant=DEFAULT_ILLUMINANT,
                  name="", notes=None, texture=None, texture_observer=DEFAULT_TEXTURE_OBSERVER) -> str:
    """The CSV text of a target (module docstring); ``lab`` computed from ``reflectance`` when omitted;
    ``texture``: {column: value} written on the first row (the others' cells empty)."""
    g = compact(geometries)
    if reflectance is not None:
        R = np.asarray(reflectance, float)
        wl = np.asarray(wavelength_nm, float)
        if lab is None:
            lab = reflectance_to_Lab(R, wl, observer, illuminant)
    if lab is None:
        raise ValueError("format_target needs lab or reflectance")
    lab = np.asarray(lab, float)
    out = io.StringIO()
    out.write("# flakedb multi-angle colour target (docs/colour-matching.md)\n")
    if name:
        out.write(f"# name: {name}\n")
    out.write(f"# observer: {observer}\n# illuminant: {illuminant}\n")
    if reflectance is not None:
        out.write("# reflectance: fraction\n")
    texture = dict(texture or {})
    if texture:
        out.write(f"# texture_observer: {texture_observer}\n")
    for k, v in (notes or {}).items():
        out.write(f"# {k}: {v}\n")
    cols = ["illumination_deg", "aspecular_deg"] + (["azimuth_deg"] if g.shape[1] == 3 else []) + ["L*", "a*", "b*"]
    if reflectance is not None:
        cols += [f"R_{w:g}" for w in wl]
    cols += list(texture)
    w = csv.writer(out, lineterminator="\n")
    w.writerow(cols)
    for i in range(g.shape[0]):
        row = [f"{v:g}" for v in g[i]] + [f"{v:.6f}" for v in lab[i]]
        if reflectance is not None:
            row += [f"{v:.9g}" for v in R[i]]
        row += [f"{v:.9g}" if i == 0 else "" for v in texture.values()]
        w.writerow(row)
    return out.getvalue()


def write_target(path, geometries, lab=None, reflectance=None, wavelength_nm=None, observer=DEFAULT_OBSERVER,
                 illuminant=DEFAULT_ILLUMINANT,
                 name="", notes=None, texture=None, texture_observer=DEFAULT_TEXTURE_OBSERVER) -> str:
    """Write :func:`format_target`'s text to ``path`` atomically; returns the path."""
    atomic_write_text(Path(path), format_target(geometries, lab, reflectance, wavelength_nm, observer, illuminant,
                                                name, notes, texture, texture_observer))
    return str(path)
