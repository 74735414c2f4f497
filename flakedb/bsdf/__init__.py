"""Fourier BSDF files: the layerlab / Mitsuba 0.6 / pbrt-v3 ``.bsdf`` file and flakedb's HDF5 file.

Writer, reader, evaluation and importance sampling of the tabulated BSDF described in
``docs/bsdf-format.md`` (called "the spec" below).  Conventions are those of
:mod:`flakedb.conventions` and of the file, which agree: ``mu > 0`` travels down into the paint,
reflection seen from above is ``mu_i > 0, mu_o < 0``, ``phi_d = 0`` is mirror reflection and
``phi_d = π`` retro-reflection.  Every quantity stored and returned here is the cosine series of
**f · |mu_o|** (BSDF in 1/sr times the outgoing cosine), ``value(phi_d) = Σ_k a_k cos(k phi_d)``.

What this module provides
-------------------------
* :class:`BSDFTable` -- what the solver hands over: nodes ``mu`` (n,), coefficients
  ``coeffs[c, i, o, l]`` (C, n, n, L) of f·|mu_o|, ``eta``, ``alpha``, ``delta``, ``metadata``;
  an opaque paint's table is given as its reflection quadrant alone (``reflection=``, (C, h, h, L);
  ``coeffs`` is built from it only when read, and the ``.bsdf`` writer never builds it).
* :func:`write_bsdf` / :func:`read_bsdf` -- the 64-byte-header Fourier file (float32, channels
  stored as Y, R, B), byte layout exactly per the spec.
* :func:`write_h5` / :func:`read_h5` -- the full-precision result (float64, every order, any number
  of channels, e.g. spectral), same evaluation code.
* :func:`open_bsdf` -- dispatch on the file's magic bytes.
* :class:`FourierBSDF` -- ``eval``, ``pdf``, ``sample``, ``series``, ``albedo``,
  ``albedo_nodes``, ``to_table``.

Evaluation (spec, "Evaluation")
-------------------------------
Catmull-Rom weights over the file nodes (including the two zero nodes) for ``mu_i`` and ``mu_o``
(:func:`catmull_rom_weights`), the 4 x 4 neighbouring coefficient vectors blended with the product
weights, and the cosine series summed.  Arguments outside ``[nodes[0], nodes[-1]]`` (or NaN) give 0,
as in layerlab and pbrt-v3 -- so a table must have a node at mu = 1 (the writer warns otherwise).
Two implementations give the same numbers: a compiled (numba) loop over points that touches only
each entry's K_e coefficients (default, ~1 µs per point on the reference car paint), and a plain
vectorised numpy reference (``method="numpy"``) that gathers the 16 coefficient vectors padded to
the chunk's largest order, in chunks of bounded memory.  Coefficients are held in float64 in the
file's sparse layout (entry-contiguous, channel-major), so one compiled kernel serves both files.

Clamping (``clamp=`` of :meth:`FourierBSDF.eval`): ``"layerlab"`` (default) reproduces layerlab's
``BSDFStorage::eval`` -- the reference reader of the spec: the result is 0 where the blended
order-0 coefficient of the sampling channel (Y) is exactly 0 (no data), a single-channel result is
clamped to >= 0, and three-channel results are *not* clamped (layerlab's ``result.clamp()``
discards its return value, so small negative ringing values survive; the reference data confirms
this).  ``"all"`` clamps every channel to >= 0 (pbrt-v3).  ``"none"`` returns the raw series.

Colour
------
A three-channel ``.bsdf`` stores Y, R, B with ``Y = 0.212671 R + 0.715160 G + 0.072169 B`` per
coefficient; ``eval`` returns R, G, B rebuilt with the spec's ``G = 1.39829 Y - 0.100913 B -
0.297375 R`` (what every renderer does), a mono file returns its channel repeated three times (as
layerlab's reader does).  :meth:`FourierBSDF.to_table` inverts the writer's formula exactly,
``G = (Y - 0.212671 R - 0.072169 B) / 0.715160``, so read -> write reproduces the file's floats.
An HDF5 file returns its channels as stored (C of them).

Importance sampling (pbrt-v3 ``SampleCatmullRom2D`` + ``SampleFourier``)
-------------------------------------------------------------------------
The *sampling channel* is Y for a ``.bsdf`` (file channel 0), the luminance of R, G, B for an RGB
HDF5 file, the single channel of a mono file and the channel mean of any other HDF5 file.  Its
order-0 coefficients ``a0[i, o]`` and their Catmull-Rom prefix integrals ``cdf[i, o]`` (spec,
"cdf") define the density of ``mu_o``; ``phi_d`` then follows the Fourier series of that channel,
inverted with Newton-bisection on ``[0, π]`` and mirrored to ``[π, 2π)`` for ``u2 >= 1/2``.  The
resulting density per steradian of ``(mu_o, phi_d)`` is

    pdf(mu_i, mu_o, phi_d) = max(0, f_s·|mu_o|) / (2π · cdf(mu_i)[N-1])          (spec, "pdf")

with ``cdf(mu_i)`` the cdf rows blended with the ``mu_i`` Catmull-Rom weights; it is exact where
the tabulated series is non-negative.  ``sample`` returns ``weight = f·|mu_o| / pdf`` per output
channel, so ``E[weight] = albedo(mu_i)`` (reflectance + transmittance).

``.bsdf`` metadata text (the trailing ``nMetadataBytes``)
--------------------------------------------------------
UTF-8, ``key=value`` lines separated by ``\\n``, no terminator.  Keys match
``[A-Za-z_][A-Za-z0-9_.-]*``.  A value is written raw when it is a one-line string that does not
parse as JSON (``delta=fresnel``, ``recipe=silver metallic``), otherwise as one-line JSON
(``delta_eta=1.5``, ``n_nodes=100``, ``wavelength_nm=[450, 550, 650]``, ``tag="1.5"``); the reader
tries JSON first and falls back to the raw string, so every JSON-able value round-trips.  Lines
that are not ``key=value`` (e.g. layerlab's free-text description) are collected, in order, into
the key ``"text"``; a ``"text"`` entry is written back raw after the key=value lines when none of
its lines looks like ``key=...``.  The smooth coat's first-surface mirror term (spec, "Carrying a
smooth clear coat's mirror reflection") is written first as ``delta=<kind>`` followed by
``delta_<field>=<value>`` for its other fields, i.e. ``delta=fresnel`` and ``delta_eta=1.5`` for
``{"kind": "fresnel", "eta": 1.5}``; the reader puts it back into :attr:`FourierBSDF.delta`.
The writer adds nothing else: the caller puts the recipe name and flakedb version in ``metadata``.

HDF5 layout (``format = "flakedb-fourier-bsdf"``, ``format_version = 1``)
------------------------------------------------------------------------
Root attributes: ``format``, ``format_version``, ``flakedb_version``, ``eta``, ``alpha`` (2,),
``channels`` (JSON list of names), ``delta`` (JSON object or ``null``), ``metadata`` (JSON object:
the table's metadata merged with ``extra_metadata``).  Datasets: ``mu`` float64 (n,) -- the
solver's nodes without the zero nodes; ``coeffs`` float64 (C, n, n, L), every order, chunked per
(channel, incident node, outgoing hemisphere), shuffle + gzip(1) when at least half of it is exactly 0
(``flakedb.bsdf.h5file.h5_filters``; float64 coefficients do not compress) (an opaque paint's reflection
quadrant is written alone, the rest is the dataset's fill value 0: the same array read back); ``albedo`` float64 (C, n), the Catmull-Rom albedo of
each channel at each incident node (derived, for inspection).  The reader inserts the two zero
nodes exactly as the ``.bsdf`` writer does, so both files evaluate identically up to float32.
"""

from flakedb.bsdf.convert import stack_to_table
from flakedb.bsdf.dispatch import open_bsdf
from flakedb.bsdf.evaluator import FourierBSDF, table_evaluator
from flakedb.bsdf.fourier_file import bsdf_file_size, read_bsdf, write_bsdf
from flakedb.bsdf.h5file import read_h5, write_h5
from flakedb.bsdf.metadata import format_metadata, parse_metadata
from flakedb.bsdf.spline import catmull_rom_cdf, catmull_rom_weights, insert_zero_nodes
from flakedb.bsdf.table import TRUNCATION_DEFAULT, BSDFFileError, BSDFTable

__all__ = [
    "BSDFTable",
    "BSDFFileError",
    "FourierBSDF",
    "table_evaluator",
    "stack_to_table",
    "write_bsdf",
    "read_bsdf",
    "write_h5",
    "read_h5",
    "open_bsdf",
    "catmull_rom_weights",
    "catmull_rom_cdf",
    "insert_zero_nodes",
    "format_metadata",
    "parse_metadata",
    "bsdf_file_size",
    "TRUNCATION_DEFAULT",
]

