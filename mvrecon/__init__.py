"""mvrecon: structure from motion in Python, validated against COLMAP."""

__version__ = "0.1.0"
