"""Interpolation weights ``w(x)``: how a latent point combines the measured tables.

Every interpolant here is *linear in the tables*: the material at latent point ``x`` is
``sum_i w_i(x) table_i`` with weights summing to 1, so a blend of pre-rendered images
(paper Eq. 13) and the ``manifold_brdf`` plugin give the same material for the same ``w``.
They differ only in the function ``w(x)``:

``gp`` (the paper's Eq. 4)
    ``b(x) = K_inv k(x)``, ``w = b + (1 - sum b) / N``. Affine: weights of both signs, so
    interpolated tables can go negative and albedos leave [0, 1]; with ``exact=True`` the
    kernel's noise term ``mu delta(x, x_i)`` applies at a training point, so ``w(x_i) = e_i``
    but ``w`` jumps by ``mu |K_inv e_i|`` an infinitesimal step away.

``shepard`` (the default)
    Convex inverse-distance weights ``w_i ∝ |x - x_i|^-p exp(-|x - x_i|^2 / (2 h(x)^2))``
    (Shepard 1968, with a Gaussian taper whose width ``h(x)`` grows with the distance to
    the data, up to a bound; ``h = inf`` is plain Shepard). Non-negative, summing to 1,
    continuous everywhere and equal to ``e_i`` at ``x_i`` (no jump): interpolated tables stay
    non-negative and albedos stay inside the range of the measured ones. Far from every latent
    point the weights tend to the mean material (``h = inf``) or, with a taper, to the
    materials furthest out in the direction of ``x`` (the taper's width is bounded).
    With ``beyond="continue"`` (the default preset) they go on changing outside the convex
    hull of the latent points instead (:meth:`ShepardWeights.continuation`): affine weights,
    held to a physically plausible material by the training tables (:meth:`ShepardWeights.attach`).

Both give their analytic Jacobian ``dw/dx`` (:meth:`Interpolant.jacobian`).
"""

from __future__ import annotations

import numbers
import weakref

import numpy as np
import scipy.optimize
import scipy.spatial

from .._util import checks
from ..errors import InputError, NotPositiveDefiniteError, UnavailableError
from ..gp.kernel import Kernel, coincident
from ..gp.posterior import Posterior
from .plausibility import StepLimit, store_path

KINDS = ("gp", "shepard")
#: Largest latent coordinate accepted: far beyond it squared distances (and their squares in the
#: Jacobians) overflow float64, while the weights there already equal their limit far from the data.
MAX_COORDINATE = 1e30


def points(x, q) -> tuple[np.ndarray, bool]:
    """``x`` as an ``(M, q)`` float array and whether it was a single point (:func:`checks.latent_points`)."""
    return checks.latent_points("latent point", x, q, MAX_COORDINATE)


class Interpolant:
    """Weights ``w(x)`` over N latent points (rows of ``latent``); subclasses define them."""

    kind = None

    def __init__(self, latent) -> None:
        self.latent = np.asarray(latent, dtype=np.float64)
        self.n, self.q = self.latent.shape

    def params(self) -> dict:
        """The parameters, as saved with a manifold (JSON-able)."""
        raise NotImplementedError

    def weights(self, x) -> np.ndarray:
        """Weights ``(M, N)`` (or ``(N,)`` for one point), each row summing to 1."""
        x, single = points(x, self.q)
        w = self._weights(x)
        return w[0] if single else w

    def b_and_w(self, x) -> tuple:
        """``b`` and the weights ``w`` (M, N) at points ``x`` (M, q): ``sum_i w_i table_i = mean + b^T Z``,
        so ``b = w - 1/N`` (the GP's Eq. 4 ``b`` for :class:`GaussianProcessWeights`).
        """
        w = self._weights(x)
        return w - 1.0 / self.n, w

    def jacobian(self, x) -> np.ndarray:
        """``dw/dx``: ``(M, N, q)`` (or ``(N, q)`` for one point); columns sum to 0."""
        x, single = points(x, self.q)
        J = self._jacobian(x)
        return J[0] if single else J

    def jump(self, eps=1e-9) -> float:
        """``max_i |w(x_i + eps l u) - e_i|_1``: how much the weights jump next to a training point."""
        u = np.zeros_like(self.latent)
        u[:, 0] = eps * getattr(self, "length_scale", 1.0)
        return float(np.abs(self._weights(self.latent + u) - np.eye(self.n)).sum(axis=1).max())


