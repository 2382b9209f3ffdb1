"""Plain helpers every subsystem may use: atomic writes, content hashes and caches, locks,
ownership records, material names as file names, timing and checks of plain values.

Imports nothing of the package but :mod:`mitsuba_manifold.errors` (and its own modules).
"""
