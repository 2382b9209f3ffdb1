"""The optimisers of the GPLVM likelihood (paper Sec. 3, "Optimization"), in length-scale units.

* :func:`hooke_jeeves`, the paper's: direct search moving one latent point at a time,
  evaluated through :class:`~mitsuba_manifold.gp.rank_update.RankUpdatedInverse`; it stops
  when every point's step is below ``tol``;
* :func:`lbfgs`: SciPy's L-BFGS-B with the analytic gradient (O(N^3) per evaluation);
* :func:`newton`: trust-region Newton with exact Hessian-vector products (O(N^3) each), its
  model solved exactly on a Krylov subspace (Lanczos).

The gradient-based two minimise ``-F / (d N / 2)`` (``F``: L, less the stress term when there
is one) and share one convergence test: the gradient's norm relative to that scale,
:func:`gradient_norm` ``<= tol``; their ``max_iter`` is a safety cap, and a fit that reaches
it is reported as not converged. Every optimiser records the final gradient norm.

Each takes the objective in units of the length scale (a :class:`~.likelihood.Likelihood`
with ``l = 1``), the starting points and its options (:class:`HookeJeevesOptions`,
:class:`LBFGSOptions`, :class:`NewtonOptions`), and returns an :class:`OptimiserResult`;
:class:`mitsuba_manifold.gp.gplvm.GPLVM` (and :func:`~mitsuba_manifold.gp.gplvm.fit_latent`)
is the public entry point.
"""

from __future__ import annotations

import functools
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.optimize

from ..errors import InputError, NotPositiveDefiniteError
from .kernel import check_positive
from .pose import rigid_modes
from .rank_update import RankUpdatedInverse

if TYPE_CHECKING:
    from typing import Any


def _check_max_iter(max_iter) -> int:
    if isinstance(max_iter, bool) or not isinstance(max_iter, numbers.Integral) or max_iter < 0:
        raise InputError(f"`max_iter` must be an integer >= 0, got {max_iter!r}")
    return int(max_iter)


@dataclass(frozen=True)
class HookeJeevesOptions:
    """Settings of :func:`hooke_jeeves`.

    Attributes
    ----------
    max_iter : int
        Sweeps over all points.
    tol : float
        Stop when every point's step is below ``tol`` (in units of ``l``).
    initial_step : float
        First step of every point, in units of ``l``.
    """

    max_iter: int = 500
    tol: float = 1e-3
    initial_step: float = 0.25

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_iter", _check_max_iter(self.max_iter))
        object.__setattr__(self, "tol", check_positive("tol", self.tol))
        object.__setattr__(self, "initial_step", check_positive("initial_step", self.initial_step))


@dataclass(frozen=True)
class LBFGSOptions:
    """Settings of :func:`lbfgs`.

    Attributes
    ----------
    max_iter : int
        Most L-BFGS-B iterations (a safety cap: reaching it leaves the fit unconverged).
    tol : float
        Converged when the gradient's relative norm (:func:`gradient_norm`) is at most ``tol``.
    """

    max_iter: int = 20000
    tol: float = 1e-7

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_iter", _check_max_iter(self.max_iter))
        object.__setattr__(self, "tol", check_positive("tol", self.tol))


