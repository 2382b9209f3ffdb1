"""The two optimisers of the GPLVM likelihood (paper Sec. 3, "Optimization"), in length-scale units.

* :func:`hooke_jeeves`, the paper's: direct search moving one latent point at a time,
  evaluated through :class:`~mitsuba_manifold.gp.rank_update.RankUpdatedInverse`;
* :func:`lbfgs`: SciPy's L-BFGS-B with the analytic gradient (O(N^3) per evaluation).

Each takes the objective in units of the length scale (a :class:`~.likelihood.Likelihood`
with ``l = 1``), the starting points and its options (:class:`HookeJeevesOptions`,
:class:`LBFGSOptions`), and returns an :class:`OptimiserResult`;
:class:`mitsuba_manifold.gp.gplvm.GPLVM` (and :func:`~mitsuba_manifold.gp.gplvm.fit_latent`)
is the public entry point.
"""

import numbers
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from ..errors import InputError, NotPositiveDefiniteError
from .kernel import check_positive, factorise
from .likelihood import objective
from .rank_update import RankUpdatedInverse


def _check_max_iter(max_iter):
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

    def __post_init__(self):
        object.__setattr__(self, "max_iter", _check_max_iter(self.max_iter))
        object.__setattr__(self, "tol", check_positive("tol", self.tol))
        object.__setattr__(self, "initial_step", check_positive("initial_step", self.initial_step))


@dataclass(frozen=True)
class LBFGSOptions:
    """Settings of :func:`lbfgs`.

    Attributes
    ----------
    max_iter : int
        L-BFGS-B iterations.
    tol : float
        Stop when the largest gradient entry of ``L / scale`` with respect to ``x / l`` is
        below ``tol`` (``scale``: the size of L's terms at the start).
    """

    max_iter: int = 2000
    tol: float = 1e-7

    def __post_init__(self):
        object.__setattr__(self, "max_iter", _check_max_iter(self.max_iter))
        object.__setattr__(self, "tol", check_positive("tol", self.tol))


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


def hooke_jeeves(likelihood, U0, options=HookeJeevesOptions(), callback=None, length_scale=1.0):
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

    def explore(i, centre, f_centre, step):
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
    )


def lbfgs(likelihood, U0, options=LBFGSOptions(), callback=None, length_scale=1.0):
    """L-BFGS-B on ``-L / scale`` with the analytic gradient, in length-scale units.

    ``likelihood``, ``callback`` and ``length_scale`` as for :func:`hooke_jeeves`.
    """
    n, q = U0.shape
    S, d, max_iter, tol, l = likelihood.S, likelihood.d, options.max_iter, options.tol, length_scale
    factor = factorise(likelihood.kernel._K(U0))
    logdet, trace0 = factor.logdet, float(np.trace(factor.solve(S)))
    if max_iter == 0:
        start = objective(logdet, trace0, d) - likelihood._penalty(U0)
        return OptimiserResult(U0, [start], 1, False, "reached max_iter = 0")
    scale = 0.5 * d * abs(logdet) + 0.5 * abs(trace0)
    if not scale > 0:
        scale = 1.0
    cache = {}
    counter = {"nev": 0}

    def fun(flat):
        counter["nev"] += 1
        U = flat.reshape(n, q)
        try:
            L, g = likelihood._value_grad(U)
        except NotPositiveDefiniteError:
            return np.inf, np.zeros_like(flat)
        cache.clear()
        cache[flat.tobytes()] = L
        return -L / scale, -g.ravel() / scale

    history = [objective(logdet, trace0, d) - likelihood._penalty(U0)]
    last = {"x": U0.ravel().copy()}

    class _Stop(Exception):
        pass

    def cb(xk):
        key = xk.tobytes()
        L = cache[key] if key in cache else likelihood._value(xk.reshape(n, q))
        history.append(L)
        last["x"] = xk.copy()
        if callback is not None and callback(len(history) - 1, xk.reshape(n, q) * l, L):
            raise _Stop

    try:
        res = scipy.optimize.minimize(
            fun,
            U0.ravel(),
            jac=True,
            method="L-BFGS-B",
            callback=cb,
            options={
                "maxiter": max_iter,
                "gtol": tol,
                "ftol": 1e3 * np.finfo(float).eps,
                "maxcor": 20,
                "maxfun": 20 * max(max_iter, 1),
            },
        )
        U, msg, ok = res.x.reshape(n, q), str(res.message), bool(res.success)
    except _Stop:
        U, msg, ok = last["x"].reshape(n, q), "stopped by callback", False
    return OptimiserResult(U, history, counter["nev"], ok, msg)
