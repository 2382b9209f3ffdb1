"""Measured data: the MERL ``.binary`` format (:mod:`.merl`), the SGD surrogate of the 100 MERL
materials (:mod:`.surrogate`), :class:`~mitsuba_manifold.data.database.Database` (a folder of
tables, read and written) and the one Gram matrix of a stack of tables (:mod:`.gram`).

The rows of ``Z`` in the paper (Sec. 3). Depends on :mod:`._util` only.
"""
