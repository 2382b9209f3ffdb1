"""The inverse covariance under single-point moves: rank-one updates (paper Sec. 3, "Optimization").

Moving one latent point changes one row and column of K. :class:`RankUpdatedInverse`
keeps ``K^-1``, ``log|K|`` and ``tr(K^-1 S)`` current with two rank-one
(Sherman-Morrison) updates and the matrix determinant lemma in O(N^2) per move, and
refactorises from scratch periodically and whenever an update loses accuracy; the
Hooke-Jeeves optimiser (:mod:`.optimisers`) evaluates its trial moves through it.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError, NotPositiveDefiniteError
from .kernel import Kernel, check_points, check_positive, factorise
from .likelihood import check_d, check_gram, objective


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

    def __init__(
        self,
        latent,
        S,
        d,
        length_scale=1.0,
        noise=1e-4,
        *,
        refactor_every=50,
        min_pivot=1e-6,
        max_correction=1e-5,
        _validated=False,
    ) -> None:
        if not _validated:
            S = check_gram(S)
            d = check_d(d)
            length_scale = check_positive("length_scale", length_scale)
            noise = check_positive("noise", noise)
            latent = check_points("latent", latent, n=S.shape[0])
        if isinstance(refactor_every, bool) or int(refactor_every) < 1:
            raise InputError(f"`refactor_every` must be an integer >= 1, got {refactor_every!r}")
        self._S = S
        self._d = float(d)
        self._l = float(length_scale)
        self._mu = float(noise)
        self._c = 1.0 + self._mu
        self._kernel = Kernel(1.0, self._mu)  # on points in units of the length scale
        self._U = np.array(latent, dtype=np.float64) / self._l
        self.refactor_every = int(refactor_every)
        self.min_pivot = float(min_pivot)
        self.max_correction = float(max_correction)
        self._version = 0
        self._prep: list | None = None
        self._logdet = self._trace = 0.0
        self.n_refactorisations = 0
        self.n_updates = 0
        self.n_trials = 0
        self.n_fresh_trials = 0
        self.max_drift = 0.0
        self.refactorise()

    # -- state
    @property
    def latent(self) -> np.ndarray:
        """Current latent points, ``(N, q)``."""
        return self._U * self._l

    @property
    def units(self) -> np.ndarray:
        """Latent points in units of the length scale (``x / l``; the array itself, do not modify)."""
        return self._U

    @property
    def K(self) -> np.ndarray:
        """Current covariance matrix (copy)."""
        return self._K.copy()

    @property
    def K_inv(self) -> np.ndarray:
        """Maintained inverse covariance (copy)."""
        return self._B.copy()

    @property
    def log_det(self) -> float:
        """Maintained ``log|K|``."""
        return self._logdet

    @property
    def trace(self) -> float:
        """Maintained ``tr(K_inv S)``."""
        return self._trace

    @property
    def log_likelihood(self) -> float:
        """Maintained L."""
        return float(objective(self._logdet, self._trace, self._d))

    @property
    def scale(self) -> float:
        """Size of L's terms, ``d/2 |log|K|| + 1/2 tr(K_inv S)``: the yardstick for rounding."""
        return 0.5 * self._d * abs(self._logdet) + 0.5 * abs(self._trace)

    def refactorise(self) -> float:
        """Recompute K, ``K_inv``, ``log|K|`` and the trace from scratch.

        Returns
        -------
        float
            Relative change of L it caused (drift of the maintained value, relative to
            :attr:`scale`); also kept as the maximum in :attr:`max_drift`.
        """
        old = self.log_likelihood if self._version else None
        K = self._kernel._K(self._U)
        self._install(K, factorise(K))
        self.n_refactorisations += 1
        drift = 0.0
        if old is not None:
            drift = abs(old - self.log_likelihood) / max(self.scale, 1e-300)
            self.max_drift = max(self.max_drift, drift)
        return drift

    def _install(self, K, factor) -> None:
        self._B = factor.inverse()
        self._K = K
        self._logdet = factor.logdet
        self._trace = float(np.sum(self._B * self._S))
        self._since = 0
        self._version += 1
        self._prep = None

    def _point(self, i) -> list:
        """``b = K_inv e_i`` and ``P = K_inv - b b^T / b_i`` (row and column i exactly zero)
        for point i, cached until the next change: ``[i, version, b, P, old]``.
        """
        if self._prep is None or self._prep[0] != i or self._prep[1] != self._version:
            b = self._B[:, i].copy()
            P = self._B - b[:, None] * (b / b[i])[None, :]
            P[i, :] = 0.0
            P[:, i] = 0.0
            self._prep = [i, self._version, b, P, None]
        return self._prep

    def _schur(self, P, k) -> tuple:
        """For rows ``k`` (``k_i = 0``): ``y = A^-1 k`` padded with ``y_i = 0``, the pivot
        ``s = (1 + mu) - k^T y`` and the relative size of the refinement correction.
        """
        y = k @ P  # P symmetric up to rounding; row/column i are zero
        dy = (k - y @ self._K) @ P  # one step of iterative refinement against exact K
        y += dy
        corr = np.sqrt(
            np.einsum("mj,mj->m", dy, dy) / np.maximum(np.einsum("mj,mj->m", y, y), 1e-300)
        )
        pivot = self._c - np.einsum("mj,mj->m", k, y)
        return y, pivot, corr

    # -- trials
    def try_moves(self, i, points) -> MoveTrial:
        """Evaluate L with point ``i`` moved to each of ``points`` ((m, q) or (q,)), O(m N^2).

        The state is not changed; pass the result to :meth:`accept` to move the point.

        Returns
        -------
        MoveTrial
        """
        n = self._U.shape[0]
        if isinstance(i, bool) or not isinstance(i, numbers.Integral) or not 0 <= i < n:
            raise InputError(f"point index {i!r} out of range for {n} points")
        pts = np.array(points, dtype=np.float64, ndmin=2)
        if pts.ndim != 2 or pts.shape[1] != self._U.shape[1]:
            raise InputError(
                f"candidate points must have shape (m, {self._U.shape[1]}), got {np.shape(points)}"
            )
        if not np.all(np.isfinite(pts)):
            raise InputError("candidate points must be finite")
        return self.try_units(int(i), pts / self._l, pts)

    def try_units(self, i, u, pts=None) -> MoveTrial:
        for attempt in range(2):
            prep = self._point(i)
            first = prep[4] is None  # then row 0 is the current position (s_old, w_old)
            uu = np.vstack([self._U[i : i + 1], u]) if first else u
            k = self._kernel._cross(uu, self._U)
            k[:, i] = 0.0
            w, pivot, corr = self._schur(prep[3], k)
            w[:, i] = -1.0  # w = A^-1 k - e_i
            if not first:
                break
            good = corr[0] <= self.max_correction and pivot[0] >= self.min_pivot * self._c
            if good or attempt == 1:
                break
            self.refactorise()  # the maintained inverse has drifted
        wsw = np.einsum("mj,mj->m", w, w @ self._S)
        if first:
            if good:  # without point i: log|A| = log|K| - log s_old, tr(A^-1 S) likewise
                prep[4] = (self._logdet - math.log(pivot[0]), self._trace - wsw[0] / pivot[0])
            else:  # point i sits (nearly) on another one: evaluate its trials from scratch
                prep[4] = (np.nan, np.nan)
            k, w, pivot, corr, wsw = k[1:], w[1:], pivot[1:], corr[1:], wsw[1:]
        logdet_out, trace_out = prep[4]
        self.n_trials += len(u)
        ok = (
            (pivot >= self.min_pivot * self._c)
            & (corr <= self.max_correction)
            & np.isfinite(logdet_out)
        )
        safe = np.where(ok, pivot, 1.0)
        logdet = logdet_out + np.log(safe)
        trace = trace_out + wsw / safe
        L = objective(logdet, trace, self._d)
        trial = MoveTrial(
            i, u * self._l if pts is None else pts, L, self._version, u, k, w, pivot, logdet, trace
        )
        for j in np.flatnonzero(~ok):
            L[j] = self._fresh_trial(trial, j)
        return trial

    def _fresh_trial(self, trial, j) -> float:
        self.n_fresh_trials += 1
        i = trial.index
        K = self._K.copy()
        K[i, :] = trial._k[j]
        K[:, i] = trial._k[j]
        K[i, i] = self._c
        try:
            factor = factorise(K)
        except NotPositiveDefiniteError:
            return -np.inf
        trace = float(np.trace(factor.solve(self._S)))
        trial._fresh[j] = (K, factor)
        trial._logdet[j] = factor.logdet
        trial._trace[j] = trace
        return float(objective(factor.logdet, trace, self._d))

    def accept(self, trial, j=0) -> float:
        """Move the point of ``trial`` to its candidate ``j``; return the new L.

        Raises
        ------
        ValueError
            If the state changed since the trial was evaluated.
        NotPositiveDefiniteError
            If that candidate makes K singular.
        """
        if trial._version != self._version:
            raise InputError("this trial was evaluated before the last change; evaluate it again")
        if not np.isfinite(trial.log_likelihood[j]):
            raise NotPositiveDefiniteError(
                f"moving point {trial.index} to {trial.points[j]} makes K singular"
            )
        i = trial.index
        self._U[i] = trial._u[j]
        self.n_updates += 1
        if j in trial._fresh:
            self._install(*trial._fresh[j])
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

    def move(self, i, point) -> float:
        """Move point ``i`` to ``point`` ((q,)); return the new L."""
        return self.accept(self.try_moves(i, np.reshape(point, (1, -1))), 0)

    def set_latent(self, latent) -> float:
        """Replace all latent points and refactorise; return the new L."""
        latent = check_points("latent", latent, n=self._U.shape[0], q=self._U.shape[1])
        self._U = latent / self._l
        self._version = 0  # no drift to measure: this is a new configuration
        self.refactorise()
        return self.log_likelihood
