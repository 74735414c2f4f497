"""The discretisation the solver works in: quadrature rules in μ, the cosine series in φ (Fourier projection,
Legendre kernels, the pole μ = 1), the special functions they need, and a layer's scattering matrices with the
adding and doubling equations on them (paper eq. 3-4, docs/model.md §4)."""
