"""Measured data: the MERL ``.binary`` format, the SGD surrogate of the 100 MERL materials and
:class:`~mitsuba_manifold.data.database.Database` (a folder of tables, its Gram matrix).

The rows of ``Z`` in the paper (Sec. 3). Depends on :mod:`._util` only.
"""
