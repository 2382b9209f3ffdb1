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

Three optimisers work on the same objective (:mod:`.optimisers`), from :func:`pca_init` (the
PCA of S) by default, or :func:`mds_init` (the classical MDS of the stress term's target
distances) when there is a stress term:

* ``"hooke-jeeves"``, the paper's: direct search moving one latent point at a time. A move
  changes one row and column of K; :class:`RankUpdatedInverse` updates ``K_inv``, ``log|K|``
  and ``tr(K_inv S)`` with two rank-one (Sherman-Morrison) updates and the matrix
  determinant lemma in O(N^2), refactorising from scratch periodically and whenever an
  update loses accuracy.
* ``"lbfgs"``: SciPy's L-BFGS-B with the analytic gradient (O(N^3) per evaluation);
* ``"newton"``: trust-region Newton with exact Hessian-vector products (O(N^3) each), each
  step the model's exact minimiser on a Krylov subspace (Lanczos), a continuous function of
  the gradient and the Hessian, and its iterates rounded to a fixed grid while its steps are
  large, so that its path does not depend on the last bits of the arithmetic; optionally
  through a continuation in the noise ``mu`` (:attr:`NewtonOptions.continuation`, e.g. fits at
  ``mu = 1e-2`` and ``1e-3`` first, each from the points of the one before, then at the
  kernel's ``mu``). A larger ``mu`` smooths the likelihood, so the large-scale arrangement is
  settled where fewer local maxima compete.

The gradient-based two stop on a stated test (the projected gradient norm relative to
``d N / 2``, or the Newton step) and report whether they met it; a fit that did not warns
(:class:`~mitsuba_manifold.errors.ConvergenceWarning`). The fitted points are returned in the
canonical pose of :mod:`.pose` (the objective sees only their distances).

The model is split GPy style: :mod:`.kernel` (the :class:`~.kernel.Kernel` object:
covariance, gradients, the factorisation of K), :mod:`.likelihood` (the objective L and its
gradients), :mod:`.rank_update` (the rank-one updated inverse), :mod:`.optimisers` (with
their options dataclasses) and :mod:`.posterior` (predictions of the fitted GP). This module
holds the PCA start and the estimator: :class:`GPLVM` (scikit-learn style: settings in the
constructor, ``fit(S, d)`` returning a :class:`FitResult`) and :func:`fit_latent`, the same
as one function; it re-exports the public names of the others.

An optional stress term (:mod:`.stress`, gradient-based optimisers only) asks the latent distances to follow
given distances between the materials: the fit then maximises ``L - lambda (d N / 2) sigma``.

Internally both work in units of the length scale (``u = x / l``): scaling ``l`` and the
latent points together changes neither K nor L, so a fit at any ``l`` is the fit at ``l = 1``
scaled by ``l``.
"""

from __future__ import annotations

import contextlib
import numbers
import time
import warnings
from dataclasses import dataclass, replace

import numpy as np

from .._util.blas import one_thread
from ..errors import ConvergenceWarning, InputError, NotPositiveDefiniteError
from . import optimisers
from .kernel import MAX_LATENT_DIM, Kernel, check_points, check_positive, kernel_matrix
from .likelihood import Likelihood, check_gram, log_likelihood, log_likelihood_grad
from .optimisers import HookeJeevesOptions, LBFGSOptions, NewtonOptions
from .pose import canonical_pose
from .rank_update import MoveTrial, RankUpdatedInverse
from .stress import PenalisedLikelihood, Stress, check_distances

__all__ = [
    "MAX_LATENT_DIM",
    "NotPositiveDefiniteError",
    "Kernel",
    "Likelihood",
    "HookeJeevesOptions",
    "LBFGSOptions",
    "NewtonOptions",
    "GPLVM",
    "kernel_matrix",
    "log_likelihood",
    "log_likelihood_grad",
    "pca_init",
    "mds_init",
    "canonical_pose",
    "RankUpdatedInverse",
    "MoveTrial",
    "FitResult",
    "Stress",
    "optimiser_options",
    "fit_latent",
]

#: Up to this many materials the fit runs BLAS on one thread
#: (:func:`~mitsuba_manifold._util.blas.one_thread`): the N x N products are too small to gain
#: from threads, which only add synchronisation (badly so on a busy machine).
SINGLE_THREAD_MAX_N = 256

#: Optimisers by name, with their options type.
METHODS = {
    "hooke-jeeves": HookeJeevesOptions,
    "lbfgs": LBFGSOptions,
    "newton": NewtonOptions,
}

#: The optimisers that take a stress term (those working from the gradient).
GRADIENT_METHODS = ("lbfgs", "newton")


def check_q(q) -> int:
    if (
        isinstance(q, (bool, np.bool_))
        or not isinstance(q, numbers.Integral)
        or not 1 <= q <= MAX_LATENT_DIM
    ):
        raise InputError(
            f"`q` must be an integer from 1 to {MAX_LATENT_DIM} (the latent dimension), got {q!r}"
        )
    return int(q)


def pca_init(S, q, length_scale=1.0) -> np.ndarray:
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
    S = check_gram(S)
    q = check_q(q)
    l = check_positive("length_scale", length_scale)
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
        raise InputError(
            "Gram matrix `S` is zero: all materials are identical after mean "
            "subtraction, there is nothing to lay out"
        )
    return coords * (l / spread)


def mds_init(distances, q, length_scale=1.0) -> np.ndarray:
    """Classical multidimensional scaling of target distances, as latent starting points.

    The principal coordinates of the doubly centred ``B = -1/2 J D^2 J`` (``J = I - 1/N``):
    ``U_q sqrt(lambda_q)`` of its ``q`` largest eigenvalues (negative ones count as zero),
    scaled like :func:`pca_init` (first coordinate of standard deviation ``l``) and signed
    the same way (each axis' largest entry positive). The start of a fit with a stress term:
    the points already have the distances the term asks for, as far as ``q`` axes allow.

    Parameters
    ----------
    distances : (N, N) array_like
        Symmetric target distances, zero diagonal.
    q : int
        Latent dimension, 1 to 8.
    length_scale : float

    Returns
    -------
    (N, q) ndarray
    """
    q = check_q(q)
    l = check_positive("length_scale", length_scale)
    D = np.asarray(distances, dtype=np.float64)
    D = check_distances(D, D.shape[0] if D.ndim == 2 else -1)
    n = D.shape[0]
    J = np.eye(n) - 1.0 / n
    B = -0.5 * J @ (D * D) @ J
    lam, vec = np.linalg.eigh(0.5 * (B + B.T))
    lam, vec = lam[::-1], vec[:, ::-1]
    k = min(q, n)
    coords = np.zeros((n, q))
    coords[:, :k] = vec[:, :k] * np.sqrt(np.maximum(lam[:k], 0.0))
    big = np.argmax(np.abs(coords), axis=0)
    coords *= np.where(coords[big, np.arange(q)] < 0, -1.0, 1.0)
    spread = coords[:, 0].std()
    if not spread > 0:
        raise InputError("target `distances` place every material at one point: nothing to lay out")
    return coords * (l / spread)


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
        an L-BFGS-B or trust-region iteration otherwise); through a noise continuation
        (:attr:`stages`) each stage's values are those of its own ``mu``, the last the kernel's.
    n_evaluations : int
        Objective evaluations (trial positions for Hooke-Jeeves, L and gradient for L-BFGS).
    time_s : float
        Wall time of the optimisation.
    method : str
    converged : bool
        Whether the optimiser's convergence test was met (:mod:`.optimisers`): the gradient
        norm (L-BFGS-B, Newton) or every step (Hooke-Jeeves) at most ``tol``.
    message : str
        Why it stopped.
    length_scale, noise : float
    n_refactorisations : int
        From-scratch factorisations of K (Hooke-Jeeves).
    max_drift : float
        Largest relative disagreement between the maintained L and a fresh one (Hooke-Jeeves).
    stress : float or None
        The stress ``sigma`` of the final points (:mod:`.stress`) when the fit had a stress
        term; ``history`` then holds ``L - lambda (d N / 2) sigma``, the objective maximised.
    grad_norm : float or None
        The objective's gradient norm at the final points, relative to ``d N / 2``
        (:func:`.optimisers.gradient_norm`; in units of the length scale).
    start : str
        The start the points came from: ``"pca"``, ``"mds"`` or ``"given"``.
    stages : list of (float, int)
        The noise levels ``mu`` fitted in turn and each one's iterations
        (:meth:`GPLVM.noise_stages`); one entry when there was no continuation.
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
    stress: float = None
    grad_norm: float = None
    start: str = "given"
    stages: list = None

    @property
    def n_iterations(self) -> int:
        """Iterations done (sweeps for Hooke-Jeeves)."""
        return len(self.history) - 1

    @property
    def kernel(self) -> Kernel:
        """The :class:`Kernel` the points were fitted with."""
        return Kernel(self.length_scale, self.noise)


class GPLVM:
    """The GPLVM fit of latent points to a Gram matrix (paper Sec. 3), scikit-learn style:
    settings in the constructor, data in :meth:`fit`.

    Parameters
    ----------
    q : int
        Latent dimension, 1 to 8.
    kernel : Kernel, optional
        ``l`` and ``mu > 0`` (default ``Kernel()``: ``l = 1``, ``mu = 1e-4``).
    method : {"hooke-jeeves", "lbfgs", "newton"}
        The paper's direct search with rank-one updates, L-BFGS-B with the gradient, or
        trust-region Newton with exact Hessian products (its model solved on a Krylov
        subspace).
    options : HookeJeevesOptions, LBFGSOptions or NewtonOptions, optional
        The optimiser's settings (default: the method's defaults).
    stress : Stress, optional
        The stress term's weight and pairs (:mod:`.stress`; default none). A term with weight
        > 0 needs ``method="newton"`` or ``"lbfgs"`` and the target distances in :meth:`fit`.

    Notes
    -----
    Hooke-Jeeves moves single points, so collective motions of the whole cloud are slow
    for it: on strongly coupled layouts it can stop (every step below ``tol``) at a lower L
    than L-BFGS; a smaller ``tol`` goes further at a higher cost. For ``N <= 256`` BLAS runs
    single-threaded during the fit.
    """

    def __init__(self, q=2, kernel=None, method="hooke-jeeves", options=None, stress=None) -> None:
        self.q = check_q(q)
        self.kernel = Kernel() if kernel is None else kernel
        check_positive("noise", self.kernel.noise)
        if method not in METHODS:
            raise InputError(f"unknown `method` {method!r}; use one of {', '.join(METHODS)}")
        self.method = method
        self.options = METHODS[method]() if options is None else options
        if not isinstance(self.options, METHODS[method]):
            raise InputError(
                f"`options` of method {method!r} must be a {METHODS[method].__name__}, "
                f"got {type(options).__name__}"
            )
        self.stress = Stress() if stress is None else stress
        if not isinstance(self.stress, Stress):
            raise InputError(f"`stress` must be a gplvm.Stress, got {type(stress).__name__}")
        if self.stress.active and method not in GRADIENT_METHODS:
            raise InputError(
                f"a stress term (weight {self.stress.weight:g}) needs method 'newton' or "
                f"'lbfgs', got {method!r}; use one of those or stress weight 0"
            )

    def fit(self, S, d, init=None, callback=None, distances=None) -> FitResult:
        """Latent points maximising the log-likelihood L (Eq. 6) of Gram matrix ``S``.

        The points come back in the canonical pose (:func:`.pose.canonical_pose`): the fit
        fixes them only up to a rigid motion, which changes neither L nor the stress term.
        A fit whose convergence test was not met warns (:class:`ConvergenceWarning`).

        Parameters
        ----------
        S : (N, N) array_like
            Gram matrix ``Z Z^T`` of the mean-subtracted observations (float64).
        d : int
            Number of values per material.
        init : (N, q) array_like, optional
            Starting points; by default :func:`mds_init` of ``distances`` when there is a
            stress term (the points then start with the distances it asks for), else
            :func:`pca_init` of ``S``.
        callback : callable, optional
            ``callback(iteration, latent, L)`` after each iteration (points as the optimiser
            has them, before the pose); returning True stops.
        distances : (N, N) array_like, optional
            The stress term's target distances between the materials (needed when it is on,
            unused otherwise).

        Returns
        -------
        FitResult
        """
        likelihood = Likelihood(S, d, self.kernel)
        term = None
        if self.stress.active:
            if distances is None:
                raise InputError(
                    "a stress term needs the target `distances` between the materials; "
                    "pass distances=(N, N) array or use stress weight 0"
                )
            term = self.stress.term(distances, likelihood.n, likelihood.d)
        l = self.kernel.length_scale
        if init is not None:
            X0, start = check_points("init", init, n=likelihood.n, q=self.q), "given"
        elif term is not None:
            X0, start = mds_init(term.D, self.q, l), "mds"
        else:
            X0, start = pca_init(likelihood.S, self.q, l), "pca"
        if callback is not None and not callable(callback):
            raise InputError("`callback` must be callable")
        unit = likelihood.in_units()
        run = getattr(optimisers, self.method.replace("-", "_"))
        single = likelihood.n <= SINGLE_THREAD_MAX_N  # small fits: BLAS threads only wait
        t0 = time.perf_counter()
        stages = [(mu, None) for mu in self.noise_stages()[:-1]] + [(self.kernel.noise, unit)]
        history: list
        U, history, n_evaluations, done = X0 / l, [], 0, []
        with one_thread() if single else contextlib.nullcontext():
            for mu, stage in stages:
                if stage is None:  # a continuation stage: the same data at a larger noise
                    stage = Likelihood(likelihood.S, likelihood.d, Kernel(1.0, mu), _checked=True)
                target = stage if term is None else PenalisedLikelihood(stage, term)
                options = self.options
                if len(stages) > 1:  # max_iter caps the whole fit, every stage together
                    used = max(len(history) - 1, 0)
                    options = replace(options, max_iter=max(options.max_iter - used, 0))
                later = {"snap_start": False} if history else {}  # a converged stage's points
                res = run(target, U, options, _offset(callback, len(history)), l, **later)
                U = res.units
                history += res.history if not history else res.history[1:]
                n_evaluations += res.n_evaluations
                done.append((mu, len(res.history) - 1))
                if res.message == "stopped by callback":
                    break
            units = canonical_pose(res.units)
            L = unit._value(units)
            sigma = None if term is None else term.value(units)
        if options.max_iter != self.options.max_iter and not res.converged:
            res.message = res.message.replace(
                f"max_iter = {options.max_iter}",
                f"max_iter = {self.options.max_iter} (every noise stage together)",
            )
        if len(done) > 1:
            res.message += (
                " (after noise continuation "
                + ", ".join(f"mu = {mu:g}: {k} iterations" for mu, k in done[:-1])
                + ")"
            )
        if not res.converged and res.message != "stopped by callback":
            warnings.warn(
                f"the GPLVM fit ({self.method}, N = {likelihood.n}, q = {self.q}) did not "
                f"converge: {res.message}; the layout is not a stationary point and may "
                "differ between machines (raise max_iter, or see FitResult.message)",
                ConvergenceWarning,
                stacklevel=2,
            )
        return FitResult(
            latent=units * l,
            log_likelihood=L,
            history=np.asarray(history, dtype=np.float64),
            n_evaluations=n_evaluations,
            time_s=time.perf_counter() - t0,
            method=self.method,
            converged=res.converged,
            message=res.message,
            length_scale=l,
            noise=self.kernel.noise,
            n_refactorisations=res.n_refactorisations,
            max_drift=res.max_drift,
            stress=sigma,
            grad_norm=res.grad_norm,
            start=start,
            stages=done,
        )

    def noise_stages(self) -> list:
        """The noise levels ``mu`` the fit goes through, the kernel's last: the optimiser's
        ``continuation`` levels above the kernel's ``mu`` (Newton; :class:`NewtonOptions`),
        largest first, each stage starting from the points of the one before.
        """
        levels = getattr(self.options, "continuation", ())
        return [mu for mu in levels if mu > self.kernel.noise] + [self.kernel.noise]


def _offset(callback, k):
    """``callback`` with its iteration numbers counted on from ``k`` (a later stage's)."""
    if callback is None or k == 0:
        return callback
    return lambda i, X, F: callback(i + k - 1, X, F)


def optimiser_options(
    method, *, max_iter=None, tol=None, initial_step=None, continuation=None, krylov=None
) -> HookeJeevesOptions | LBFGSOptions | NewtonOptions:
    """The settings of the optimiser ``method`` (:data:`METHODS`), its defaults but those given.

    Parameters
    ----------
    method : {"hooke-jeeves", "lbfgs", "newton"}
    max_iter : int, optional
        The safety cap: sweeps over all points (Hooke-Jeeves, default 500), L-BFGS-B
        iterations (default 20000) or trust-region iterations (Newton, default 2000).
    tol : float, optional
        Hooke-Jeeves: converged when every point's step is below ``tol * l`` (default 1e-3).
        L-BFGS-B and Newton: converged when the projected gradient norm of ``F / (d N / 2)``
        with respect to ``x / l`` is at most ``tol`` (default 1e-7;
        :func:`.optimisers.gradient_norm`).
    initial_step : float, optional
        Hooke-Jeeves: first step, in units of ``l`` (default 0.25; unused by the others).
    continuation : sequence of float, optional
        Newton: the noise levels fitted before the kernel's, largest first (default ``()``:
        none; e.g. ``(1e-2, 1e-3)``; :class:`NewtonOptions`).
    krylov : int, optional
        Newton: the dimension of the Krylov subspace each step is solved on (default 64;
        :class:`NewtonOptions`).

    Returns
    -------
    HookeJeevesOptions, LBFGSOptions or NewtonOptions
    """
    if method not in METHODS:
        raise InputError(f"unknown `method` {method!r}; use one of {', '.join(METHODS)}")
    given = {k: v for k, v in (("max_iter", max_iter), ("tol", tol)) if v is not None}
    if initial_step is not None:
        step = check_positive("initial_step", initial_step)
        if method == "hooke-jeeves":
            given["initial_step"] = step
    for name, value, what in (
        ("continuation", continuation, "noise levels fitted first"),
        ("krylov", krylov, "the dimension of each step's Krylov subspace"),
    ):
        if value is None:
            continue
        if method != "newton":
            raise InputError(
                f"`{name}` ({what}) is an option of method 'newton', not {method!r}; leave it "
                f"out or use method='newton'"
            )
        given[name] = value
    return METHODS[method](**given)


def fit_latent(
    S,
    d,
    q=2,
    *,
    method="hooke-jeeves",
    length_scale=1.0,
    noise=1e-4,
    init=None,
    options=None,
    callback=None,
) -> FitResult:
    """Latent points maximising the GPLVM log-likelihood L (Eq. 6): :class:`GPLVM` as one call.

    ``GPLVM(q, Kernel(length_scale, noise), method, options).fit(S, d, init, callback)``; a
    fit with a stress term is made with :class:`GPLVM` itself.

    Parameters
    ----------
    S, d, init, callback
        See :meth:`GPLVM.fit`.
    q, method
        See :class:`GPLVM`.
    length_scale, noise : float
        ``l`` and ``mu`` of the :class:`Kernel`.
    options : HookeJeevesOptions or LBFGSOptions, optional
        The optimiser's settings, of ``method``'s type (default: its defaults; see
        :func:`optimiser_options`).

    Returns
    -------
    FitResult
    """
    kernel = Kernel(check_positive("length_scale", length_scale), check_positive("noise", noise))
    if method not in METHODS:
        raise InputError(f"unknown `method` {method!r}; use one of {', '.join(METHODS)}")
    options = METHODS[method]() if options is None else options
    if not isinstance(options, METHODS[method]):
        raise InputError(
            f"`options` of method {method!r} must be a {METHODS[method].__name__}, "
            f"got {type(options).__name__}; make them with gplvm.optimiser_options"
        )
    return GPLVM(q, kernel, method, options).fit(S, d, init, callback)
