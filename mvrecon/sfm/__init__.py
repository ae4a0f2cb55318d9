"""Incremental structure from motion: tracks, initial pair, registration, triangulation, GTSAM bundle
adjustment.

The engine estimates with OpenCV, GTSAM, scipy and numpy (numba compiling its inner loops) only; it reads a
`database.Correspondences` and returns `model.Reconstruction` objects that `io.colmap_model` writes as COLMAP models.
"""
