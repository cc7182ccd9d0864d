"""Spatial encoders: the tri-plane multiresolution hash encoder."""

from lmgs.encoders.triplane import TriplaneEncoder, hash_grid_2d

__all__ = ["TriplaneEncoder", "hash_grid_2d"]
