"""Eq. 13 in memory: the weighted sum of a basis's images and cross terms (:mod:`.blend`)."""

import time

import numpy as np

from .._util.blas import axpy, one_thread
from .folder import BASE


def compose(basis, keys, weights, cross=None):
    """Eq. 13: ``base + sum_j weights[..., j] image(keys[j])`` (no base with several targets),
    plus ``sum_r products[..., r] C[rows[r]]`` with ``cross = (rows, products)`` (full GI).

    Returns the image(s), the seconds spent reading images and the seconds of the sum (the
    cross terms, which planning the blend needs, are read before: :func:`.blend.blend`).
    """
    t_read = basis.read(keys + ([BASE] if basis.p == 1 else []))
    t0 = time.perf_counter()
    images = basis.weighted_sum(keys, weights)
    if basis.p == 1:
        images += basis.image(BASE)
    if cross is not None and len(cross[0]):
        _add_cross(images, basis, cross[0], np.asarray(cross[1], np.float32))
    return images, t_read, time.perf_counter() - t0


def single_image(basis, name):
    """The image of the training material ``name`` alone (weight 1, a basis of one target): its
    L1- image plus the base (Eq. 13 at that material, without cross terms).
    """
    return basis.image(basis.key([name])) + basis.image(BASE)


def _add_cross(images, basis, rows, products):
    """``images += sum_r products[..., r] C[rows[r]]``: one image in place, term by term
    (:func:`~mitsuba_manifold._util.blas.axpy`, on one BLAS thread), from the float32 rows the basis keeps
    (:meth:`Basis.cross_term`); a sequence by ``tensordot``.
    """
    if products.ndim == 1:
        with one_thread():
            for r, p in zip(rows, products):
                if p != 0.0:
                    axpy(images, basis.cross_term(int(r)), p)
        return
    images += np.tensordot(products, basis.cross_terms()[1][rows].astype(np.float32), axes=1)


def read_cross(basis, component):
    """Seconds reading the cross terms of a ``component`` ("full" or "l1") blend from disk (once
    per basis; before planning the blend, which needs them).
    """
    if component != "full":
        return 0.0
    t0 = time.perf_counter()
    basis.cross_terms()
    return time.perf_counter() - t0
