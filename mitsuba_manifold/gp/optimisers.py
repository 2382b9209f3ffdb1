"""The two optimisers of the GPLVM likelihood (paper Sec. 3, "Optimization"), in length-scale units.

* :func:`hooke_jeeves`, the paper's: direct search moving one latent point at a time,
  evaluated through :class:`~mitsuba_manifold.gp.rank_update.RankUpdatedInverse`;
* :func:`lbfgs`: SciPy's L-BFGS-B with the analytic gradient (O(N^3) per evaluation).

Both return an :class:`OptimiserResult`; :func:`mitsuba_manifold.gp.gplvm.fit_latent` is the
public entry point.
"""

from dataclasses import dataclass

import numpy as np
import scipy.optimize

from ..errors import NotPositiveDefiniteError
from .kernel import cov, factorise
from .likelihood import objective, value_grad_u, value_u
from .rank_update import RankUpdatedInverse


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


def hooke_jeeves(U0, S, d, mu, max_iter, tol, step0, callback, l):
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
        trial = state.try_units(i, cand)
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
    return OptimiserResult(state.units.copy(), history, state.n_trials, converged, message,
                           state.n_refactorisations, state.max_drift)


def lbfgs(U0, S, d, mu, max_iter, tol, callback, l):
    """L-BFGS-B on ``-L / scale`` with the analytic gradient, in length-scale units."""
    n, q = U0.shape
    factor = factorise(cov(U0, mu))
    logdet, trace0 = factor.logdet, float(np.trace(factor.solve(S)))
    if max_iter == 0:
        return OptimiserResult(U0, [objective(logdet, trace0, d)], 1, False, "reached max_iter = 0")
    scale = 0.5 * d * abs(logdet) + 0.5 * abs(trace0)
    if not scale > 0:
        scale = 1.0
    cache = {}
    counter = {"nev": 0}

    def fun(flat):
        counter["nev"] += 1
        U = flat.reshape(n, q)
        try:
            L, g = value_grad_u(U, S, d, mu)
        except NotPositiveDefiniteError:
            return np.inf, np.zeros_like(flat)
        cache.clear()
        cache[flat.tobytes()] = L
        return -L / scale, -g.ravel() / scale

    history = [objective(logdet, trace0, d)]
    last = {"x": U0.ravel().copy()}

    class _Stop(Exception):
        pass

    def cb(xk):
        key = xk.tobytes()
        L = cache[key] if key in cache else value_u(xk.reshape(n, q), S, d, mu)
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
    return OptimiserResult(U, history, counter["nev"], ok, msg)