@dataclass(frozen=True)
class NewtonOptions:
    """Settings of :func:`newton`.

    Attributes
    ----------
    max_iter : int
        Most trust-region iterations, every stage of the ``continuation`` together (a safety
        cap: reaching it leaves the fit unconverged).
    tol : float
        Converged when the gradient's relative norm (:func:`gradient_norm`) is at most ``tol``.
    step_tol : float
        Or when the Newton step (the model's minimiser on the Krylov subspace, inside the
        trust region) moves no coordinate by more than ``step_tol`` (in units of ``l``): near
        a maximum it approximates the full Newton step, so the points are about that close to
        the stationary point, where the gradient's own rounding (``d K^-1`` and
        ``K^-1 S K^-1`` nearly cancel there) keeps its norm above ``tol``.
    continuation : tuple of float
        Noise levels ``mu`` fitted first, largest first, each from the points of the one
        before (:class:`~mitsuba_manifold.gp.gplvm.GPLVM`), e.g. ``(1e-2, 1e-3)``: a larger
        ``mu`` smooths the likelihood, so the first stages settle the layout's large-scale
        arrangement where few local maxima compete and the last one, at the kernel's own
        ``mu``, refines it. Levels at or below the kernel's ``mu`` are skipped; ``()`` (the
        default): one fit at the kernel's ``mu``.
    krylov : int
        The dimension of the Krylov subspace each step's model is solved on
        (:class:`_KrylovModel`; at most the number of unknowns): more Hessian products per
        step, and steps closer to the full Newton step.
    """

    max_iter: int = 2000
    tol: float = 1e-7
    step_tol: float = 1e-5
    continuation: tuple = ()
    krylov: int = 64

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_iter", _check_max_iter(self.max_iter))
        object.__setattr__(self, "tol", check_positive("tol", self.tol))
        object.__setattr__(self, "step_tol", check_positive("step_tol", self.step_tol))
        if (
            isinstance(self.krylov, bool)
            or not isinstance(self.krylov, numbers.Integral)
            or self.krylov < 1
        ):
            raise InputError(
                f"`krylov` (the dimension of each step's Krylov subspace) must be an integer "
                f">= 1, got {self.krylov!r}"
            )
        object.__setattr__(self, "krylov", int(self.krylov))
        try:
            levels = tuple(float(check_positive("continuation", v)) for v in self.continuation)
        except TypeError:
            raise InputError(
                f"`continuation` must be a sequence of noise levels > 0 (largest first), "
                f"got {self.continuation!r}"
            ) from None
        if any(b >= a for a, b in zip(levels, levels[1:])):
            raise InputError(
                f"`continuation` noise levels must decrease (largest first), got {levels}"
            )
        object.__setattr__(self, "continuation", levels)


def objective_scale(likelihood) -> float:
    """``d N / 2``: the gradient-based optimisers work on ``L / (d N / 2)``, the objective per
    value and material, whose size does not grow with the data.
    """
    return 0.5 * likelihood.d * likelihood.n


def project(g, Q) -> np.ndarray:
    """``(I - Q Q^T) g``: ``g`` (flat) without its components along the rigid motions ``Q``
    (:func:`.pose.rigid_modes`).
    """
    return g - Q @ (Q.T @ g)


def gradient_norm(likelihood, U) -> float:
    """The convergence test's measure: ``|P dF/du|_2 / (d N / 2)`` at points ``U`` in units of
    the length scale (``F`` the objective maximised: L, less the stress term when there is one;
    ``P`` the projection off the rigid motions, :func:`project`, along which F is constant).
    Zero exactly at a stationary point; ``inf`` where K is not positive definite.
    """
    try:
        _, g = likelihood._value_grad(U)
    except NotPositiveDefiniteError:
        return float("inf")
    g = project(g.ravel(), rigid_modes(U))
    return float(np.linalg.norm(g) / objective_scale(likelihood))


@dataclass
class OptimiserResult:
    """What an optimiser found, in units of the length scale."""

    units: np.ndarray
    history: list
    n_evaluations: int
    converged: bool
    message: str
    n_refactorisations: int = 0
    max_drift: float = 0.0
    grad_norm: float = None


