"""Dask pipeline definitions (the build graph); they only wire flakedb's pure functions together."""
