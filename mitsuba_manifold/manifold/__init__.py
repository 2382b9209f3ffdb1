"""The learned material space: :class:`~mitsuba_manifold.manifold.model.Manifold` (latent points
and what was learned, its :class:`~.fit_record.FitRecord`), the fit of a database (:mod:`.fitting`),
the interpolants giving weights ``w(x)`` (paper Eq. 4 and the convex default), the training
tables and their combination (:mod:`.tables`), pruning, materials by name and weight text
(:mod:`.materials`), projection of new tables, diagnostics and the summary (:mod:`.report`),
presets, space metrics and the ``.npz`` format (:mod:`.io`) with its schema (:mod:`.schema`).

Depends on :mod:`.gp`, :mod:`.data` and :mod:`._util`.
"""
