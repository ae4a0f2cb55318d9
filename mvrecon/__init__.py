"""mvrecon: structure from motion in Python, validated against COLMAP."""

from . import zlib_order  # noqa: F401  (first: the system's zlib before pycolmap's, see its docstring)

__version__ = "0.1.0"