class GaussianProcessWeights(Interpolant):
    """The paper's weights (Eq. 4): ``b = K_inv k(x)``, ``w = b + (1 - sum b) / N``.

    Parameters
    ----------
    latent : (N, q) array
    length_scale, noise : float
        ``l`` and ``mu`` of ``c(x, x') = mu delta + exp(-|x - x'|^2 / 2 l^2)``.
    exact : bool
        Apply the noise term ``mu delta(x, x_i)`` at training points (the paper's rule:
        ``w(x_i) = e_i``, discontinuous there); False gives the continuous GP mean
        ``b(x) = (K_smooth + mu I)^-1 k(x)`` everywhere.
    """

    kind = "gp"

    def __init__(self, latent, length_scale=1.0, noise=1e-4, exact=True) -> None:
        super().__init__(latent)
        self.length_scale = _number(self.kind, "length_scale", length_scale)
        self.noise = _number(self.kind, "noise", noise)
        if not isinstance(exact, (bool, np.bool_)):
            raise InputError(
                f"interpolant {self.kind!r}: `exact` must be True or False, got {exact!r}"
            )
        self.exact = bool(exact)
        self.gp = posterior(self.latent, Kernel(self.length_scale, self.noise))

    @property
    def K(self) -> np.ndarray:
        """The covariance matrix of the latent points."""
        return self.gp.K

    def params(self) -> dict:
        return {
            "kind": self.kind,
            "length_scale": self.length_scale,
            "noise": self.noise,
            "exact": self.exact,
        }

    def jump(self, eps=1e-9) -> float:
        """Exact for ``exact=True``: at ``x_i`` the noise term makes ``w = e_i``; an infinitesimal
        step away it is absent and ``b = e_i - mu K_inv e_i``. The paper calls this negligible;
        it is only when K's smooth part is well conditioned (points far apart compared with l).
        """
        if not self.exact:
            return super().jump(eps)
        db = -self.noise * self.gp.inverse()  # column i: b(x_i+) - e_i
        dw = db - db.sum(axis=0, keepdims=True) / self.n  # the affine weights' change
        return float(np.abs(dw).sum(axis=0).max())

    def gp_weights(self, x) -> np.ndarray:
        """``b(x)`` (M, N) of Eq. 4."""
        b = self.gp.weights(x)
        if self.exact:
            rows, cols = coincident(x, self.latent)
            single = np.bincount(rows, minlength=len(x))[rows] == 1
            rows, cols = rows[single], cols[single]
            b[rows] = 0.0  # k(x_i) + mu e_i is column i of K: K_inv of it is e_i exactly
            b[rows, cols] = 1.0
        return b

    def affine(self, b) -> np.ndarray:
        """The affine weights ``w = b + (1 - sum(b)) / N`` of Eq. 4's ``b`` (M, N)."""
        return b + (1.0 - b.sum(axis=1, keepdims=True)) / self.n

    def b_and_w(self, x) -> tuple:
        b = self.gp_weights(x)
        return b, self.affine(b)

    def _weights(self, x) -> np.ndarray:
        return self.affine(self.gp_weights(x))

    def _jacobian(self, x):
        # db = K_inv dk/dx (the posterior's); dw = db - sum(db) / N
        db = self.gp.weights_jacobian(x)
        return db - db.sum(axis=1, keepdims=True) / self.n


