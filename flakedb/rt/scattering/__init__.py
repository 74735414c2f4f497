"""Scattering media: phase-function media, the translucent micro-flake medium (paper eq. 2, 5-8) and the
projection of their kernels on the cosine series, direct or from stored factors (docs/model.md §3,
docs/projection.md, docs/store.md)."""
