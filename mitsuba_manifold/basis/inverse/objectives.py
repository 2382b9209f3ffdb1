"""Image errors of a blend as functions of its weights: the objectives of :func:`match.match`.

A blend is ``I(w) = base + sum_i w_i I_i`` (paper Eq. 13). Each objective here is built
once from the basis images over the masked pixels and then evaluated for any weights
``w`` (one vector: error, gradient ``dE/dw``, exposure; many at once: :meth:`batch`):

- :class:`RelativeMSE`: the relative MSE of :mod:`metrics`, ``(a - r)^2 / (r^2 + eps)`` per
  pixel and channel averaged with the mask's weights, as a quadratic form in ``u = (1, w)``
  (exact, O(N^2) per evaluation after one float64 Gram matrix);
- :class:`LogLuminanceMSE`: the MSE of log luminance (the images evaluated at every step).

Exposure-free, both fit the blend's scale in closed form at every evaluation.
"""

import numpy as np
from scipy.linalg import blas

from ..._util.float32 import weights32
from ...imaging.metrics import REL_EPS
from ..folder import BASE

LOSSES = ("rel_mse", "log")
#: Rec. 709 luminance of linear RGB.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
#: ``eps`` of the log loss, relative to the mean luminance over the mask.
LOG_EPS = 1e-3


