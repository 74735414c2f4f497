"""The render check of every Mitsuba route: the unit sphere under a constant environment (a white
furnace at radiance 0.5), seen by an orthographic camera, and the image it must give (each pixel
0.5 x the directional albedo at its view angle, plus the mirror term)."""

from __future__ import annotations

import numpy as np

#: Radiance of the constant environment of the render check.
FURNACE_RADIANCE = 0.5
#: Half-width of the orthographic view, in sphere radii (the unit sphere fills 71 % of the frame).
FURNACE_HALF_WIDTH = 1.05


def furnace_sphere_scene(bsdf: dict, res: int = 64, max_depth: int = 3) -> dict:
    """A Mitsuba 3 scene dict: the unit sphere with material ``bsdf`` under a ``constant``
    environment of radiance :data:`FURNACE_RADIANCE`, seen by an orthographic camera along -z
    whose ``res`` x ``res`` film spans ``±FURNACE_HALF_WIDTH``, box reconstruction filter
    (so a pixel's expected value is the mean radiance over its square), ``path`` integrator.

    Pixel (column c, row r) covers ``x, y`` in ``FURNACE_HALF_WIDTH · [-1 + 2c/res, -1 + 2(c+1)/res]``
    (up to a mirror, irrelevant here): the sphere is radially symmetric.
    """
    import mitsuba as mi  # lazy: optional renderer (test extra), large import

    T = mi.ScalarTransform4f
    cam = T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]) @ T().scale(
        [FURNACE_HALF_WIDTH, FURNACE_HALF_WIDTH, 1.0])
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(max_depth)},
        "sensor": {"type": "orthographic", "to_world": cam, "near_clip": 0.1, "far_clip": 10.0,
                   "film": {"type": "hdrfilm", "width": int(res), "height": int(res), "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": FURNACE_RADIANCE}},
        "sphere": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
    }


def furnace_sphere_prediction(albedo, res: int = 64, supersample: int = 8):
    """Expected image of :func:`furnace_sphere_scene`: ``(image (res, res, C), mu (res, res), cover
    (res, res))``.

    ``albedo(mu)`` -> (..., C) is the directional albedo (reflection, plus any delta term) at view
    cosine ``mu``.  A point (x, y) of the image plane inside the unit disk sees the sphere at view
    cosine ``mu = sqrt(1 - x² - y²)`` and has expected radiance ``0.5 · albedo(mu)`` (a constant
    environment: the reflected radiance is the environment's times the albedo); outside it sees
    0.5.  Each pixel is the mean over ``supersample²`` points of its square.  ``mu`` is the view
    cosine at each pixel's centre (0 outside), ``cover`` the fraction of the pixel on the sphere.


    A white sphere (albedo 1) vanishes in the white furnace; a black one leaves its silhouette:

    >>> white = lambda mu: np.ones(np.shape(mu) + (3,))
    >>> img, mu, cover = furnace_sphere_prediction(white, res=16, supersample=4)
    >>> img.shape, bool(np.allclose(img, FURNACE_RADIANCE)), float(cover.max()), float(cover.min())
    ((16, 16, 3), True, 1.0, 0.0)
    >>> black, _, _ = furnace_sphere_prediction(lambda mu: 0.0 * white(mu), res=16, supersample=4)
    >>> bool(np.allclose(black, FURNACE_RADIANCE * (1.0 - cover)[..., None]))
    True
    >>> abs(float(cover.mean()) - np.pi / (4 * FURNACE_HALF_WIDTH**2)) < 0.01      # the disc's share of the frame
    True
    """
    L = FURNACE_RADIANCE
    h = FURNACE_HALF_WIDTH
    ss = int(supersample)
    edges = np.linspace(-h, h, res + 1)
    sub = (np.arange(ss) + 0.5) / ss
    x = (edges[:-1, None] + (edges[1] - edges[0]) * sub[None, :]).ravel()       # (res·ss,)
    r2 = x[None, :] ** 2 + x[:, None] ** 2
    inside = r2 < 1.0
    mu = np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    a = np.asarray(albedo(mu[inside]), dtype=np.float64)
    C = a.shape[-1]
    val = np.full(r2.shape + (C,), L)
    val[inside] = L * a
    img = val.reshape(res, ss, res, ss, C).mean(axis=(1, 3))
    cover = inside.reshape(res, ss, res, ss).mean(axis=(1, 3))
    xc = 0.5 * (edges[:-1] + edges[1:])
    rc2 = xc[None, :] ** 2 + xc[:, None] ** 2
    return img, np.sqrt(np.clip(1.0 - rc2, 0.0, 1.0)), cover
