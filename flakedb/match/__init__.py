"""Colour matching for formulators: multi-angle targets (CSV), comparison and recipe fitting (docs/colour-matching.md)."""
