"""Texture of effect paints (sparkle and graininess) predicted from flake statistics (docs/texture.md).

Kernel tier: arrays and small frozen dataclasses in, numbers out.  :mod:`flakedb.texture.model` is
the analytic model, :mod:`flakedb.texture.instruments` the observation presets.  The recipe → model
inputs adapter is :mod:`flakedb.paint.texture_inputs`; the independent discrete-flake simulation is
:mod:`flakedb.reference.flake_sim` (it shares no code with the model).
"""
