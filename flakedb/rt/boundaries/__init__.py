"""Interfaces as scattering matrices: smooth (Fresnel) and rough (microfacet flux cells, the height chain's
multiple scattering) (docs/model.md §4, docs/rough-interfaces.md)."""
