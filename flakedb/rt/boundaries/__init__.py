"""Interfaces and boundaries as scattering matrices: smooth (Fresnel), rough (microfacet flux cells) and the
specular part of a stack's reflection (docs/model.md §4, docs/rough-interfaces.md)."""