class ShepardWeights(Interpolant):
    """Convex weights ``w_i ∝ r_i^-p exp(-r_i^2 / 2 h(x)^2)``, ``r_i = |x - x_i| / l``.

    The taper's width adapts to the local spacing of the data, the same for every material
    at a given ``x`` (so that between two neighbours neither dominates the other's half)::

        h(x)^2 = h^2 + s^2 min(m(x), M),   m(x) = sum_j r_j^(2-p) / sum_j r_j^-p

    ``m`` is a mean of the squared distances weighted by ``r_j^-p``; for ``p = 2`` their
    harmonic mean ``N / sum_j r_j^-2``. It is 0 at a data point and grows as ``N r_i^2``
    next to ``x_i`` (the nearest point dominates the sum), then levels off near the
    data's typical squared spacing: so the taper widens from ``h`` at the data to
    ``sqrt(h^2 + s^2 m)`` between materials, the more where every material is far.
    ``M`` (:attr:`SPREAD_BOUND`) stops the widening a few ``l`` outside the data, where ``m``
    keeps growing as the squared distance: unbounded, the taper would widen as fast as the
    distances grow and the weights would drift to the mean of all materials; bounded, they
    settle on the materials furthest out in that direction.

    Parameters
    ----------
    latent : (N, q) array
    power : float
        ``p``; 2 gives the smoothest transition between two neighbours.
    taper : float
        ``h`` in units of ``l`` (``inf``: no taper). Small values make the weights local:
        between two neighbours, the material is a blend of those two.
    spread : float
        ``s``: how much the taper widens with the distance to the data.
    length_scale : float
        ``l``: the unit of distances.
    beyond : {"nearest", "continue"}
        Outside the convex hull of the latent points: the convex weights alone (they tend
        to the nearest materials), or continued (:meth:`continuation`) once
        :meth:`attach` gave the tables.
    secant : float
        ``eps`` of the continuation, in units of ``l``.
    """

    kind = "shepard"
    #: What the weights do outside the hull of the latent points.
    BEYOND = ("nearest", "continue")
    #: Weights below this share are dropped from the two ends of the continuation's secant.
    SECANT_FLOOR = 0.05
    #: ``M``: the largest ``m(x)`` (units of ``l^2``) that widens the taper. Inside the hull of a
    #: fitted layout ``m`` is a few ``l^2``; it reaches ``M`` a few ``l`` outside.
    SPREAD_BOUND = 25.0
    #: The continuation's reach stops growing this many ``eps`` outside the hull (where the
    #: plausibility limit holds it long before): farther out the material no longer changes.
    REACH_BOUND = 1e3
    #: Distance from the data's centre (units of ``l``) beyond which the continuation is that of
    #: the point this far out in the same direction.
    FAR = 1e4

    def __init__(
        self,
        latent,
        power=2.0,
        taper=np.inf,
        spread=0.0,
        length_scale=1.0,
        beyond="nearest",
        secant=0.3,
    ) -> None:
        super().__init__(latent)
        if beyond not in self.BEYOND:
            raise InputError(
                f"shepard weights: unknown `beyond` {beyond!r}; use one of {', '.join(self.BEYOND)}"
            )
        self.beyond = beyond
        self.secant = _number(self.kind, "secant", secant)
        if not self.secant > 0:
            raise InputError(f"shepard weights need `secant` > 0, got {self.secant}")
        self.limit = None
        self._hull: LatentHull | None = None
        given = (
            ("power", power),
            ("taper", taper),
            ("spread", spread),
            ("length_scale", length_scale),
        )
        self.power, self.taper, self.spread, self.length_scale = (
            _number(self.kind, k, v) for k, v in given
        )
        if (
            not self.power > 0
            or not self.taper > 0
            or not self.length_scale > 0
            or not self.spread >= 0
        ):
            raise InputError(
                f"shepard weights need `power` > 0, `taper` > 0, `spread` >= 0 and `length_scale` > 0, "
                f"got {self.power}, {self.taper}, {self.spread}, {self.length_scale}"
            )

    def params(self) -> dict:
        return {
            "kind": self.kind,
            "power": self.power,
            "taper": self.taper,
            "spread": self.spread,
            "length_scale": self.length_scale,
            **({"beyond": self.beyond, "secant": self.secant} if self.beyond != "nearest" else {}),
        }

    def attach(self, manifold) -> None:
        """Give the continuation beyond the hull its plausibility limit (:class:`StepLimit`)
        from the tables of ``manifold`` (a :class:`~.model.Manifold` over these latent points):
        those in memory when all are loaded, else each material's read when first needed.
        Without it (or with ``beyond="nearest"``) the weights are the convex ones everywhere.
        The limit holds the manifold by a weak reference: the manifold holds this interpolant, and
        a strong one back would keep both, and the tables the manifold holds, until the next
        garbage collection; the limit is asked only while the manifold is in use.
        """
        if self.beyond != "continue" or manifold.dims is None:
            return
        owner = weakref.ref(manifold)

        def held():
            m = owner()
            if m is None:
                raise UnavailableError(
                    "the manifold of these interpolation weights no longer exists; "
                    "take the weights from the manifold (Manifold.weights), not from its interpolant"
                )
            return m

        def rows(idx):
            m = held()
            if m._tables is not None:  # views of the rows, no copy
                return [m._tables[i] for i in idx]
            names = [m.names[i] for i in idx]
            return m.open_database(names=names).stack(names)

        def store() -> (
            str | None
        ):  # asked at the first step: the database may have been pointed elsewhere
            m = held()
            return store_path(getattr(m, "hashes", None), m.dims, m.database)

        self.limit = StepLimit(rows, self.n, manifold.dims, store=store)

    def continuation(self, x, w) -> np.ndarray:
        """What the weights gain outside the hull of the latent points: ``s(x) e(x)`` (M, N).

        With ``p`` the point of the hull closest to ``x``, ``rho = |x - p|`` and ``n`` the unit
        vector from ``p`` to ``x``, the weights continue along ``n``:

            e(x) = a(rho / (eps l)) (w~(p) - w~(p - eps l n)),   a(r) = r^4 / (1 + r^3)

        (the change of the material over the last ``eps l`` inside the data, carried on: ``a``
        grows as ``r`` far out and starts flat, as ``r^4``, so that the weights stay smooth
        across the hull and flat at the training points on it; ``r`` is bounded by
        :attr:`REACH_BOUND`;
        ``w~``: Shepard's weights without the taper, ``w_i ∝ r_i^-p``, so that the change is
        not flattened next to a material, thinned continuously: each less :data:`SECANT_FLOOR`
        (or half the largest, if less), the negative ones dropped, the rest scaled to sum 1).
        The weights ``w(x) + s(x) e(x)`` sum to 1; ``s`` is the largest step in [0, 1] for
        which :meth:`StepLimit.step` holds the material plausible: no negative bin, directional
        albedo at most 1. Zero inside the hull (so at every training point) and continuous
        across its boundary. A point more than :attr:`FAR` from the data's centre gets the
        continuation of the point that far out in its direction.
        """
        out = np.zeros_like(w)
        if self.limit is None:
            return out
        # points farther out than where the reach stops growing are brought in along the line
        # from the data's centre (the hull's closest point loses its precision far out)
        centre, far_out = self.latent.mean(axis=0), self.FAR * self.length_scale
        away = np.linalg.norm(x - centre, axis=1)
        if (away > far_out).any():
            x, pulled = x.copy(), away > far_out
            x[pulled] = centre + (x[pulled] - centre) * (far_out / away[pulled])[:, None]
        p, rho = self.hull().project(x)
        far = np.flatnonzero(rho > 1e-12 * self.length_scale)
        if len(far) == 0:
            return out
        n = (x[far] - p[far]) / rho[far, None]
        eps = self.secant * self.length_scale
        ends = self._thin(self._untapered(np.concatenate([p[far], p[far] - eps * n])))
        r = np.minimum(rho[far] / eps, self.REACH_BOUND)
        reach = r**4 / (1.0 + r**3)  # ~rho / eps far out, flat at the hull
        e = reach[:, None] * (ends[: len(far)] - ends[len(far) :])
        s = self.limit.step(w[far], e)
        out[far] = s[:, None] * e
        return out

    def hull(self) -> LatentHull:
        """The :class:`LatentHull` of the latent points (made on first use)."""
        if self._hull is None:
            self._hull = LatentHull(self.latent)
        return self._hull

    def _untapered(self, x) -> np.ndarray:
        diff = (x[:, None, :] - self.latent[None]) / self.length_scale
        with np.errstate(divide="ignore"):
            return _normalise(-0.5 * self.power * np.log(np.einsum("mnq,mnq->mn", diff, diff)))

    def _thin(self, w) -> np.ndarray:
        floor = np.minimum(self.SECANT_FLOOR, 0.5 * w.max(axis=1, keepdims=True))
        w = np.maximum(w - floor, 0.0)
        return w / w.sum(axis=1, keepdims=True)

    def _terms(self, x) -> tuple:
        """``x - x_i`` (units of l), ``r_i^2``, hit rows, ``m(x)``, ``h(x)^2`` and ``log u_i``."""
        diff = (x[:, None, :] - self.latent[None]) / self.length_scale
        r2 = np.einsum("mnq,mnq->mn", diff, diff)
        hit = (r2 == 0).any(axis=1)
        r2s = np.where(hit[:, None], 1.0, r2)  # hit rows are set apart
        inv = (r2s / r2s.min(1, keepdims=True)) ** (
            -0.5 * self.power
        )  # scaled: no underflow far out
        m = np.where(hit, 0.0, (r2s * inv).sum(1) / inv.sum(1))
        m = np.minimum(m, self.SPREAD_BOUND)
        h2 = self.taper**2 + self.spread**2 * m
        with np.errstate(divide="ignore"):
            log_u = -0.5 * self.power * np.log(r2) - 0.5 * r2 / h2[:, None]
        bounded = np.flatnonzero(m == self.SPREAD_BOUND)
        if len(bounded) and np.isfinite(self.taper):
            # far out r_i^2 / h^2 is huge and its differences between materials are lost in it:
            # the same exponents less a constant per row, ``r_i^2 - r_k^2`` computed exactly
            # (``k`` the nearest): ``(|x_i|^2 - |x_k|^2 - 2 x . (x_i - x_k)) / l^2``
            y = x[bounded] / self.length_scale
            lat = self.latent / self.length_scale
            k = r2s[bounded].argmin(axis=1)
            sq = np.einsum("nq,nq->n", lat, lat)
            rel = (
                sq[None]
                - sq[k][:, None]
                - 2.0 * (y @ lat.T - np.einsum("mq,mq->m", y, lat[k])[:, None])
            )
            with np.errstate(divide="ignore"):
                log_u[bounded] = (
                    -0.5 * self.power * np.log(r2[bounded]) - 0.5 * rel / h2[bounded, None]
                )
        return diff, r2s, hit, inv, m, h2, log_u

    def _convex(self, x) -> np.ndarray:
        return _normalise(self._terms(x)[-1])

    def _weights(self, x) -> np.ndarray:
        w = self._convex(x)
        if self.limit is not None:
            w = w + self.continuation(x, w)
        return w

    def _jacobian(self, x) -> np.ndarray:
        J = self._convex_jacobian(x)
        if self.limit is None:
            return J
        _, rho = self.hull().project(x)
        far = np.flatnonzero(rho > 1e-12 * self.length_scale)
        if len(far):  # beyond the hull: central differences of the continued weights, with
            # steps that stay outside it (no larger than half the distance to it), extrapolated
            # from steps h and h / 2 (Richardson: the error of order h^2 cancels)
            # from steps h and h / 2 (Richardson: the error of order h^2 cancels). Each point's
            # steps are evaluated on their own, so that a point's row does not depend on the
            # other points of the batch.
            q = self.q
            for i in far:
                h = np.clip(0.5 * rho[i], 1e-9, 1e-4) * self.length_scale
                steps = np.eye(q) * h
                X = x[i] + np.concatenate([steps, -steps, steps / 2, -steps / 2])
                W = self._weights(X)
                d_h = (W[:q] - W[q : 2 * q]) / (2 * h)
                d_half = (W[2 * q : 3 * q] - W[3 * q :]) / h
                J[i] = ((4 * d_half - d_h) / 3).T
        return J

    def _convex_jacobian(self, x) -> np.ndarray:
        diff, r2, hit, inv, m, h2, log_u = self._terms(x)
        w = _normalise(log_u)
        p, l = self.power, self.length_scale
        # dm/dx = (dS2 - m dS0) / S0 with S0 = sum r^-p, S2 = sum r^(2-p)
        S0 = inv.sum(1)
        dS0 = np.einsum("mn,mnq->mq", -p * inv / r2, diff) / l
        dS2 = np.einsum("mn,mnq->mq", (2 - p) * inv, diff) / l
        dm = (dS2 - m[:, None] * dS0) / S0[:, None]
        dm[m == self.SPREAD_BOUND] = 0.0  # the taper's width no longer grows
        dh2 = self.spread**2 * dm
        # d log u_i / dx = -p (x - x_i) / (l r_i^2) - (x - x_i) / (l h^2) + r_i^2 / (2 h^4) dh^2/dx
        g = (
            -(p / r2 + 1.0 / h2[:, None])[..., None] * diff / l
            + (0.5 * r2 / h2[:, None] ** 2)[..., None] * dh2[:, None, :]
        )
        J = w[..., None] * (g - np.einsum("mn,mnq->mq", w, g)[:, None, :])
        J[hit] = 0.0  # at a latent point w = e_i and (for p > 1) it is stationary
        return J


