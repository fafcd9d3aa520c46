"""Sigma-point (quadrature) rules for Gaussian moment matching."""

from .rules import SigmaPoints, cubature, gauss_hermite, julier, unscented

__all__ = ["SigmaPoints", "unscented", "julier", "cubature", "gauss_hermite"]
