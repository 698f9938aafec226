"""Meshes and rasters: the 5x7 IPAM font of PROBLEMS.md (shared by poisson2d and membrane2d)."""
from .font import GLYPHS, IPAM_BOX, bitmap_mask, ipam_mask, word_bitmap

__all__ = ["GLYPHS", "IPAM_BOX", "bitmap_mask", "ipam_mask", "word_bitmap"]
