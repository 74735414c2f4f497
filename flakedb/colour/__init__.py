"""Colour matching for formulators: multi-angle targets, tolerances and recipe fitting (docs/colour-matching.md)."""