def hooke_jeeves(  # noqa: C901  its poll, defined inside, shares the search state
    likelihood, U0, options=HookeJeevesOptions(), callback=None, length_scale=1.0
) -> OptimiserResult:
    """Hooke-Jeeves direct search, one latent point at a time, in length-scale units.

    ``likelihood``: the objective with ``l = 1`` (:meth:`Likelihood.in_units`); ``callback``
    gets the points times ``length_scale``.

    For each point: an exploratory poll of ``+-step`` along every coordinate (evaluated in
    one batch), plus the move combining every improving coordinate; then pattern moves
    ``x + (x - base)``, polled the same way, while they improve. A point whose poll fails
    halves its step; the search ends when every step is below ``tol``. Only improvements
    are accepted, and a sweep whose fresh L came out lower (rounding) is undone.
    """
    n, q = U0.shape
    max_iter, tol, l = options.max_iter, options.tol, length_scale
    state = RankUpdatedInverse(
        U0,
        likelihood.S,
        likelihood.d,
        1.0,
        likelihood.kernel.noise,
        refactor_every=max(n, 10),
        _validated=True,
    )
    history = [state.log_likelihood]
    steps = np.full(n, float(options.initial_step))
    poll = np.zeros((2 * q, q))
    poll[0::2][np.diag_indices(q)] = 1.0
    poll[1::2][np.diag_indices(q)] = -1.0

    def explore(i, centre, f_centre, step) -> tuple[Any, Any, None, int]:
        """Best ``(x, L, trial, row)`` of the poll around ``centre``; ``f_centre=None``
        evaluates the centre too. ``trial`` is None when nothing beats the centre.
        """
        cand = centre + step * poll
        if f_centre is None:
            cand = np.vstack([cand, centre])
        trial = state.try_units(i, cand)
        Lc = trial.log_likelihood
        margin = 1e-12 * state.scale
        best = (centre, f_centre, None, 0)
        if f_centre is None:
            best = (centre, float(Lc[-1]), trial, 2 * q)
        gain = Lc[: 2 * q].reshape(q, 2) - best[1]
        pick = np.argmax(gain, axis=1)
        up = gain[np.arange(q), pick] > margin
        j = int(np.argmax(Lc[: 2 * q]))
        if Lc[j] > best[1] + margin:
            best = (cand[j], float(Lc[j]), trial, j)
        if np.count_nonzero(up) >= 2:
            x = centre + step * np.where(up, np.where(pick == 0, 1.0, -1.0), 0.0)
            combined = state.try_units(i, x[None, :])
            if combined.log_likelihood[0] > best[1] + margin:
                best = (x, float(combined.log_likelihood[0]), combined, 0)
        return best

    message = f"reached max_iter = {max_iter} sweeps"
    stopped = False
    for sweep in range(max_iter):
        if np.all(steps < tol):
            break
        start = state.units.copy()
        for i in range(n):
            if steps[i] < tol:
                continue
            base = state.units[i].copy()
            x, fx, trial, row = explore(i, base, state.log_likelihood, steps[i])
            if trial is None:
                steps[i] *= 0.5
                continue
            for _ in range(8):  # pattern moves
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
    return OptimiserResult(
        state.units.copy(),
        history,
        state.n_trials,
        converged,
        message,
        state.n_refactorisations,
        state.max_drift,
        gradient_norm(likelihood, state.units),
    )


class _Scaled:
    """``-F / (d N / 2)`` and its derivatives for SciPy's minimisers, counting evaluations,
    keeping the last value (the per-iteration history) and ``inf`` where K is not positive
    definite (the step is then rejected).
    """

    def __init__(self, likelihood, n, q) -> None:
        self.likelihood, self.shape = likelihood, (n, q)
        self.scale = objective_scale(likelihood)
        self.n_evaluations = 0
        self.last: dict = {}
        self._q = None

    def fun(self, flat) -> tuple[float, Any]:
        """Value and projected gradient (:func:`project`)."""
        self.n_evaluations += 1
        U = flat.reshape(self.shape)
        try:
            F, g = self.likelihood._value_grad(U)
        except NotPositiveDefiniteError:
            return np.inf, np.zeros_like(flat)
        self.last = {flat.tobytes(): F}
        return -F / self.scale, -project(g.ravel(), self._modes(flat)) / self.scale

    def hessp(self, flat, p) -> np.ndarray:
        """The projected Hessian ``P H P`` times ``p``."""
        Q = self._modes(flat)
        H = self.likelihood._hessp(flat.reshape(self.shape), project(p, Q).reshape(self.shape))
        return -project(H.ravel(), Q) / self.scale

    def _modes(self, flat) -> np.ndarray:
        key = flat.tobytes()
        if self._q is None or self._q[0] != key:
            self._q = (key, rigid_modes(flat.reshape(self.shape)))
        return self._q[1]

    def value(self, flat) -> float:
        key = flat.tobytes()
        return (
            self.last[key] if key in self.last else self.likelihood._value(flat.reshape(self.shape))
        )


