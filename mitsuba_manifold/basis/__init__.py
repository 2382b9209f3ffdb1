"""Per-material images and what is done with them without rendering (paper Sec. 5.2): the basis
folder (format, ownership, reader), blends (Eq. 9 and 13; full GI with the cross terms of
:mod:`.crossterms`), denoised blends, and inverse rendering without rendering in
:mod:`.inverse` (matching a target image, its objectives and targets, the latent search, the
acquisition programme).

NumPy only; depends on :mod:`.manifold`, :mod:`.imaging`, :mod:`.data` and :mod:`._util`.
"""

from .._util.moved import alias as _alias

#: Modules that moved into sub-packages: their old names import the new modules, deprecated.
_MOVED = {
    "match": ".inverse.match",
    "objectives": ".inverse.objectives",
    "targets": ".inverse.targets",
    "acquisition": ".inverse.acquisition",
}
_alias(__name__, _MOVED)
