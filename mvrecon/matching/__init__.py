"""Pair selection, descriptor matching and geometric verification."""
