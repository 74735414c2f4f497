"""Radiative transfer, by concept, from the ground up: ``common`` (input bounds, threads, a fit's reuse cache),
``basis`` (quadrature, the cosine series in φ, a layer's scattering matrices and the adding equations),
``boundaries`` (smooth and rough interfaces), ``scattering`` (media and their kernels' projection) and
``adding`` (the stack's parts, channels and order-by-order solve, its specular part and its BSDF)."""
