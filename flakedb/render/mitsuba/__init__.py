"""Mitsuba 3 integration (tested with 3.9.1; docs/renderers.md), one module per concept:

* :mod:`~flakedb.render.mitsuba.directions` -- renderer directions <-> the file's ``(mu_i, mu_o,
  phi_d)``; what a file holds per output channel (reflection albedo, the mirror term, spectral
  channels, the map to linear sRGB);
* :mod:`~flakedb.render.mitsuba.tensor` -- the RGL tensor file (write atomically, read with checks);
* :mod:`~flakedb.render.mitsuba.measured` -- :func:`export_measured`: the built-in ``measured`` BSDF
  (Dupuy & Jakob 2018), fast in every variant, front-side reflection of the table only;
* :mod:`~flakedb.render.mitsuba.coated` -- :func:`export_coated`: the ``measured`` table with the
  smooth coat's Fresnel mirror put back by Mitsuba's own ``conductor`` (k = 0 is the dielectric
  Fresnel) in a ``blendbsdf`` (both halves written at twice their value, weight 1/2: the sum);
* :mod:`~flakedb.render.mitsuba.plugin` -- :func:`register`: the ``flakedb`` Python BSDF plugin
  (flakedb's reader, exact, with the mirror term as a delta lobe);
* :mod:`~flakedb.render.mitsuba.furnace` -- the render check: a sphere in a white furnace.

Mitsuba itself is imported inside the functions that need it, so this package imports without it.
"""

from flakedb.render.mitsuba.coated import coated_bsdf_dict, export_coated
from flakedb.render.mitsuba.directions import (RGB_TO_Y, MeasuredExportError, channel_wavelengths,
                                               delta_reflectance, direction_from_file, file_coordinates,
                                               reflectance_albedo, rgb_matrix)
from flakedb.render.mitsuba.furnace import (FURNACE_HALF_WIDTH, FURNACE_RADIANCE, furnace_sphere_prediction,
                                            furnace_sphere_scene)
from flakedb.render.mitsuba.measured import (FLOOR_DEFAULT, N_THETA_DEFAULT, N_THETA_MAX, RES_DEFAULT, RES_MAX,
                                             check_export_size, export_measured, measured_tensors)
from flakedb.render.mitsuba.plugin import (LLVM_LIBRARY_DEFAULT, PluginCore, evaluated_mode, fresnel_unpolarised,
                                           llvm_library, register)
from flakedb.render.mitsuba.tensor import MAGIC_TENSOR, TENSOR_FILE_MAX_BYTES, read_tensor_file, write_tensor_file

__all__ = [
    "MeasuredExportError", "file_coordinates", "direction_from_file", "reflectance_albedo", "delta_reflectance",
    "channel_wavelengths", "rgb_matrix", "RGB_TO_Y", "measured_tensors", "write_tensor_file", "read_tensor_file",
    "MAGIC_TENSOR", "TENSOR_FILE_MAX_BYTES", "export_measured", "check_export_size", "export_coated",
    "coated_bsdf_dict", "register", "PluginCore", "fresnel_unpolarised", "evaluated_mode", "llvm_library",
    "LLVM_LIBRARY_DEFAULT", "furnace_sphere_scene", "furnace_sphere_prediction", "FURNACE_RADIANCE",
    "FURNACE_HALF_WIDTH", "RES_DEFAULT", "RES_MAX", "N_THETA_DEFAULT", "N_THETA_MAX", "FLOOR_DEFAULT",
]
