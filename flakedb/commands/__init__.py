"""One module per CLI command; each defines a click command registered in :mod:`flakedb.cli`."""
