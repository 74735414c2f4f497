"""flakedb: predict a car paint's BSDF from its composition.

Translucent micro-flake radiative transfer (Ergun et al.), solved by adding-doubling in a Fourier
basis.  Conventions: :mod:`flakedb.conventions`.
"""

__version__ = "0.1.0"
