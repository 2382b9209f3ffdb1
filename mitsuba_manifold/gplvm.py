"""Fit of the latent manifold: a GPLVM on the Gram matrix of the measured tables (paper Sec. 3).

Each of the N measured materials gets a latent point ``x_i`` in ``q`` dimensions (the
*latent* points, rows of an ``(N, q)`` array) chosen to maximise the log-likelihood of a
Gaussian process (Eq. 6)::

    L = -d/2 log|K| - 1/2 tr(K^-1 S),      S = Z Z^T,
    K_ij = mu delta_ij + exp(-|x_i - x_j|^2 / (2 l^2))                         (Eq. 5)

where Z is the mean-subtracted ``N x d`` observation matrix, K the covariance matrix of the
latent points, ``K_inv`` its inverse (the *inverse covariance*), ``l`` the length scale and
``mu`` the noise. Only the ``N x N`` Gram matrix S and the number of values d enter the fit,
so this module never sees a table.

Two optimisers work on the same objective from the same start (:func:`pca_init` by default):

* ``"hooke-jeeves"``, the paper's: direct search moving one latent point at a time. A move
  changes one row and column of K; :class:`RankUpdatedInverse` updates ``K_inv``, ``log|K|``
  and ``tr(K_inv S)`` with two rank-one (Sherman-Morrison) updates and the matrix
  determinant lemma in O(N^2), refactorising from scratch periodically and whenever an
  update loses accuracy.
* ``"lbfgs"``: SciPy's L-BFGS-B with the analytic gradient (O(N^3) per evaluation).

Internally both work in units of the length scale (``u = x / l``): scaling ``l`` and the
latent points together changes neither K nor L, so a fit at any ``l`` is the fit at ``l = 1``
scaled by ``l``.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.spatial.distance

try:  # optional: lets small fits run BLAS single-threaded, much faster for N ~ 100
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover - depends on the environment
    threadpool_limits = None

__all__ = [
    "MAX_LATENT_DIM",
    "NotPositiveDefiniteError",
    "kernel_matrix",
    "log_likelihood",
    "log_likelihood_grad",
    "pca_init",
    "RankUpdatedInverse",
    "MoveTrial",
    "FitResult",
    "fit_latent",
]

#: Largest latent dimension accepted.
MAX_LATENT_DIM = 8

#: Up to this many materials the fit runs BLAS on one thread (when threadpoolctl is
#: installed): the N x N products are too small to gain from threads, which only add
#: synchronisation (badly so on a busy machine).
SINGLE_THREAD_MAX_N = 256

_METHODS = ("hooke-jeeves", "lbfgs")


class NotPositiveDefiniteError(np.linalg.LinAlgError, ValueError):
    """The covariance matrix K is not positive definite to working precision."""


# ------------------------------------------------------------------------ validation

def _check_gram(S, check_psd=True):
    """Return S as a symmetric float64 array, or raise ValueError saying what is wrong."""
    try:
        S = np.array(S, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"Gram matrix S must be a real numeric array: {e}") from None
    if S.ndim != 2 or S.shape[0] != S.shape[1]:
        raise ValueError(f"Gram matrix S must be square (N x N), got shape {S.shape}")
    n = S.shape[0]
    if n < 2:
        raise ValueError(f"need at least 2 materials to fit a manifold, S is {n} x {n}")
    if not np.all(np.isfinite(S)):
        bad = np.argwhere(~np.isfinite(S))[0]
        raise ValueError(f"Gram matrix S has a non-finite entry ({S[tuple(bad)]}) at {tuple(bad)}")
    scale = np.abs(S).max()
    asym = np.abs(S - S.T).max()
    if asym > 1e-8 * scale:
        raise ValueError(f"Gram matrix S is not symmetric (max |S - S^T| = {asym:.3g}, "
                         f"max |S| = {scale:.3g})")
    S = 0.5 * (S + S.T)
    if check_psd and scale > 0:
        ev = np.linalg.eigvalsh(S)
        if ev[0] < -1e-8 * max(ev[-1], 0.0) or ev[-1] <= 0:
            raise ValueError(
                f"Gram matrix S is not positive semi-definite (eigenvalues from {ev[0]:.3g} to "
                f"{ev[-1]:.3g}); it must be Z Z^T of the mean-subtracted observations")
    return S


def _check_d(d):
    if isinstance(d, (bool, np.bool_)) or not isinstance(d, numbers.Real):
        raise ValueError(f"d (number of values per material) must be an integer >= 1, got {d!r}")
    d = float(d)
    if not math.isfinite(d) or d < 1 or d != round(d):
        raise ValueError(f"d (number of values per material) must be an integer >= 1, got {d!r}")
    return d


def _check_q(q):
    if isinstance(q, (bool, np.bool_)) or not isinstance(q, numbers.Integral) \
            or not 1 <= q <= MAX_LATENT_DIM:
        raise ValueError(f"latent dimension q must be an integer from 1 to {MAX_LATENT_DIM}, "
                         f"got {q!r}")
    return int(q)


def _check_positive(name, value, allow_zero=False):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        need = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {need}, got {value!r}")
    return v


def _check_points(name, X, n=None, q=None):
    try:
        X = np.array(X, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a real numeric array: {e}") from None
    if X.ndim != 2:
        raise ValueError(f"{name} must have shape (N, q), got {X.shape}")
    if n is not None and X.shape[0] != n:
        raise ValueError(f"{name} has {X.shape[0]} points but S is {n} x {n}")
    if q is not None and X.shape[1] != q:
        raise ValueError(f"{name} has dimension {X.shape[1]}, expected q = {q}")
    if not 1 <= X.shape[1] <= MAX_LATENT_DIM:
        raise ValueError(f"{name} has latent dimension {X.shape[1]}; "
                         f"q must be from 1 to {MAX_LATENT_DIM}")
    if not np.all(np.isfinite(X)):
        row = int(np.argwhere(~np.isfinite(X))[0, 0])
        raise ValueError(f"{name} has a non-finite coordinate in point {row}: {X[row]}")
    return X


# ------------------------------------------------------------------------ kernel, L

def _sq_dist(A, B):
    """Squared distances, summed from coordinate differences (no cancellation, no inf - inf)."""
    return scipy.spatial.distance.cdist(A, B, "sqeuclidean")


def _cov(U, noise):
    """K for latent points ``U`` in units of the length scale."""
    K = np.exp(-0.5 * _sq_dist(U, U))
    K[np.diag_indices_from(K)] = 1.0 + noise
    return K


def kernel_matrix(A, B=None, length_scale=1.0, noise=1e-4):
    """Covariance ``c(x, x') = mu delta(x, x') + exp(-|x - x'|^2 / (2 l^2))`` (Eq. 5).

    Parameters
    ----------
    A : (n, q) array_like
        Latent points.
    B : (m, q) array_like, optional
        Second set of points. If given, the cross-covariance ``exp(...)`` of shape
        ``(n, m)`` is returned, without the noise term (the vector ``k(x)`` of Eq. 1).
    length_scale, noise : float
        ``l > 0`` and ``mu >= 0``.

    Returns
    -------
    ndarray
        ``K`` (n x n, ``1 + mu`` on the diagonal) when ``B`` is None, else ``(n, m)``.
    """
    l = _check_positive("length_scale", length_scale)
    mu = _check_positive("noise", noise, allow_zero=True)
    A = _check_points("A", A)
    if B is None:
        return _cov(A / l, mu)
    B = _check_points("B", B, q=A.shape[1])
    return np.exp(-0.5 * _sq_dist(A / l, B / l))


def _factorise(K):
    """Cholesky factor and ``log|K|``, raising :class:`NotPositiveDefiniteError`."""
    try:
        cho = scipy.linalg.cho_factor(K, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        cho = None
    diag = None if cho is None else np.diag(cho[0])
    if cho is None or not np.all(np.isfinite(cho[0])) or not np.all(diag > 0):
        mu = K[0, 0] - 1.0
        raise NotPositiveDefiniteError(
            f"covariance matrix K ({K.shape[0]} x {K.shape[0]}) is not positive definite to "
            f"working precision (noise mu = {mu:.3g}); latent points probably coincide: use a "
            f"larger noise mu or separate the points")
    return cho, 2.0 * float(np.sum(np.log(diag)))


def _objective(logdet, trace, d):
    return -0.5 * d * logdet - 0.5 * trace


def _value_u(U, S, d, noise):
    cho, logdet = _factorise(_cov(U, noise))
    trace = float(np.trace(scipy.linalg.cho_solve(cho, S, check_finite=False)))
    return _objective(logdet, trace, d)


def _value_grad_u(U, S, d, noise):
    """L and dL/dU for latent points in units of the length scale."""
    K = _cov(U, noise)
    cho, logdet = _factorise(K)
    n = K.shape[0]
    K_inv = scipy.linalg.cho_solve(cho, np.eye(n), check_finite=False)
    K_inv = 0.5 * (K_inv + K_inv.T)
    KS = K_inv @ S
    L = _objective(logdet, float(np.trace(KS)), d)
    # dL = 1/2 tr(G dK) with G = K_inv S K_inv - d K_inv; dK_ij/du_i = -E_ij (u_i - u_j)
    G = KS @ K_inv - d * K_inv
    W = G * K
    W[np.diag_indices_from(W)] = 0.0
    grad = W @ U - W.sum(axis=1)[:, None] * U
    return L, grad


def log_likelihood(latent, S, d, length_scale=1.0, noise=1e-4):
    """Log-likelihood ``L = -d/2 log|K| - 1/2 tr(K_inv S)`` of latent points (Eq. 6).

    Parameters
    ----------
    latent : (N, q) array_like
        Latent points, one per material.
    S : (N, N) array_like
        Gram matrix ``Z Z^T`` of the mean-subtracted observations.
    d : int
        Number of values per material (columns of Z).
    length_scale, noise : float
        ``l > 0`` and ``mu > 0`` of the covariance function.

    Raises
    ------
    NotPositiveDefiniteError
        If K cannot be factorised (a ``numpy.linalg.LinAlgError``).
    ValueError
        On invalid input.
    """
    S = _check_gram(S)
    d = _check_d(d)
    l = _check_positive("length_scale", length_scale)
    mu = _check_positive("noise", noise)
    X = _check_points("latent", latent, n=S.shape[0])
    return _value_u(X / l, S, d, mu)


def log_likelihood_grad(latent, S, d, length_scale=1.0, noise=1e-4):
    """Log-likelihood and its analytic gradient with respect to the latent points.

    With ``G = K_inv S K_inv - d K_inv``, ``dL/dx_i = -sum_j G_ij K_ij (x_i - x_j) / l^2``.
    Same parameters as :func:`log_likelihood`.

    Returns
    -------
    L : float
    grad : (N, q) ndarray
    """
    S = _check_gram(S)
    d = _check_d(d)
    l = _check_positive("length_scale", length_scale)
    mu = _check_positive("noise", noise)
    X = _check_points("latent", latent, n=S.shape[0])
    L, grad_u = _value_grad_u(X / l, S, d, mu)
    return L, grad_u / l


def pca_init(S, q, length_scale=1.0):
    """Linear PCA of the materials from their Gram matrix, as latent starting points.

    The principal coordinates are ``U_q sqrt(lambda_q)`` from the eigendecomposition of S,
    scaled by one common factor so that the first coordinate has standard deviation ``l``
    (the axes keep their relative sizes). Each axis is signed so that its largest entry is
    positive. Axes beyond the rank of S are zero.

    Parameters
    ----------
    S : (N, N) array_like
        Gram matrix of the mean-subtracted observations.
    q : int
        Latent dimension, 1 to 8.
    length_scale : float
        ``l``; the result is proportional to it.

    Returns
    -------
    (N, q) ndarray
    """
    S = _check_gram(S)
    q = _check_q(q)
    l = _check_positive("length_scale", length_scale)
    n = S.shape[0]
    lam, vec = np.linalg.eigh(S)
    lam, vec = lam[::-1], vec[:, ::-1]
    k = min(q, n)
    coords = np.zeros((n, q))
    keep = lam[:k] > 1e-12 * lam[0]
    coords[:, :k] = vec[:, :k] * np.sqrt(np.where(keep, lam[:k], 0.0))
    big = np.argmax(np.abs(coords), axis=0)
    coords *= np.where(coords[big, np.arange(q)] < 0, -1.0, 1.0)
    spread = coords[:, 0].std()
    if not spread > 0:
        raise ValueError("Gram matrix S is zero: all materials are identical after mean "
                         "subtraction, there is nothing to lay out")
    return coords * (l / spread)


# ------------------------------------------------------------------- rank updates

@dataclass
class MoveTrial:
    """Candidate positions of one latent point, evaluated by :meth:`RankUpdatedInverse.try_moves`.

    Attributes
    ----------
    index : int
        The point that moves.
    points : (m, q) ndarray
        Candidate positions (in the caller's units).
    log_likelihood : (m,) ndarray
        L with the point at each candidate; ``-inf`` where K would not be positive definite.
    """

    index: int
    points: np.ndarray
    log_likelihood: np.ndarray
    _version: int = field(repr=False, default=-1)
    _u: np.ndarray = field(repr=False, default=None)
    _k: np.ndarray = field(repr=False, default=None)
    _w: np.ndarray = field(repr=False, default=None)
    _pivot: np.ndarray = field(repr=False, default=None)
    _logdet: np.ndarray = field(repr=False, default=None)
    _trace: np.ndarray = field(repr=False, default=None)
    _fresh: dict = field(repr=False, default_factory=dict)


class RankUpdatedInverse:
    """``K_inv``, ``log|K|`` and ``tr(K_inv S)`` maintained while single latent points move.

    Moving point i replaces row and column i of K. With ``K_inv = B`` and ``b = B e_i``, this
    is two rank-one Sherman-Morrison updates of the inverse: removing point i,
    ``P = B - b b^T / B_ii`` (the inverse of ``A``, K without row and column i, padded with
    zeros), then inserting it at its new place with new covariances ``k`` (``k_i = 0``)::

        s       = (1 + mu) - k^T P k          (Schur complement, >= mu in exact arithmetic)
        w       = P k - e_i
        K_inv'  = P + w w^T / s
        log|K'| = log|K| - log s_old + log s  (matrix determinant lemma, twice)
        tr(K_inv' S) = tr(K_inv S) - w_old^T S w_old / s_old + w^T S w / s

    where ``s_old`` and ``w_old`` are the same quantities for the current position (in exact
    arithmetic ``s_old = 1 / B_ii`` and ``w_old = -b / B_ii``). Each ``P k`` gets one step of
    iterative refinement against the exactly known K, so ``s`` and ``w`` stay accurate when
    K is stiff (nearly coincident points, small ``mu``); the size of that correction
    measures how far the maintained inverse has drifted. All O(N^2) per trial; trials of one
    point are evaluated in batches.

    K is refactorised from scratch (Cholesky) every ``refactor_every`` accepted moves and as
    soon as an update is ill-conditioned: when the refinement correction exceeds
    ``max_correction`` the inverse is refactorised, and a trial whose pivot ``s`` is below
    ``min_pivot * (1 + mu)`` or that stays inaccurate after refactorisation is evaluated
    with a fresh factorisation of its own.

    Parameters
    ----------
    latent : (N, q) array_like
        Initial latent points.
    S : (N, N) array_like
        Gram matrix of the mean-subtracted observations.
    d : int
        Number of values per material.
    length_scale, noise : float
        ``l`` and ``mu``.
    refactor_every : int
        Accepted moves between refactorisations.
    min_pivot : float
        Relative Schur complement below which a trial is evaluated from scratch.
    max_correction : float
        Largest relative refinement correction of ``P k`` accepted from the maintained inverse.
    """

    def __init__(self, latent, S, d, length_scale=1.0, noise=1e-4, refactor_every=50,
                 min_pivot=1e-6, max_correction=1e-5, _validated=False):
        if not _validated:
            S = _check_gram(S)
            d = _check_d(d)
            length_scale = _check_positive("length_scale", length_scale)
            noise = _check_positive("noise", noise)
            latent = _check_points("latent", latent, n=S.shape[0])
        if isinstance(refactor_every, bool) or int(refactor_every) < 1:
            raise ValueError(f"refactor_every must be an integer >= 1, got {refactor_every!r}")
        self._S = S
        self._d = float(d)
        self._l = float(length_scale)
        self._mu = float(noise)
        self._c = 1.0 + self._mu
        self._U = np.array(latent, dtype=np.float64) / self._l
        self.refactor_every = int(refactor_every)
        self.min_pivot = float(min_pivot)
        self.max_correction = float(max_correction)
        self._version = 0
        self._prep = None
        self._logdet = self._trace = 0.0
        self.n_refactorisations = 0
        self.n_updates = 0
        self.n_trials = 0
        self.n_fresh_trials = 0
        self.max_drift = 0.0
        self.refactorise()

    # -- state
    @property
    def latent(self):
        """Current latent points, ``(N, q)``."""
        return self._U * self._l

    @property
    def K(self):
        """Current covariance matrix (copy)."""
        return self._K.copy()

    @property
    def K_inv(self):
        """Maintained inverse covariance (copy)."""
        return self._B.copy()

    @property
    def log_det(self):
        """Maintained ``log|K|``."""
        return self._logdet

    @property
    def trace(self):
        """Maintained ``tr(K_inv S)``."""
        return self._trace

    @property
    def log_likelihood(self):
        """Maintained L."""
        return _objective(self._logdet, self._trace, self._d)

    @property
    def scale(self):
        """Size of L's terms, ``d/2 |log|K|| + 1/2 tr(K_inv S)``: the yardstick for rounding."""
        return 0.5 * self._d * abs(self._logdet) + 0.5 * abs(self._trace)

    def refactorise(self):
        """Recompute K, ``K_inv``, ``log|K|`` and the trace from scratch.

        Returns
        -------
        float
            Relative change of L it caused (drift of the maintained value, relative to
            :attr:`scale`); also kept as the maximum in :attr:`max_drift`.
        """
        old = self.log_likelihood if self._version else None
        K = _cov(self._U, self._mu)
        cho, logdet = _factorise(K)
        self._install(K, cho, logdet)
        self.n_refactorisations += 1
        drift = 0.0
        if old is not None:
            drift = abs(old - self.log_likelihood) / max(self.scale, 1e-300)
            self.max_drift = max(self.max_drift, drift)
        return drift

    def _install(self, K, cho, logdet):
        n = K.shape[0]
        B = scipy.linalg.cho_solve(cho, np.eye(n), check_finite=False)
        self._B = 0.5 * (B + B.T)
        self._K = K
        self._logdet = logdet
        self._trace = float(np.sum(self._B * self._S))
        self._since = 0
        self._version += 1
        self._prep = None

    def _point(self, i):
        """``b = K_inv e_i`` and ``P = K_inv - b b^T / b_i`` (row and column i exactly zero)
        for point i, cached until the next change: ``[i, version, b, P, old]``."""
        if self._prep is None or self._prep[0] != i or self._prep[1] != self._version:
            b = self._B[:, i].copy()
            P = self._B - b[:, None] * (b / b[i])[None, :]
            P[i, :] = 0.0
            P[:, i] = 0.0
            self._prep = [i, self._version, b, P, None]
        return self._prep

    def _schur(self, P, k):
        """For rows ``k`` (``k_i = 0``): ``y = A^-1 k`` padded with ``y_i = 0``, the pivot
        ``s = (1 + mu) - k^T y`` and the relative size of the refinement correction."""
        y = k @ P                       # P symmetric up to rounding; row/column i are zero
        dy = (k - y @ self._K) @ P      # one step of iterative refinement against exact K
        y += dy
        corr = np.sqrt(np.einsum("mj,mj->m", dy, dy)
                       / np.maximum(np.einsum("mj,mj->m", y, y), 1e-300))
        pivot = self._c - np.einsum("mj,mj->m", k, y)
        return y, pivot, corr

    # -- trials
    def try_moves(self, i, points):
        """Evaluate L with point ``i`` moved to each of ``points`` ((m, q) or (q,)), O(m N^2).

        The state is not changed; pass the result to :meth:`accept` to move the point.

        Returns
        -------
        MoveTrial
        """
        n = self._U.shape[0]
        if isinstance(i, bool) or not isinstance(i, numbers.Integral) or not 0 <= i < n:
            raise IndexError(f"point index {i!r} out of range for {n} points")
        pts = np.array(points, dtype=np.float64, ndmin=2)
        if pts.ndim != 2 or pts.shape[1] != self._U.shape[1]:
            raise ValueError(f"candidate points must have shape (m, {self._U.shape[1]}), "
                             f"got {np.shape(points)}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("candidate points must be finite")
        return self._try_u(int(i), pts / self._l, pts)

    def _try_u(self, i, u, pts=None):
        for attempt in range(2):
            prep = self._point(i)
            first = prep[4] is None       # then row 0 is the current position (s_old, w_old)
            uu = np.vstack([self._U[i:i + 1], u]) if first else u
            k = np.exp(-0.5 * _sq_dist(uu, self._U))
            k[:, i] = 0.0
            w, pivot, corr = self._schur(prep[3], k)
            w[:, i] = -1.0                # w = A^-1 k - e_i
            if not first:
                break
            good = corr[0] <= self.max_correction and pivot[0] >= self.min_pivot * self._c
            if good or attempt == 1:
                break
            self.refactorise()            # the maintained inverse has drifted
        wsw = np.einsum("mj,mj->m", w, w @ self._S)
        if first:
            if good:   # without point i: log|A| = log|K| - log s_old, tr(A^-1 S) likewise
                prep[4] = (self._logdet - math.log(pivot[0]),
                           self._trace - wsw[0] / pivot[0])
            else:      # point i sits (nearly) on another one: evaluate its trials from scratch
                prep[4] = (np.nan, np.nan)
            k, w, pivot, corr, wsw = k[1:], w[1:], pivot[1:], corr[1:], wsw[1:]
        logdet_out, trace_out = prep[4]
        self.n_trials += len(u)
        ok = ((pivot >= self.min_pivot * self._c) & (corr <= self.max_correction)
              & np.isfinite(logdet_out))
        safe = np.where(ok, pivot, 1.0)
        logdet = logdet_out + np.log(safe)
        trace = trace_out + wsw / safe
        L = _objective(logdet, trace, self._d)
        trial = MoveTrial(i, u * self._l if pts is None else pts, L, self._version, u, k, w,
                          pivot, logdet, trace)
        for j in np.flatnonzero(~ok):
            L[j] = self._fresh_trial(trial, j)
        return trial

    def _fresh_trial(self, trial, j):
        self.n_fresh_trials += 1
        i = trial.index
        K = self._K.copy()
        K[i, :] = trial._k[j]
        K[:, i] = trial._k[j]
        K[i, i] = self._c
        try:
            cho, logdet = _factorise(K)
        except NotPositiveDefiniteError:
            return -np.inf
        trace = float(np.trace(scipy.linalg.cho_solve(cho, self._S, check_finite=False)))
        trial._fresh[j] = (K, cho, logdet)
        trial._logdet[j] = logdet
        trial._trace[j] = trace
        return _objective(logdet, trace, self._d)

    def accept(self, trial, j=0):
        """Move the point of ``trial`` to its candidate ``j``; return the new L.

        Raises
        ------
        ValueError
            If the state changed since the trial was evaluated.
        NotPositiveDefiniteError
            If that candidate makes K singular.
        """
        if trial._version != self._version:
            raise ValueError("this trial was evaluated before the last change; evaluate it again")
        if not np.isfinite(trial.log_likelihood[j]):
            raise NotPositiveDefiniteError(
                f"moving point {trial.index} to {trial.points[j]} makes K singular")
        i = trial.index
        self._U[i] = trial._u[j]
        self.n_updates += 1
        if j in trial._fresh:
            K, cho, logdet = trial._fresh[j]
            self._install(K, cho, logdet)
            self.n_refactorisations += 1
            return self.log_likelihood
        b = self._point(i)[2]
        v = b / math.sqrt(b[i])
        g = trial._w[j] / math.sqrt(trial._pivot[j])
        B = self._B
        B -= v[:, None] * v[None, :]
        B += g[:, None] * g[None, :]
        k = trial._k[j]
        self._K[i, :] = k
        self._K[:, i] = k
        self._K[i, i] = self._c
        self._logdet = float(trial._logdet[j])
        self._trace = float(trial._trace[j])
        self._version += 1
        self._prep = None
        self._since += 1
        if self._since >= self.refactor_every:
            self.refactorise()
        return self.log_likelihood

    def move(self, i, point):
        """Move point ``i`` to ``point`` ((q,)); return the new L."""
        return self.accept(self.try_moves(i, np.reshape(point, (1, -1))), 0)

    def set_latent(self, latent):
        """Replace all latent points and refactorise; return the new L."""
        latent = _check_points("latent", latent, n=self._U.shape[0], q=self._U.shape[1])
        self._U = latent / self._l
        self._version = 0        # no drift to measure: this is a new configuration
        self.refactorise()
        return self.log_likelihood


# ------------------------------------------------------------------------- the fit

@dataclass
class FitResult:
    """Outcome of :func:`fit_latent`.

    Attributes
    ----------
    latent : (N, q) ndarray
        Optimised latent points.
    log_likelihood : float
        Final L, from a fresh factorisation.
    history : ndarray
        L at the start and after each iteration (a sweep over all points for Hooke-Jeeves,
        an L-BFGS-B iteration otherwise).
    n_evaluations : int
        Objective evaluations (trial positions for Hooke-Jeeves, L and gradient for L-BFGS).
    time_s : float
        Wall time of the optimisation.
    method : str
    converged : bool
        Whether the stopping tolerance was met before ``max_iter``.
    message : str
    length_scale, noise : float
    n_refactorisations : int
        From-scratch factorisations of K (Hooke-Jeeves).
    max_drift : float
        Largest relative disagreement between the maintained L and a fresh one (Hooke-Jeeves).
    """

    latent: np.ndarray
    log_likelihood: float
    history: np.ndarray
    n_evaluations: int
    time_s: float
    method: str
    converged: bool = False
    message: str = ""
    length_scale: float = 1.0
    noise: float = 1e-4
    n_refactorisations: int = 0
    max_drift: float = 0.0

    @property
    def n_iterations(self):
        """Iterations done (sweeps for Hooke-Jeeves)."""
        return len(self.history) - 1


def fit_latent(S, d, q=2, method="hooke-jeeves", length_scale=1.0, noise=1e-4, init=None,
               max_iter=None, tol=None, callback=None, initial_step=0.25):
    """Latent points maximising the GPLVM log-likelihood L (Eq. 6).

    Parameters
    ----------
    S : (N, N) array_like
        Gram matrix ``Z Z^T`` of the mean-subtracted observations (float64).
    d : int
        Number of values per material.
    q : int
        Latent dimension, 1 to 8.
    method : {"hooke-jeeves", "lbfgs"}
        The paper's direct search with rank-one updates, or L-BFGS-B with the gradient.
    length_scale, noise : float
        ``l`` and ``mu``.
    init : (N, q) array_like, optional
        Starting points; :func:`pca_init` by default.
    max_iter : int, optional
        Sweeps over all points (Hooke-Jeeves, default 500) or L-BFGS-B iterations (default
        2000).
    tol : float, optional
        Hooke-Jeeves: stop when every point's step is below ``tol * l`` (default 1e-3).
        L-BFGS-B: stop when the largest gradient entry of ``L / scale`` with respect to
        ``x / l`` is below ``tol`` (default 1e-7; ``scale`` is the size of L's terms at the
        start).
    callback : callable, optional
        ``callback(iteration, latent, L)`` after each iteration; returning True stops.
    initial_step : float
        Hooke-Jeeves: first step, in units of ``l``.

    Returns
    -------
    FitResult

    Notes
    -----
    Hooke-Jeeves moves single points, so collective motions of the whole cloud are slow
    for it: on strongly coupled layouts it can stop (every step below ``tol``) at a lower L
    than L-BFGS; a smaller ``tol`` goes further at a higher cost. For ``N <= 256`` BLAS runs
    single-threaded during the fit when ``threadpoolctl`` is installed.
    """
    S = _check_gram(S)
    d = _check_d(d)
    q = _check_q(q)
    l = _check_positive("length_scale", length_scale)
    mu = _check_positive("noise", noise)
    if method not in _METHODS:
        raise ValueError(f"unknown method {method!r}; use one of {', '.join(_METHODS)}")
    if init is None:
        X0 = pca_init(S, q, l)
    else:
        X0 = _check_points("init", init, n=S.shape[0], q=q)
    if max_iter is not None and (isinstance(max_iter, bool)
                                 or not isinstance(max_iter, numbers.Integral) or max_iter < 0):
        raise ValueError(f"max_iter must be an integer >= 0, got {max_iter!r}")
    if tol is not None:
        tol = _check_positive("tol", tol)
    if callback is not None and not callable(callback):
        raise ValueError("callback must be callable")
    step = _check_positive("initial_step", initial_step)
    U0 = X0 / l
    single = threadpool_limits is not None and S.shape[0] <= SINGLE_THREAD_MAX_N
    t0 = time.perf_counter()
    with threadpool_limits(1, user_api="blas") if single else contextlib.nullcontext():
        if method == "hooke-jeeves":
            res = _hooke_jeeves(U0, S, d, mu, 500 if max_iter is None else int(max_iter),
                                1e-3 if tol is None else tol, step, callback, l)
        else:
            res = _lbfgs(U0, S, d, mu, 2000 if max_iter is None else int(max_iter),
                         1e-7 if tol is None else tol, callback, l)
        U, hist, nev, converged, msg, nref, drift = res
        L = _value_u(U, S, d, mu)
    return FitResult(latent=U * l, log_likelihood=L, history=np.asarray(hist, dtype=np.float64),
                     n_evaluations=nev, time_s=time.perf_counter() - t0, method=method,
                     converged=converged, message=msg, length_scale=l, noise=mu,
                     n_refactorisations=nref, max_drift=drift)


def _hooke_jeeves(U0, S, d, mu, max_iter, tol, step0, callback, l):
    """Hooke-Jeeves direct search, one latent point at a time, in length-scale units.

    For each point: an exploratory poll of ``+-step`` along every coordinate (evaluated in
    one batch), plus the move combining every improving coordinate; then pattern moves
    ``x + (x - base)``, polled the same way, while they improve. A point whose poll fails
    halves its step; the search ends when every step is below ``tol``. Only improvements
    are accepted, and a sweep whose fresh L came out lower (rounding) is undone.
    """
    n, q = U0.shape
    state = RankUpdatedInverse(U0, S, d, 1.0, mu, refactor_every=max(n, 10), _validated=True)
    history = [state.log_likelihood]
    steps = np.full(n, float(step0))
    poll = np.zeros((2 * q, q))
    poll[0::2][np.diag_indices(q)] = 1.0
    poll[1::2][np.diag_indices(q)] = -1.0

    def explore(i, centre, f_centre, step):
        """Best ``(x, L, trial, row)`` of the poll around ``centre``; ``f_centre=None``
        evaluates the centre too. ``trial`` is None when nothing beats the centre."""
        cand = centre + step * poll
        if f_centre is None:
            cand = np.vstack([cand, centre])
        trial = state._try_u(i, cand)
        Lc = trial.log_likelihood
        margin = 1e-12 * state.scale
        best = (centre, f_centre, None, 0)
        if f_centre is None:
            best = (centre, float(Lc[-1]), trial, 2 * q)
        gain = Lc[:2 * q].reshape(q, 2) - best[1]
        pick = np.argmax(gain, axis=1)
        up = gain[np.arange(q), pick] > margin
        j = int(np.argmax(Lc[:2 * q]))
        if Lc[j] > best[1] + margin:
            best = (cand[j], float(Lc[j]), trial, j)
        if np.count_nonzero(up) >= 2:
            x = centre + step * np.where(up, np.where(pick == 0, 1.0, -1.0), 0.0)
            combined = state._try_u(i, x[None, :])
            if combined.log_likelihood[0] > best[1] + margin:
                best = (x, float(combined.log_likelihood[0]), combined, 0)
        return best

    message = f"reached max_iter = {max_iter} sweeps"
    stopped = False
    for sweep in range(max_iter):
        if np.all(steps < tol):
            break
        start = state._U.copy()
        for i in range(n):
            if steps[i] < tol:
                continue
            base = state._U[i].copy()
            x, fx, trial, row = explore(i, base, state.log_likelihood, steps[i])
            if trial is None:
                steps[i] *= 0.5
                continue
            for _ in range(8):           # pattern moves
                px, pfx, ptrial, prow = explore(i, 2.0 * x - base, None, steps[i])
                if not pfx > fx + 1e-12 * state.scale:
                    break
                base, x, fx, trial, row = x, px, pfx, ptrial, prow
            state.accept(trial, row)
        state.refactorise()
        if state.log_likelihood < history[-1]:
            # rounding of the maintained values made this sweep a net loss: undo it
            state.set_latent(start)
            steps *= 0.5
        history.append(state.log_likelihood)
        if callback is not None and callback(sweep + 1, state.latent * l, history[-1]):
            message, stopped = "stopped by callback", True
            break
    converged = not stopped and bool(np.all(steps < tol))
    if converged:
        message = f"every step below tol = {tol:g} (in units of the length scale)"
    return (state._U.copy(), history, state.n_trials, converged, message,
            state.n_refactorisations, state.max_drift)


def _lbfgs(U0, S, d, mu, max_iter, tol, callback, l):
    """L-BFGS-B on ``-L / scale`` with the analytic gradient, in length-scale units."""
    n, q = U0.shape
    cho, logdet = _factorise(_cov(U0, mu))
    trace0 = float(np.trace(scipy.linalg.cho_solve(cho, S, check_finite=False)))
    if max_iter == 0:
        return U0, [_objective(logdet, trace0, d)], 1, False, "reached max_iter = 0", 0, 0.0
    scale = 0.5 * d * abs(logdet) + 0.5 * abs(trace0)
    if not scale > 0:
        scale = 1.0
    cache = {}
    counter = {"nev": 0}

    def fun(flat):
        counter["nev"] += 1
        U = flat.reshape(n, q)
        try:
            L, g = _value_grad_u(U, S, d, mu)
        except NotPositiveDefiniteError:
            return np.inf, np.zeros_like(flat)
        cache.clear()
        cache[flat.tobytes()] = L
        return -L / scale, -g.ravel() / scale

    history = [_objective(logdet, trace0, d)]
    last = {"x": U0.ravel().copy()}

    class _Stop(Exception):
        pass

    def cb(xk):
        key = xk.tobytes()
        L = cache[key] if key in cache else _value_u(xk.reshape(n, q), S, d, mu)
        history.append(L)
        last["x"] = xk.copy()
        if callback is not None and callback(len(history) - 1, xk.reshape(n, q) * l, L):
            raise _Stop

    try:
        res = scipy.optimize.minimize(
            fun, U0.ravel(), jac=True, method="L-BFGS-B", callback=cb,
            options={"maxiter": max_iter, "gtol": tol, "ftol": 1e3 * np.finfo(float).eps,
                     "maxcor": 20, "maxfun": 20 * max(max_iter, 1)})
        U, msg, ok = res.x.reshape(n, q), str(res.message), bool(res.success)
    except _Stop:
        U, msg, ok = last["x"].reshape(n, q), "stopped by callback", False
    return U, history, counter["nev"], ok, msg, 0, 0.0