def _minimise(likelihood, U0, method, options, callback, l, extra) -> OptimiserResult:
    """SciPy's ``method`` on ``-F / (d N / 2)`` from ``U0``; converged by :func:`gradient_norm`."""
    n, q = U0.shape
    f = _Scaled(likelihood, n, q)
    start = likelihood._value(U0)
    history = [start]
    if options.max_iter == 0:
        norm = gradient_norm(likelihood, U0)
        ok = norm <= options.tol
        return OptimiserResult(U0, history, 1, ok, "reached max_iter = 0", grad_norm=norm)
    last = {"x": U0.ravel().copy()}

    class _Stop(Exception):
        pass

    def cb(xk) -> None:
        F = f.value(xk)
        history.append(F)
        last["x"] = xk.copy()
        if callback is not None and callback(len(history) - 1, xk.reshape(n, q) * l, F):
            raise _Stop

    stopped = False
    try:
        res = scipy.optimize.minimize(
            f.fun, U0.ravel(), jac=True, method=method, callback=cb, **extra(f)
        )
        U, msg = res.x.reshape(n, q), str(res.message)
    except _Stop:
        U, msg, stopped = last["x"].reshape(n, q), "stopped by callback", True
    norm = gradient_norm(likelihood, U)
    ok = not stopped and norm <= options.tol
    if ok:
        msg = f"gradient norm {norm:.3g} <= tol = {options.tol:g}"
    elif not stopped:
        cap = len(history) - 1 >= options.max_iter
        msg = (
            f"{'reached max_iter = ' + str(options.max_iter) if cap else msg}; gradient norm "
            f"{norm:.3g} > tol = {options.tol:g}"
        )
    return OptimiserResult(U, history, f.n_evaluations, ok, msg, grad_norm=norm)


def lbfgs(
    likelihood, U0, options=LBFGSOptions(), callback=None, length_scale=1.0
) -> OptimiserResult:
    """L-BFGS-B on ``-F / (d N / 2)`` with the analytic gradient, in length-scale units.

    ``likelihood``, ``callback`` and ``length_scale`` as for :func:`hooke_jeeves`. Stops when
    the gradient's largest entry is below ``tol / sqrt(N q)`` (so its norm is below ``tol``),
    when no step improves, or at ``max_iter``; converged when :func:`gradient_norm` ``<= tol``.
    """
    n, q = U0.shape

    def extra(f) -> dict:
        gtol = options.tol / np.sqrt(n * q)
        return {
            "options": {
                "maxiter": options.max_iter,
                "gtol": gtol,
                "ftol": 0.0,
                "maxcor": 20,
                "maxfun": 20 * max(options.max_iter, 1),
            }
        }

    return _minimise(likelihood, U0, "L-BFGS-B", options, callback, length_scale, extra)


#: The grid (in units of the length scale) that :func:`newton` rounds its iterates to while
#: they move by more than :data:`SNAP_ABOVE`: a power of two, so rounding is exact.
SNAP_GRID = 2.0**-10
#: Steps whose largest entry is above this (in units of ``l``) end on the grid.
SNAP_ABOVE = 2.0**-5
#: Lanczos stops early when the new direction's norm is below this, relative to the
#: tridiagonal's entries so far: the subspace is then invariant under H.
BREAKDOWN = 1e-12
#: Bisection steps of the secular equation at most (it stops when the interval's ends meet).
#: A boundary step shorter than the radius by more than this fraction after the bisection is
#: the hard case (:meth:`_KrylovModel.step`).
BISECTIONS = 200
HARD_CASE = 1e-8
#: Relative size of a predicted gain below which the objective's own rounding (that of
#: ``log|K|`` with an ill-conditioned K) could hide it: such a step is taken when it lowers the
#: gradient norm instead.
ROUNDING = 1e-10
#: The trust radius: initial, largest and smallest (below it no step improves: the
#: objective's rounding is reached). Powers of two, changed by factors of two and four.
RADIUS = (1.0, 64.0, 2.0**-40)