#: Points outside the hull from which :meth:`LatentHull.project` (``q >= 4``) first tries the facet
#: each is farthest outside of, all at once (fewer: the face last found, point by point).
MANY = 32


class LatentHull:
    """The convex hull of latent points and the closest point of it to any point.

    A point is inside when no facet's plane has it outside (``scipy.spatial.ConvexHull``;
    for ``q = 1`` the interval). The closest point of the hull to one outside: for ``q`` of 2
    and 3, the nearest of its projections onto each facet (where it falls inside the facet)
    and onto each edge (clamped to the edge), which holds the closest point whether it lies
    inside a facet, on an edge or at a vertex; for larger ``q``, the convex combination of
    the hull's vertices nearest to it (non-negative least squares with the weights' sum held
    at 1 by a heavy extra row, then solved exactly on the face it found). Two shortcuts give
    the same point without the least squares: the projection onto the plane of the facet the
    point is farthest outside of, where it falls inside that facet (every vertex is on the
    inner side of the plane: the closest point); then the face last found, whose projection,
    where it falls on the face, is the closest point when no vertex lies beyond it
    (``(x - p) . (v - p) <= 0`` for every vertex ``v``, the optimality condition of a
    projection onto a convex set), so points near each other (a descent's steps, the
    differences of a Jacobian) share it.
    """

    def __init__(self, latent) -> None:
        latent = np.asarray(latent, dtype=np.float64)
        self.q = latent.shape[1]
        self.scale = float(np.ptp(latent, axis=0).max()) or 1.0
        try:
            if self.q < 2:
                raise ValueError("one dimension")
            hull = scipy.spatial.ConvexHull(latent)
            self.vertices, self.planes = latent[hull.vertices], hull.equations
            self.facets = latent[hull.simplices]  # (F, q, q): the corners of each facet
        except (ValueError, scipy.spatial.QhullError):
            self.vertices, self.planes, self.facets = latent, None, None
            if self.q == 1:
                self.vertices = np.array([[latent.min()], [latent.max()]])
        self._faces: dict = {}  # active vertices -> (base vertex, rows, pseudo-inverse) of the face
        self._last = None  # the face the last projection found (q >= 4)
        self._facet_pinv: np.ndarray | None = None

    def project(self, x) -> tuple:
        """The closest points of the hull ``(M, q)`` and the distances to them ``(M,)``."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        p = x.copy()
        if self.planes is not None:
            beyond = x @ self.planes[:, :-1].T + self.planes[:, -1]  # unit normals (Qhull)
            outside = (beyond > 1e-12 * self.scale).any(1)
        elif self.q == 1:
            outside = (x[:, 0] < self.vertices[0, 0]) | (x[:, 0] > self.vertices[1, 0])
        else:
            outside = np.ones(len(x), dtype=bool)
        if self.facets is not None and self.q in (2, 3):
            out = np.flatnonzero(outside)
            for s in range(0, len(out), 1024):
                p[out[s : s + 1024]] = self._closest_on_faces(x[out[s : s + 1024]])
            return p, np.sqrt(((x - p) ** 2).sum(axis=1))
        out = np.flatnonzero(outside)
        if self.planes is not None and len(out) >= MANY:  # inside the facet farthest outside of
            f = beyond[out].argmax(axis=1)
            y = x[out] - beyond[out, f][:, None] * self.planes[f, :-1]
            target = np.c_[y, np.ones(len(y))]
            lam = np.einsum("mij,mj->mi", self._facet_solvers()[f], target)
            # a flat facet (corners in a lower-dimensional plane) has least-squares coordinates:
            # accept only those that give the point back, on the facet
            back = np.einsum("mcd,mc->md", self.facets[f], lam)
            miss = np.abs(back - y).max(axis=1) + np.abs(lam.sum(axis=1) - 1.0)
            inside = (lam >= 0).all(axis=1) & (miss <= 1e-9 * self.scale)
            p[out[inside]] = y[inside]
            outside[out[inside]] = False
        heavy = 1e4 * self.scale
        A = np.vstack([self.vertices.T, np.full(len(self.vertices), heavy)])
        for i in np.flatnonzero(outside):
            last = self._last
            near = None if last is None else self._on_face(x[i], last)
            if near is not None and self._closest(x[i], near):
                p[i] = near
                continue
            lam, _ = scipy.optimize.nnls(A, np.append(x[i], heavy))
            active = tuple(np.flatnonzero(lam > 0).tolist())
            p[i] = self._exact(x[i], active, lam / lam.sum())
            self._last = active  # a hint only: a stale one (another thread's) is checked
        rho = np.sqrt(((x - p) ** 2).sum(axis=1))
        return p, rho

    def _facet_solvers(self) -> np.ndarray:
        """Per facet, the pseudo-inverse ``(F, q, q + 1)`` giving the barycentric coordinates of
        a point of its plane from ``(point, 1)`` (made once).
        """
        if self._facet_pinv is None:
            corners = np.concatenate(
                [np.transpose(self.facets, (0, 2, 1)), np.ones((len(self.facets), 1, self.q))],
                axis=1,
            )
            self._facet_pinv = np.linalg.pinv(corners)
        return self._facet_pinv

    def _face(self, active) -> tuple:
        """Base vertex, the other vertices less it (rows) and their pseudo-inverse, of face
        ``active`` (made once per face).
        """
        face = self._faces.get(active)
        if face is None:
            V = self.vertices[list(active)]
            B = V[:-1] - V[-1]
            face = self._faces[active] = (V[-1], B, np.linalg.pinv(B.T))
        return face

    def _on_face(self, x, active) -> np.ndarray | None:
        """The closest point to ``x`` of the affine span of face ``active`` where it falls on the
        face (barycentric coordinates >= 0), else None.
        """
        base, B, pinv = self._face(active)
        if not len(B):
            return base
        mu = pinv @ (x - base)
        if (mu >= 0).all() and mu.sum() <= 1:
            return base + mu @ B
        return None

    def _closest(self, x, p) -> bool:
        """Whether ``p`` (on the hull) is the closest point of the hull to ``x``: no vertex lies
        beyond the plane through ``p`` normal to ``x - p`` (to rounding).
        """
        d = x - p
        return bool(((self.vertices - p) @ d).max() <= 1e-12 * self.scale * np.sqrt(d @ d))

    def _closest_on_faces(self, x) -> np.ndarray:
        """The closest point of the hull's surface to each row of ``x`` (``q`` of 2 or 3)."""
        F = self.facets
        edges = np.concatenate([F[:, [a, (a + 1) % self.q]] for a in range(self.q)])
        a, d = edges[:, 0], edges[:, 1] - edges[:, 0]  # (E, q)
        t = np.einsum("meq,eq->me", x[:, None] - a[None], d) / np.einsum("eq,eq->e", d, d)
        cand = a[None] + np.clip(t, 0.0, 1.0)[..., None] * d[None]  # (M, E, q)
        if self.q == 3:  # inside a facet: the projection onto its plane, where it falls inside
            o, u, v = F[:, 0], F[:, 1] - F[:, 0], F[:, 2] - F[:, 0]
            G = np.stack([np.stack([(u * u).sum(1), (u * v).sum(1)], 1),
                          np.stack([(u * v).sum(1), (v * v).sum(1)], 1)], 1)  # fmt: skip
            r = x[:, None] - o[None]  # (M, F, q)
            rhs = np.stack([(r * u[None]).sum(-1), (r * v[None]).sum(-1)], -1)
            ab = np.einsum("fij,mfj->mfi", np.linalg.inv(G), rhs)
            inside = (ab >= 0).all(-1) & (ab.sum(-1) <= 1)
            on = o[None] + ab[..., :1] * u[None] + ab[..., 1:] * v[None]
            on = np.where(inside[..., None], on, np.inf)
            cand = np.concatenate([cand, on], axis=1)
        dist = ((cand - x[:, None]) ** 2).sum(-1)
        return cand[np.arange(len(x)), dist.argmin(axis=1)]

    def _exact(self, x, active, lam) -> np.ndarray:
        """The closest point of the affine span of the ``active`` vertices (the face NNLS found),
        solved exactly (least squares by the face's pseudo-inverse); NNLS's own point where that
        leaves the face.
        """
        p = self._on_face(x, active)
        return lam @ self.vertices if p is None else p


