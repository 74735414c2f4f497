"""Particle optics: optical constants, Fresnel, thin films (transfer matrix), Mie (Du 2004)."""