class _KrylovModel:
    """The quadratic model ``m(p) = g.p + p.H p / 2`` of one trust-region iteration on the
    Krylov subspace ``span{g, H g, ..., H^(k-1) g}``, solved exactly there for any radius.

    Lanczos with full reorthogonalisation gives an orthonormal basis ``Q`` ((k, n) rows) and
    the tridiagonal ``T = Q H Q^T``; with ``T = V diag(e) V^T`` and ``c = |g| V^T e_1`` the
    model's minimiser within ``|p| <= radius`` is ``p = -Q^T V (c / (e + lam))`` with
    ``lam = 0`` when ``T`` is positive definite and that step lies inside, else the ``lam >=
    max(0, -e_min)`` where ``|c / (e + lam)| = radius`` (Moré and Sorensen's secular equation,
    solved by bisection). The step is a continuous function of ``g`` and ``H`` (no truncation
    test decides where it ends, as the loose residual and boundary tests of truncated
    conjugate gradients do), so arithmetic that differs in its last bits gives steps that
    differ in their last bits. ``k`` is ``m`` unless the subspace is invariant under ``H``
    sooner (Lanczos breaks down: the model is then exact). A rejected step's smaller radius
    is solved again without new Hessian products.
    """

    def __init__(self, hessp, g, m) -> None:
        n = g.size
        m = min(m, n)
        gnorm = float(np.linalg.norm(g))
        Q = np.empty((m, n))
        alpha, beta = np.empty(m), np.empty(m)
        v, k = g / gnorm, m
        for j in range(m):
            Q[j] = v
            w = hessp(v)
            alpha[j] = v @ w
            for _ in range(2):  # twice is enough (Kahan's "twice is enough")
                w = w - Q[: j + 1].T @ (Q[: j + 1] @ w)
            beta[j] = np.linalg.norm(w)
            if beta[j] <= BREAKDOWN * max(np.abs(alpha[: j + 1]).max(), beta[: j + 1].max()):
                k = j + 1  # an invariant subspace: the model is exact there
                break
            v = w / beta[j]
        self._factor(alpha[:k], beta[: k - 1], Q[:k], gnorm)

    def _factor(self, alpha, beta, Q, gnorm) -> None:
        T = np.diag(alpha) + np.diag(beta, 1) + np.diag(beta, -1)
        self.e, V = np.linalg.eigh(T)
        self.basis = V.T @ Q  # the eigenvectors of T as steps (rows)
        self.c = gnorm * V[0]

    def _size(self, lam) -> float:
        with np.errstate(divide="ignore"):
            return float(np.linalg.norm(self.c / (self.e + lam)))

    def step(self, radius) -> tuple[Any, bool, float]:
        """The model's minimiser within ``radius``, whether it is on the boundary, and the
        decrease the model predicts, ``-m(p)``.
        """
        e, c = self.e, self.c
        if e[0] > 0 and self._size(0.0) <= radius:
            y, boundary = -c / e, False
        else:
            lo = max(0.0, -e[0])
            hi = lo + max(np.linalg.norm(c) / radius, np.finfo(float).tiny)
            while self._size(hi) > radius:
                hi = lo + 2.0 * (hi - lo)
            for _ in range(BISECTIONS):
                mid = 0.5 * (lo + hi)
                if mid in (lo, hi):
                    break
                if self._size(mid) > radius:
                    lo = mid
                else:
                    hi = mid
            shift = e + hi
            y = np.where(shift > 0, -c / np.where(shift > 0, shift, 1.0), 0.0)
            if e[0] <= 0 and y @ y < (radius * (1.0 - HARD_CASE)) ** 2:
                # the (near-)hard case: g has (almost) nothing along the lowest eigenvector, so
                # the step stays inside as lam -> -e_min; it is completed to the boundary along
                # that vector, downhill in the model (Moré and Sorensen)
                tau = np.sqrt(max(radius * radius - y[1:] @ y[1:], 0.0))
                y[0] = -tau if c[0] > 0 else tau
            boundary = True
        predicted = -(c @ y + 0.5 * (e * y) @ y)
        return self.basis.T @ y, boundary, float(predicted)


