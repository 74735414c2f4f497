"""Advice for a target a match did not reach: the colour direction no free parameter moves, and the
catalogue species that move it (docs/colour-matching.md, "Outcome").

The direction (pure, from the match's own sensitivities)
-------------------------------------------------------
At the fit, the remaining difference r_g = target_g − fit_g (CIELAB, per geometry g) and the sensitivities
S_g = ∂Lab_g/∂p (:attr:`flakedb.match.fit.MatchResult.sensitivities`, (G, 3, P)) are stacked over the
geometries into r (3G,) and S (3G, P).  To first order a change δp of the parameters moves the colour by
S δp, so the part of r that no change can produce is r⊥ = r − S S⁺ r, the residual orthogonal to the
span of S (S⁺ the pseudo-inverse, :func:`unreachable_part`).  "Free" parameters are those not at a
bound (:attr:`~flakedb.match.fit.MatchResult.at_bound`): a parameter at its bound cannot go further.  r⊥
is worded per geometry (:func:`direction_words`) along the fitted colour's own axes: ΔL* (lighter /
darker), the chroma component (r⊥ · (a*, b*)/C*: more / less chroma) and the hue component
(r⊥ · (−b*, a*)/C*, i.e. the direction of increasing h_ab: hue toward the next of red 0°, yellow 90°,
green 180°, blue 270° in that direction).  A near-neutral fit (C* < :data:`NEUTRAL_CHROMA`), or one whose
a*b* step is longer than its chroma (the step crosses the neutral axis, where hue and chroma turn over), is
worded on a* and b* (redder / greener / yellower / bluer).  A component is named when it is at least
:data:`WORD_FRACTION` of that geometry's |r⊥_g|; the geometries named are those with |r⊥_g| ≥ half the
largest.

The species (one compose per candidate)
----------------------------------------
Each catalogue colourant (pigment or tinter) not in the recipe is added to the fitted recipe's first
layer with particles at :data:`PROBE_VOLUME_FRACTION` and composed at the fit's geometries, node count
and conditions: its colour change d (G, 3), made orthogonal to the free span like r (d⊥), is compared
with r⊥: cos θ = d⊥ · r⊥ / (|d⊥| |r⊥|).  A species with cos θ > 0 moves the colour the way no free
parameter can; adding it at t = (d⊥ · r⊥ / |d⊥|²) × the probe's fraction removes, to first order, the
share 1 − sin θ of |r⊥| (the estimate of the volume fraction to start from, not a fit).  Candidates are
ranked by cos θ.  This is first order: a probe is a small step from the fit, and the ranking is of
directions, not of reachable matches; run ``match`` with the species added to know.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np

from flakedb.colour.geometry import label as geometry_label
from flakedb.colour.tolerance import lch, shade_words
from flakedb.match.fit import predict, recipe_from_doc
from flakedb.paint.catalog import load_catalog
from flakedb.paint.recipe import RecipeError

#: Volume fraction at which a candidate species is probed (a small step from the fit).
PROBE_VOLUME_FRACTION = 0.005
#: Fitted colours with C*ab below this are worded on a* and b*, not chroma and hue (hue is undefined at 0).
NEUTRAL_CHROMA = 2.0
#: A component of r⊥_g is named when at least this fraction of |r⊥_g|.
WORD_FRACTION = 0.3
#: There is an unreachable direction when the largest |r⊥_g| is at least this fraction of the largest |r_g|.
UNREACHABLE_FRACTION = 0.25
#: Kinds of catalogue species probed as colourants.
PROBE_KINDS = ("pigment", "tinter")
_HUE_NAMES = {0: "red", 90: "yellow", 180: "green", 270: "blue"}


def unreachable_part(residual, sensitivities) -> np.ndarray:
    """r⊥ (G, 3): the part of ``residual`` (G, 3) orthogonal to the span of the columns of ``sensitivities``
    (G, 3, P) stacked over the geometries (module docstring); P = 0 gives the residual itself.

    >>> S = np.zeros((1, 3, 1)); S[0, 0, 0] = 2.0                      # one parameter moving L* only
    >>> unreachable_part(np.array([[1.0, 0.5, -0.25]]), S).tolist()
    [[0.0, 0.5, -0.25]]
    """
    r = np.asarray(residual, float)
    S = np.asarray(sensitivities, float).reshape(r.size, -1)
    if S.shape[1] == 0:
        return r.copy()
    coef, *_ = np.linalg.lstsq(S, r.ravel(), rcond=None)
    return (r.ravel() - S @ coef).reshape(r.shape)


def direction_words(lab_fit, r_perp) -> list:
    """Words (a string per geometry) for moving each fitted colour ``lab_fit`` (G, 3) by ``r_perp`` (G, 3)
    (module docstring).

    >>> direction_words([[50.0, 20.0, 0.0]], [[0.0, 0.0, 3.0]])      # a red, moved toward +b*: its hue
    ['hue toward yellow']
    >>> direction_words([[50.0, 0.0, 30.0]], [[-2.0, 0.0, 4.0]])     # a yellow, darker and more chroma
    ['darker, more chroma']
    """
    lab = np.asarray(lab_fit, float).reshape(-1, 3)
    rp = np.asarray(r_perp, float).reshape(-1, 3)
    out = []
    for (L, a, b), d in zip(lab, rp):
        size = float(np.linalg.norm(d))
        if size == 0.0:
            out.append("")
            continue
        words = []
        if abs(d[0]) >= WORD_FRACTION * size:
            words.append("lighter" if d[0] > 0 else "darker")
        C = float(np.hypot(a, b))
        if C < max(NEUTRAL_CHROMA, float(np.hypot(d[1], d[2]))):   # near neutral, or a step across the axis
            for v, pos, neg in ((d[1], "redder", "greener"), (d[2], "yellower", "bluer")):
                if abs(v) >= WORD_FRACTION * size:
                    words.append(pos if v > 0 else neg)
        else:
            radial = (d[1] * a + d[2] * b) / C
            tangential = (-d[1] * b + d[2] * a) / C
            if abs(radial) >= WORD_FRACTION * size:
                words.append("more chroma" if radial > 0 else "less chroma")
            if abs(tangential) >= WORD_FRACTION * size:
                h = float(lch([L, a, b])[2])
                nxt = (np.floor(h / 90.0) + 1) * 90.0 if tangential > 0 else (np.ceil(h / 90.0) - 1) * 90.0
                words.append(f"hue toward {_HUE_NAMES[int(nxt % 360)]}")
        out.append(", ".join(words))
    return out


def _label(g) -> str:
    return geometry_label(g)


@dataclass
class Advice:
    """What :func:`advise` found (module docstring)."""

    r_perp: np.ndarray                      # (G, 3) the part no free parameter moves
    reachable_by_bounded: bool              # the parameters at a bound would move it (widen them)
    direction: list = field(default_factory=list)   # [(words, [geometry labels])], worst first
    species: list = field(default_factory=list)     # ranked {species, cos, share_removed, volume_fraction, adds}
    skipped: list = field(default_factory=list)     # [(species, reason)]
    probed: bool = False

    @property
    def unreachable(self) -> bool:
        return bool(self.direction)

    def lines(self) -> list:
        """The lines ``flakedb match`` prints."""
        if not self.direction:
            return ["advice: the free parameters can move the colour every way the target differs (to first "
                    "order): the fit stopped at a bound, in a local minimum or at the evaluation limit"]
        where = "; ".join(f"{w} at {', '.join(gs)}" for w, gs in self.direction)
        out = [f"advice: no free parameter moves the colour {where} (|out of reach| up to "
               f"{float(np.max(np.linalg.norm(self.r_perp, axis=-1))):.2f} CIELAB units)"]
        if self.reachable_by_bounded:
            out.append("advice: the parameters at a bound do move it: widen their bounds")
        elif self.probed:
            good = [s for s in self.species if s["cos"] > 0]
            if good:
                out.append("advice: catalogue species that move it (probe of " f"{PROBE_VOLUME_FRACTION:g} volume "
                           "fraction in the fitted recipe; first order): "
                           + "; ".join(f"{s['species']} (adds {s['adds']}; removes ~{s['share_removed']:.0%} of it at "
                                       f"volume_fraction ~{s['volume_fraction']:.2g})" for s in good[:3]))
            else:
                out.append("advice: no catalogue colourant moves it (probed: "
                           + ", ".join(s["species"] for s in self.species) + "); a colourant outside the catalogue "
                           "may: `flakedb calibrate` one, or give a user catalogue with --catalog")
        return out

    def record(self) -> dict:
        """A JSON-able record (``flakedb match``'s NAME-match.json ``advice``)."""
        return {"unreachable": [{"direction": w, "geometries": gs} for w, gs in self.direction],
                "r_perp": self.r_perp.tolist(), "reachable_by_parameters_at_a_bound": self.reachable_by_bounded,
                "species": self.species, "skipped": [{"species": s, "reason": r} for s, r in self.skipped],
                "probe_volume_fraction": PROBE_VOLUME_FRACTION}


def _directions(lab_fit, r_perp, geometries, residual) -> list:
    norms = np.linalg.norm(r_perp, axis=-1)
    if norms.max() < UNREACHABLE_FRACTION * max(float(np.linalg.norm(residual, axis=-1).max()), 1e-300):
        return []
    order = [int(i) for i in np.argsort(-norms) if norms[i] >= 0.5 * norms.max()]
    words = direction_words(lab_fit, r_perp)
    groups = {}
    for i in order:
        if words[i]:
            groups.setdefault(words[i], []).append(_label(geometries[i]))
    return list(groups.items())


def probe_species(res, candidates, catalog, store=None, raw=False):
    """(rows, skipped): each candidate species added to ``res.fitted_doc`` at :data:`PROBE_VOLUME_FRACTION`
    and composed at the fit's geometries (module docstring); rows {species, d (G, 3)}."""
    rows, skipped = [], []
    for name in candidates:
        doc = copy.deepcopy(res.fitted_doc)
        layer = next((lay for lay in doc.get("layers", []) for v in lay.values()
                      if isinstance(v, dict) and isinstance(v.get("particles"), list)), None)
        if layer is None:
            skipped.append((name, "the recipe has no layer with particles"))
            continue
        body = next(v for v in layer.values() if isinstance(v, dict) and isinstance(v.get("particles"), list))
        body["particles"].append({"species": name, "volume_fraction": PROBE_VOLUME_FRACTION})
        try:
            rec = recipe_from_doc(doc, f"<probe {name}>", catalog)
            lab = predict(rec, res.geometries, res.n, catalog, store, raw).lab(res.observer, res.illuminant)
        except (RecipeError, ValueError) as exc:
            skipped.append((name, str(exc).splitlines()[0][:200]))
            continue
        rows.append({"species": name, "d": lab - res.lab_fit})
    return rows, skipped


def advise(res, catalog=None, store=None, raw=False, candidates=None, log=None) -> Advice:
    """The :class:`Advice` for a :class:`flakedb.match.fit.MatchResult` (module docstring).  ``candidates``:
    species to probe (default: the catalogue's colourants, :data:`PROBE_KINDS`, not in the recipe); the
    probes run only when the unreachable direction is not one the parameters at a bound would move."""
    log = log or (lambda s: None)
    residual = np.asarray(res.lab_target, float) - np.asarray(res.lab_fit, float)
    bounded = {name for name, _, _ in res.at_bound}
    free = [j for j, p in enumerate(res.params) if p.name not in bounded]
    S = np.asarray(res.sensitivities, float)
    r_perp = unreachable_part(residual, S[:, :, free])
    r_all = unreachable_part(residual, S)
    direction = _directions(res.lab_fit, r_perp, res.geometries, residual)
    reachable_by_bounded = bool(direction and bounded
                                and np.linalg.norm(r_all) < UNREACHABLE_FRACTION * np.linalg.norm(r_perp))
    adv = Advice(r_perp=r_perp, reachable_by_bounded=reachable_by_bounded, direction=direction)
    if not direction or reachable_by_bounded:
        return adv
    catalog = catalog if catalog is not None else load_catalog()
    if candidates is None:
        used = {str(p.get("species")) for lay in res.fitted_doc.get("layers", []) for v in lay.values()
                if isinstance(v, dict) for p in v.get("particles", []) or [] if isinstance(p, dict)}
        candidates = [k for k, v in catalog["particles"].items() if v.get("kind") in PROBE_KINDS and k not in used]
    log(f"probing {len(candidates)} catalogue species for the direction no free parameter moves")
    rows, adv.skipped = probe_species(res, candidates, catalog, store, raw)
    adv.probed = True
    rn = float(np.linalg.norm(r_perp))
    worst = int(np.argmax(np.linalg.norm(r_perp, axis=-1)))
    for row in rows:
        d_perp = unreachable_part(row["d"], S[:, :, free])
        dn = float(np.linalg.norm(d_perp))
        cos = float(np.sum(d_perp * r_perp) / (dn * rn)) if dn > 0 and rn > 0 else 0.0
        t = float(np.sum(d_perp * r_perp) / dn ** 2) if dn > 0 else 0.0
        adv.species.append({"species": row["species"], "cos": cos,
                            "share_removed": 1.0 - float(np.sqrt(max(0.0, 1.0 - cos * cos))) if cos > 0 else 0.0,
                            "volume_fraction": max(t, 0.0) * PROBE_VOLUME_FRACTION,
                            "adds": shade_words(res.lab_fit[worst], res.lab_fit[worst] + row["d"][worst])[0]
                            + f" at {_label(res.geometries[worst])}"})
    adv.species.sort(key=lambda s: -s["cos"])
    return adv
