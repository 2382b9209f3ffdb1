"""The learned material space: :class:`~mitsuba_manifold.manifold.model.Manifold` (latent points
and what was learned, its :class:`~.file.fit_record.FitRecord`; its fit, materials by name and
weight text, diagnostics and summary are its methods), the fit's settings (:mod:`.presets`),
the interpolants giving weights ``w(x)`` (:mod:`.interpolant`: paper Eq. 4 and the convex
default), the training tables and their combination (:mod:`.tables`), pruning (:mod:`.pruning`),
plausibility beyond the data (:mod:`.plausibility`), projection of new tables
(:mod:`.projection`), adding materials (:mod:`.adding`), paths (:mod:`.paths`), space metrics
(:mod:`.space`); the saved file in :mod:`.file`: the ``.npz`` format (:mod:`.file.io`), its
schema (:mod:`.file.schema`), the fit's record, the identity of a manifold and the shipped
manifolds.

Depends on :mod:`.gp`, :mod:`.data` and :mod:`._util`.
"""

from .._util.moved import alias as _alias

#: Modules that moved into sub-packages: their old names import the new modules, deprecated.
_MOVED = {
    "search": "..basis.inverse.search",
    "io": ".file.io",
    "schema": ".file.schema",
    "shipped": ".file.shipped",
    "identity": ".file.identity",
    "fit_record": ".file.fit_record",
}
_alias(__name__, _MOVED)
