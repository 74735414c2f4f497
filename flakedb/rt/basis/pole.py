"""The pole μ = 1 of a rule: a direction along the normal has no azimuth, so in the cosine series of
φ_d only order 0 may be non-zero in the row and the column of that node (docs/model.md §4, "Specular
paths and the pole").  A flux-cell rule integrates over the pole's cap, where the BSDF does depend on
φ_d, and left azimuth-dependent terms there (a rough conductor under a smooth coat: up to 35 % of the
maximum at n = 16, falling as 1/n); every layer kind sets them to zero (:func:`zero_pole_orders`)."""

import numpy as np


def pole_index(x):
    """Index of the node μ = 1 of a rule (the Gauss–Radau end point and its Snell images), or None."""
    x = np.asarray(x)
    return int(len(x) - 1) if len(x) and x[-1] == 1.0 else None


def zero_pole_orders(S, x_out, x_in):
    """Orders l ≥ 1 of the row and column of the pole node set to zero in place (a block (L, C, h_o, h_i)
    on the rules with nodes ``x_out``, ``x_in``); returns S.  Order 0 (the energy) is untouched, so
    albedo, reciprocity (rows and columns alike) and positivity (the φ-average of a positive function)
    are kept.

    >>> x = np.array([0.5, 1.0])                       # the last node is the pole μ = 1
    >>> S = zero_pole_orders(np.ones((3, 1, 2, 2)), x, x)
    >>> S[0].tolist() == np.ones((1, 2, 2)).tolist(), S[1:, 0, 1, :].tolist(), S[1:, 0, 0, 0].tolist()
    (True, [[0.0, 0.0], [0.0, 0.0]], [1.0, 1.0])
    """
    if S.shape[0] < 2:
        return S
    po, pi = pole_index(x_out), pole_index(x_in)
    if po is not None:
        S[1:, ..., po, :] = 0.0
    if pi is not None:
        S[1:, ..., :, pi] = 0.0
    return S
