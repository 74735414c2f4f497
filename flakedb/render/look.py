"""What makes a preview read as car paint: a soft-box studio, automatic exposure and a filmic tone
curve, and a contact sheet.  Pure numerics (arrays in, arrays out); :mod:`flakedb.cli.render` writes
the files.

Studio (:class:`SoftboxStudio`)
-------------------------------
A photographic car studio: a vertical gradient from a bright ceiling to a mid-grey wall, a dark
ground, and soft boxes (rectangular area lights seen as disks of angular radius ``radius_deg`` with a
smooth rim).  The sky-to-ground transition is a smoothstep over a ±``blend`` band of ``c = d·up``
(default ±0.35, i.e. about ±20° of elevation), so no horizon line crosses the sphere; the soft boxes
are what the smooth coat's mirror term reflects (a sharp, recognisable highlight: the coat reads as
glossy) and what the flakes sparkle against.  Radiance is linear RGB, relative units.

Tone mapping
------------
* **Automatic exposure** (:func:`auto_exposure`): the log-average luminance of the sphere's pixels
  ``L_w = exp(mean(ln(δ + Y)))`` is mapped to the key 0.18 (Reinhard, Stark, Shirley & Ferwerda
  2002, "Photographic tone reproduction for digital images", SIGGRAPH, eq. 1-2), with Y the linear
  sRGB luminance (0.2126, 0.7152, 0.0722).
* **Filmic curve** (:func:`aces_filmic`): Narkowicz's fit of the ACES reference rendering
  transform (K. Narkowicz 2016, "ACES Filmic Tone Mapping Curve", knarkowicz.wordpress.com):
  ``f(x) = x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)``, clipped to [0, 1], per channel, then the
  sRGB transfer function.  It rolls highlights off smoothly and reaches 1 only at x ≈ 7.24, 5.3
  stops above middle grey, so an exposed sphere clips only where a highlight is that bright.
  colour-science offers no ACES output transform as a function of linear radiance (and no AgX), so
  the published curve is used.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Luminance of linear sRGB (ITU-R BT.709 primaries).
LUMA = np.array([0.2126, 0.7152, 0.0722])
#: Reinhard et al. 2002's middle-grey key.
KEY = 0.18
#: Input at which the filmic curve reaches 1 (the root of 0.08 x² − 0.56 x − 0.14 = 0).
FILMIC_WHITE = (0.56 + np.sqrt(0.56 ** 2 + 4 * 0.08 * 0.14)) / 0.16


def _smoothstep(e0, e1, x):
    u = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


@dataclasses.dataclass(frozen=True)
class SoftboxStudio:
    """Distant studio radiance ``L(d)`` for unit directions ``d`` (..., 3) -> (..., 3) (module docstring).

    ``boxes``: tuples (direction (3,), radiance (3,), radius_deg); each adds its radiance inside its
    cone with a smooth rim of width ``rim_deg``."""

    kind: str = "softbox"
    ceiling: tuple = (0.85, 0.87, 0.9)
    wall: tuple = (0.32, 0.32, 0.33)
    ground: tuple = (0.06, 0.06, 0.06)
    blend: float = 0.35
    up: tuple = (0.0, 1.0, 0.0)
    boxes: tuple = (
        ((-0.35, 0.80, 0.49), (2.5, 2.5, 2.5), 24.0),    # key: overhead, front left
        ((0.85, 0.25, 0.46), (1.2, 1.22, 1.28), 18.0),   # fill: right
        ((-0.6, 0.1, -0.79), (2.0, 2.0, 2.0), 20.0),     # rim: behind left
    )
    rim_deg: float = 3.0

    def __call__(self, d) -> np.ndarray:
        d = np.asarray(d, dtype=np.float64)
        up = np.asarray(self.up, float) / np.linalg.norm(self.up)
        c = np.clip(d @ up, -1.0, 1.0)[..., None]
        sky = np.asarray(self.wall) + (np.asarray(self.ceiling) - np.asarray(self.wall)) * np.maximum(c, 0.0)
        b = _smoothstep(-self.blend, self.blend, c)
        out = np.asarray(self.ground) + b * (sky - np.asarray(self.ground))
        for direction, radiance, radius in self.boxes:
            a = np.asarray(direction, float)
            a = a / np.linalg.norm(a)
            ang = np.degrees(np.arccos(np.clip(d @ a, -1.0, 1.0)))[..., None]
            out = out + np.asarray(radiance) * (1.0 - _smoothstep(radius - self.rim_deg, radius + self.rim_deg, ang))
        return out


def softbox_studio() -> SoftboxStudio:
    """The default studio of ``flakedb render``."""
    return SoftboxStudio()


def luminance(rgb) -> np.ndarray:
    return np.asarray(rgb, float) @ LUMA


def auto_exposure(image, mask=None, key: float = KEY, delta: float = 1e-4) -> float:
    """Scale that maps the log-average luminance of ``image``'s pixels (where ``mask``) to ``key``
    (Reinhard et al. 2002, eq. 1-2).  Returns the multiplier (1 for an all-black image).

    A uniform image of luminance 0.5 is scaled to the key 0.18 (to the ``delta`` of the log average):

    >>> scale = auto_exposure(np.full((4, 4, 3), 0.5))
    >>> round(float(scale * 0.5), 3), KEY
    (0.18, 0.18)
    >>> aces_filmic(np.array([-1.0, 0.0, 1e9])).tolist()                  # negative is 0, bright saturates at 1
    [0.0, 0.0, 1.0]
    """
    Y = luminance(image)
    if mask is not None:
        Y = Y[np.asarray(mask, bool)]
    Y = Y[np.isfinite(Y)]
    if Y.size == 0:
        return 1.0
    Lw = float(np.exp(np.mean(np.log(delta + np.maximum(Y, 0.0)))))
    return key / Lw if Lw > delta else 1.0


def aces_filmic(x) -> np.ndarray:
    """Narkowicz 2016 ACES fit (module docstring), clipped to [0, 1]; negative input counts as 0."""
    x = np.maximum(np.nan_to_num(np.asarray(x, float), nan=0.0, posinf=1e6), 0.0)
    return np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


def tone_map(image, scale: float) -> np.ndarray:
    """Display-referred linear values in [0, 1]: ``aces_filmic(scale · image)`` (encode with sRGB after)."""
    return aces_filmic(np.asarray(image, float) * float(scale))


def clipped_fraction(display, mask) -> float:
    """Fraction of ``mask``'s pixels with any channel at 1 after tone mapping (8-bit 255)."""
    m = np.asarray(mask, bool)
    if not m.any():
        return 0.0
    return float(np.mean(np.any(np.asarray(display)[m] >= 254.5 / 255.0, axis=-1)))


def contact_sheet(images, gap: int = 8, background=(0.12, 0.12, 0.12)) -> np.ndarray:
    """Side by side: (H, W, 3) display images (same height) with ``gap`` pixels between them."""
    imgs = [np.asarray(i, float) for i in images]
    if not imgs:
        raise ValueError("contact_sheet needs at least one image")
    H = max(i.shape[0] for i in imgs)
    W = sum(i.shape[1] for i in imgs) + gap * (len(imgs) - 1)
    out = np.empty((H, W, 3))
    out[:] = np.asarray(background, float)
    x = 0
    for i in imgs:
        out[:i.shape[0], x:x + i.shape[1]] = i
        x += i.shape[1] + gap
    return out
