"""A solved paint's appearance: its BSDF evaluated at the report's geometries, XYZ / CIELAB under the colour
conditions of :mod:`flakedb.colour.settings` (the rule for a target: :func:`flakedb.colour.settings.for_target`),
flop, directional albedo and the texture model's grounding (:mod:`flakedb.appearance.report`)."""
