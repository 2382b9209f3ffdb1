"""Measured data: the MERL ``.binary`` format (:mod:`.merl`), the NBRDF networks of 159 measured
materials shipped with the package (:mod:`.nbrdf`, MIT licence in ``NBRDF_LICENSE``), the SGD
surrogate of the 100 MERL materials (:mod:`.surrogate`), the sources a material's table comes
from (:mod:`.sources`: ``.binary`` and Mitsuba ``measured`` files, networks, fits, the built-in
sets), :class:`~mitsuba_manifold.data.database.Database` (a set of them, read and written) and
the one Gram matrix of a stack of tables (:mod:`.gram`).

The rows of ``Z`` in the paper (Sec. 3). Depends on :mod:`._util` only.
"""