def newton(  # noqa: C901  a trust-region iteration read as a whole
    likelihood, U0, options=NewtonOptions(), callback=None, length_scale=1.0, snap_start=True
) -> OptimiserResult:
    """Trust-region Newton on ``-F / (d N / 2)``, in length-scale units.

    Each iteration minimises the quadratic model on the exact Hessian-vector products
    (:meth:`Likelihood._hessp`, the stress term's :meth:`~.stress.StressTerm.hessp`) inside
    the trust region, exactly on the Krylov subspace of dimension ``options.krylov``
    (:class:`_KrylovModel`), following directions of negative curvature out of saddles. A
    step is taken when it gains more than a tenth of what the model predicts (a predicted
    gain below :data:`ROUNDING` of the objective: when it lowers the gradient norm and loses
    nothing); the radius (a power of two) is quartered below a quarter and doubled above
    three quarters on the boundary.

    So that the path depends on the data and not on the last bits of its arithmetic (BLAS
    kernels, summation order), each step is a continuous function of the gradient and the
    Hessian (:class:`_KrylovModel`), and the start (unless ``snap_start`` is False: a start
    that is itself a converged fit, whose last bits rounding could only amplify) and every
    iterate after a step larger than :data:`SNAP_ABOVE` are rounded to the grid
    :data:`SNAP_GRID`: two runs whose numbers differ in the last bits land on the same grid
    points, and end at the same maximum. The last small steps, off the grid, converge to it.

    ``likelihood``, ``callback`` and ``length_scale`` as for :func:`hooke_jeeves`. Stops when
    :func:`gradient_norm` is at most ``tol`` or the model's step, inside the region, at most
    ``step_tol`` (converged, :class:`NewtonOptions`), when the radius falls below
    ``RADIUS[2]`` (no step improves: not converged) or at ``max_iter`` (not converged).
    """
    n, q = U0.shape
    l = length_scale
    f = _Scaled(likelihood, n, q)
    x = U0.ravel().copy()
    if snap_start:
        x = np.round(x / SNAP_GRID) * SNAP_GRID
    fx, g = f.fun(x)
    if not np.isfinite(fx):
        raise NotPositiveDefiniteError(
            "the starting latent points give a covariance matrix K that is not positive "
            "definite (points coincide); separate them or use a larger `noise` mu"
        )
    history = [-fx * f.scale]
    radius, largest, smallest = RADIUS
    message = f"reached max_iter = {options.max_iter}"
    stopped, newton_step, model = False, None, None
    for _ in range(options.max_iter):
        if np.linalg.norm(g) <= options.tol:
            break
        if model is None:  # the same model serves the smaller radii after a rejection
            model = _KrylovModel(functools.partial(f.hessp, x), g, options.krylov)
        step, boundary, predicted = model.step(radius)
        if not boundary and np.abs(step).max() <= options.step_tol:
            newton_step = float(np.abs(step).max())
            break
        trial = x + step
        if np.abs(step).max() > SNAP_ABOVE:
            trial = np.round(trial / SNAP_GRID) * SNAP_GRID
        f_trial, g_trial = f.fun(trial)
        rho = (fx - f_trial) / predicted if predicted > 0 else -np.inf
        if 0 < predicted < ROUNDING * max(abs(fx), 1.0) and np.isfinite(f_trial):
            # gains below the objective's rounding: judge the step by the gradient it leaves,
            # never taking a loss (the history stays monotone)
            better = np.linalg.norm(g_trial) < np.linalg.norm(g) and f_trial <= fx
            rho = 1.0 if better else -np.inf
        if rho < 0.25:
            radius /= 4.0
        elif rho > 0.75 and boundary:
            radius = min(2.0 * radius, largest)
        if rho > 0.1:
            x, fx, g, model = trial, f_trial, g_trial, None
            history.append(-fx * f.scale)
            if callback is not None and callback(
                len(history) - 1, x.reshape(n, q) * l, history[-1]
            ):
                message, stopped = "stopped by callback", True
                break
        if radius < smallest:
            message = "no step improves (trust radius below the objective's rounding)"
            break
    U = x.reshape(n, q)
    norm = gradient_norm(likelihood, U)
    ok = not stopped and (norm <= options.tol or newton_step is not None)
    if norm <= options.tol and not stopped:
        message = f"gradient norm {norm:.3g} <= tol = {options.tol:g}"
    elif ok:
        message = (
            f"Newton step {newton_step:.3g} <= step_tol = {options.step_tol:g} (gradient norm "
            f"{norm:.3g}, at its rounding)"
        )
    elif not stopped:
        message += f"; gradient norm {norm:.3g} > tol = {options.tol:g}"
    return OptimiserResult(U, history, f.n_evaluations, ok, message, grad_norm=norm)
