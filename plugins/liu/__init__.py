"""Geometry-guided BTF synthesis after Liu, Yu & Shum (2001)."""
