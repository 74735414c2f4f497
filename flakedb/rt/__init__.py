"""Radiative transfer: quadrature, Fourier projection, adding-doubling layers, interfaces."""
