"""The discretisation the solver works in: quadrature rules in μ, the cosine series in φ (Fourier projection,
Legendre kernels, the pole μ = 1) and the special functions they need (docs/model.md §4)."""
