"""The learned material space: :class:`~mitsuba_manifold.manifold.model.Manifold` (latent points
and what was learned), the interpolants giving weights ``w(x)`` (paper Eq. 4 and the convex
default), presets, pruning, projection of new tables, space diagnostics and the ``.npz`` format.

Depends on :mod:`.gp`, :mod:`.data` and :mod:`._util`.
"""
