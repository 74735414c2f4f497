"""Solving a recipe: its node count (:mod:`flakedb.solve.resolution`) and the one path from a recipe to a checked,
solved stack and its table (:mod:`flakedb.solve.pipeline`), shared by compose, compare, match, calibrate and build."""