def pool(img, f):
    """Box-average ``f x f`` blocks of (..., H, W[, C]) images over axes -3/-2 (cropped to fit)."""
    if f == 1:
        return img
    h, w = img.shape[-3] // f * f, img.shape[-2] // f * f
    img = img[..., :h, :w, :]
    shape = img.shape[:-3] + (h // f, f, w // f, f, img.shape[-1])
    return img.reshape(shape).mean(axis=(-4, -2))


def masked_pool(img, weight, f, pooled_weight=None):
    """Mask-weighted box average of ``f x f`` blocks: pixels outside the mask do not leak in."""
    if f == 1:
        return img
    pooled_weight = pool(weight, f) if pooled_weight is None else pooled_weight
    return pool(img * weight, f) / np.maximum(pooled_weight, 1e-12)


def _luminance(basis, names):
    """Luminance of the base and material images as float64 (N + 1, H, W)."""
    keys = [BASE] + basis.material_keys(names)
    first = basis.image(keys[0])
    out = np.empty((len(keys),) + first.shape[:2])
    for j, key in enumerate(keys):
        np.matmul(basis.image(key).astype(np.float64), LUMINANCE, out=out[j])
    return out


class RelativeMSE:
    """Relative MSE as a quadratic form in ``u = (1, w)`` (exact, O(N^2) per evaluation).

    ``E = s^2 u^T G u - 2 s u^T h + e0`` with ``G = R C R^T``, ``h = R C r``,
    ``e0 = r^T C r``, ``C = diag(mask / (r^2 + eps)) / sum(mask)``; ``s = 1`` or, exposure-free,
    ``s = max(0, u^T h / u^T G u)``.
    """

    def __init__(self, images, target, weight, exposure_free, chunk=8192):
        """``images``: the base then the N material images (H, W, 3); ``weight`` (H, W)."""
        n1, (h, w) = len(images), weight.shape
        step = max(1, chunk // w)
        self.G = np.zeros((n1, n1))
        self.h = np.zeros(n1)
        self.e0 = 0.0
        total = 3.0 * weight.sum()
        for y in range(0, h, step):  # one band of image rows at a time: no (N + 1, P) copy
            m = weight[y : y + step]
            sel = m > 0
            r = target[y : y + step][sel].reshape(-1)
            c = np.repeat(m[sel], 3) / (r * r + REL_EPS) / total
            R = np.stack([img[y : y + step][sel].reshape(-1) for img in images]).astype(np.float64)
            self.G = blas.dsyrk(
                1.0, R * np.sqrt(c), beta=1.0, c=self.G, overwrite_c=True
            )  # upper half
            self.h += R @ (c * r)
            self.e0 += float(c @ (r * r))
        self.G = np.triu(self.G) + np.triu(self.G, 1).T
        self.exposure_free = exposure_free

    def __call__(self, w):
        """``(error, dE/dw, exposure)``."""
        u = np.concatenate(([1.0], w))
        Gu = self.G @ u
        a, b = float(u @ Gu), float(u @ self.h)
        s = max(b / a, 0.0) if self.exposure_free and a > 0 else 1.0
        err = s * s * a - 2.0 * s * b + self.e0
        grad = 2.0 * s * s * Gu - 2.0 * s * self.h  # s is optimal: no ds/dw term (envelope)
        return max(err, 0.0), grad[1:], s

    def batch(self, W):
        """Errors and exposures of many weight vectors W (M, N) at once."""
        U = np.concatenate((np.ones((len(W), 1)), W), axis=1)
        a = ((U @ self.G) * U).sum(axis=1)  # BLAS: faster than the three-operand einsum
        b = U @ self.h
        s = (
            np.where(a > 0, np.maximum(b / np.where(a > 0, a, 1.0), 0.0), 1.0)
            if self.exposure_free
            else np.ones(len(W))
        )
        return np.maximum(s * s * a - 2.0 * s * b + self.e0, 0.0), s

    def singles(self):
        """:meth:`batch` of every material alone (``W`` the identity)."""
        return self.batch(np.eye(len(self.h) - 1))

    def evaluate(self, W):
        """Errors and exposures of weight vectors W (M, N) as :meth:`__call__` gives them (the
        quadratic form is exact: :meth:`batch`).
        """
        return self.batch(W)


class LogLuminanceMSE:
    """MSE over the mask of ``log(lum / k + eps)`` against ``log(lum_r / mean(lum_r) + eps)``.

    ``k = mean(lum_r)`` (a fixed normalisation), or exposure-free ``k = mean(lum)`` of the
    blend itself, which makes the loss exactly invariant to the blend's scale; the exposure
    is then ``mean(lum_r) / mean(lum)`` (means weighted by the mask).
    """

    def __init__(self, lum_rows, target, weight, exposure_free, eps=LOG_EPS):
        self.A = lum_rows  # (N + 1, P) float64
        self.A32 = lum_rows.astype(np.float32)  # for batches (ranking)
        self.m = weight / weight.sum()
        self.eps = eps
        lum_r = np.maximum(target @ LUMINANCE, 0.0)
        self.mean_r = max(float(self.m @ lum_r), 1e-30)
        self.lr = np.log(lum_r / self.mean_r + eps)
        self.lr32 = self.lr.astype(np.float32)
        self.exposure_free = exposure_free

    def _norm(self, lum):
        """Normalisation ``k`` of each row of ``lum`` (..., P)."""
        if self.exposure_free:
            return np.maximum(np.maximum(lum, 0.0) @ self.m, 1e-12 * self.mean_r)
        return np.full(lum.shape[:-1], self.mean_r)

    def __call__(self, w):
        lum = self.A[0] + w @ self.A[1:]
        k = float(self._norm(lum))
        n = np.maximum(lum, 0.0) / k
        d = np.log(n + self.eps) - self.lr
        gn = 2.0 * self.m * d / (n + self.eps) * (lum > 0)  # dE/dn
        g = gn / k
        if self.exposure_free:  # k = m . max(lum, 0) depends on w
            g = g - self.m * (lum > 0) * float(gn @ n) / k
        return float(self.m @ (d * d)), self.A[1:] @ g, self.mean_r / k

    def evaluate(self, W):
        """Errors and exposures of weight vectors W (M, N) in float64, each as :meth:`__call__`
        gives it, in one product (the images are read once for all).
        """
        lum = self.A[0] + np.atleast_2d(W) @ self.A[1:]
        k = self._norm(lum)
        d = np.log(np.maximum(lum, 0.0) / k[:, None] + self.eps) - self.lr
        return (d * d) @ self.m, self.mean_r / k

    def batch(self, W, chunk=256):
        """Errors and exposures of many weight vectors W (M, N) at once (in float32, the weights
        below float32's normal range set to 0: :func:`~mitsuba_manifold._util.float32.weights32`).
        """
        errs, norms = [], []
        for s in range(0, len(W), chunk):  # in place: one (chunk, P) array a chunk
            lum = np.matmul(weights32(W[s : s + chunk]), self.A32[1:])
            lum += self.A32[0]
            errs.append(self._errors(lum, norms))
        return np.concatenate(errs), self.mean_r / np.concatenate(norms)

    def singles(self, chunk=None):
        """:meth:`batch` of every material alone (``W`` the identity), without the product; a
        chunk of about a million values at a time (default), which stays in the cache.
        """
        chunk = chunk or max(1, (1 << 20) // self.A32.shape[1])
        errs, norms = [], []
        for s in range(1, len(self.A32), chunk):
            errs.append(self._errors(self.A32[s : s + chunk] + self.A32[0], norms))
        return np.concatenate(errs), self.mean_r / np.concatenate(norms)

    def _errors(self, lum, norms):
        """Errors of the blends' luminance ``lum`` (M, P) float32, overwritten; appends the
        normalisations ``k`` (M,) to ``norms``.
        """
        k = self._norm(lum)
        d = np.maximum(lum, 0.0, out=lum)
        d /= k[:, None].astype(np.float32)
        d += np.float32(self.eps)
        d = np.log(d, out=d)
        d -= self.lr32
        norms.append(k)
        return np.square(d, out=d) @ self.m


def objectives(basis, manifold, target, weight, loss, exposure_free, f=1):
    """The objective of ``loss`` for ``target`` (H, W, 3) with mask weights ``weight`` (H, W)
    (the pixels of weight > 0 count), and the one a search runs on: the same, or with ``f > 1``
    (log loss only) on ``f x f`` box averages of the images, each weighted by the mask
    (:func:`masked_pool`). The log loss takes the images' luminance once for both.
    """
    if loss == "rel_mse":
        keys = [BASE] + basis.material_keys(manifold.names)
        full = RelativeMSE([basis.image(k) for k in keys], target, weight, exposure_free)
        return full, full
    lum = _luminance(basis, manifold.names)
    pixels = weight > 0
    rows = lum.reshape(len(lum), -1) if pixels.all() else lum[:, pixels]
    full = LogLuminanceMSE(rows, target[pixels], weight[pixels], exposure_free)
    if f == 1:
        return full, full
    wp = pool(weight[..., None], f)[..., 0]
    rows = masked_pool(lum[..., None], weight[..., None], f, wp[..., None])[..., 0]
    tp = masked_pool(target, weight[..., None], f, wp[..., None])
    on = wp > 0
    return full, LogLuminanceMSE(rows[:, on], tp[on], wp[on], exposure_free)


def masked_rel_mse(a, ref, weight):
    """:func:`metrics.rel_mse` with pixel weights (the plain mean when all weights are 1)."""
    e = np.square(a - ref) / (np.square(ref) + REL_EPS)
    return float((e.mean(axis=-1) * weight).sum() / weight.sum())
