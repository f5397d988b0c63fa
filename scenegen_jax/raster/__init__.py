"""Rasters: map layers (shapely, host side) and actor drawing (jax.numpy, jit side)."""
