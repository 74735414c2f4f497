"""The whole stack: its parts and channels, the order-by-order and blocked solves, the specular part of its
reflection, the solved stack and its BSDF, and the solver's settings (docs/model.md §1, §4)."""