def _normalise(log_u) -> np.ndarray:
    """Softmax along the last axis, with ``+inf`` entries sharing the whole weight."""
    inf = np.isposinf(log_u)
    rows = inf.any(axis=1)
    out = np.empty_like(log_u)
    if (~rows).any():
        lu = log_u[~rows]
        e = np.exp(lu - lu.max(axis=1, keepdims=True))
        out[~rows] = e / e.sum(axis=1, keepdims=True)
    if rows.any():
        hit = inf[rows].astype(np.float64)
        out[rows] = hit / hit.sum(axis=1, keepdims=True)
    return out


def posterior(latent, kernel) -> Posterior:
    """The GP :class:`~mitsuba_manifold.gp.posterior.Posterior` of ``latent`` (the one factorisation
    of its K), or an :class:`InputError` saying why K has none.
    """
    try:
        return Posterior(latent, kernel)
    except NotPositiveDefiniteError:
        raise InputError(
            f"the covariance K of the {len(latent)} latent points is not positive definite "
            f"(`noise` mu={kernel.noise:g} too small for coincident points?)"
        ) from None


def _number(kind, name, value) -> float:
    """``value`` as a float; a bool or a text is refused (``True`` is not a power)."""
    number = isinstance(value, (numbers.Real, np.floating, np.integer))
    if isinstance(value, (bool, np.bool_)) or not number:
        raise InputError(f"interpolant {kind!r}: `{name}` must be a number, got {value!r}")
    return float(value)


def make(latent, params) -> GaussianProcessWeights | ShepardWeights:
    """An interpolant from saved parameters ``{"kind": ..., ...}``."""
    params = dict(params)
    kind = params.pop("kind", None)
    cls = {"gp": GaussianProcessWeights, "shepard": ShepardWeights}.get(kind)
    if cls is None:
        raise InputError(f"unknown interpolant kind {kind!r}; use one of {', '.join(KINDS)}")
    try:
        return cls(latent, **params)
    except InputError:
        raise
    except (TypeError, ValueError) as e:
        raise InputError(f"interpolant {kind!r}: {e}") from None
