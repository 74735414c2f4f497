"""Exporters to the renderers rendering teams use (docs/renderers.md); the registry is :mod:`flakedb.export.registry`."""
