"""Per-material images and what is done with them without rendering (paper Sec. 5.2): the basis
folder (format, ownership, reader), blends (Eq. 9 and 13; full GI with the cross terms of
:mod:`.crossterms`), matching a target image, the
match objectives and denoised blends.

NumPy only; depends on :mod:`.manifold`, :mod:`.imaging`, :mod:`.data` and :mod:`._util`.
"""
