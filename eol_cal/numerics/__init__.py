"""Numerics shared by numpy and JAX code: array type names, angle wrapping, BLAS threads, the XLA option,
pytrees packed into one array per dtype."""
