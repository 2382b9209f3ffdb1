"""A differentiable latent point for ``manifold_brdf`` in Mitsuba's AD variants.

In an AD variant, once ``params["<id>.x"]`` is grad-enabled, the BSDF renders the same material
as without gradients: the weights at ``x`` pruned by :meth:`Manifold.prune` with the plugin's
``prune`` and rescaled to sum to 1, clamped at 0 per bin, ``max(0, sum_{i in S} v_i table_i)``.
Its gradient is that of the rendered image with pruning's selection ``S`` held fixed (it is
piecewise constant in ``x``): ``dv/dx`` is the Jacobian of the rescaling ``w_S / sum(w_S)``
(:func:`rescaled`). The materials sit in a FIXED number K of device slots (at least ``ad_terms``,
more when pruning keeps more), padded with zero-weight materials: K is unrolled into the kernel,
and only the indices (which tables sit in the slots) and the weights change, so nothing is
recompiled when the set changes. The tables are never grad-enabled; the weights ``w`` are a
``mi.Float`` of size K that follows ``x`` through :class:`LatentWeights`, a ``dr.CustomOp`` whose
derivative is the analytic Jacobian of :meth:`Manifold.weights` (:meth:`Manifold.weights_jacobian`)
restricted to ``S`` and rescaled.

Inside a render the same map enters every table lookup as :func:`traced_weights`:
``w = v + J (x - detach(x))`` made of ordinary Dr.Jit operations (value ``v`` exactly, derivative
``J dx``), recorded where the lookup is. Mitsuba's ``render_forward`` (``prb`` and the others)
isolates its AD scope and refuses to propagate across an edge made outside it, and a CustomOp's
callbacks cannot read arrays inside the integrators' symbolic loops: with the edges made inside, a
user's ``dr.set_grad(params["<id>.x"], dx)`` then ``render_forward`` (or ``mi.render`` and
``dr.forward_to``/``dr.forward``) gives the image's derivative along ``dx``, and ``dr.backward``
its gradient. :class:`LatentWeights` remains the weights' operation outside a render
(``ManifoldBRDF.ad_weights``, ``forward_weights``).

The slots not taken by ``S`` hold the materials of largest score ``|w_i| + step ||dw_i/dx||``
(:func:`choose_active`), the weight a material can reach within one typical step, so that a
material entering ``S`` is usually in a slot already; members of the current slots get a bonus
(hysteresis), so the slots do not flicker between two materials of nearly equal score.

The convex Shepard weights have a zero Jacobian exactly at a training point (``w = e_i``
is a flat maximum of ``w_i``): the gradient there is 0, and an optimisation started at a
training point never moves. Start a little away from it (:func:`jitter`). Near a training point
pruning may also keep that one material alone: the rendered material is then constant in ``x``
and so is the image (gradient 0); a smaller ``prune`` (0 keeps every material) gives the
optimisation a slope there.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from .material import Combination

#: Default size of the active set.
DEFAULT_TERMS = 8
#: Bonus factor of the current members' scores (hysteresis of the active set).
HYSTERESIS = 0.25


def typical_step(latent):
    """A typical step in latent space: a quarter of the median nearest-neighbour distance."""
    latent = np.asarray(latent, dtype=np.float64)
    if latent.shape[0] < 2:
        return 1.0
    d = np.sqrt(((latent[:, None, :] - latent[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    return 0.25 * float(np.median(d.min(axis=1)))


def choose_active(w, J, k, step, previous=None, hysteresis=HYSTERESIS):
    """Indices (sorted, ``min(k, N)`` of them) of the active set for weights ``w`` (N,) and
    Jacobian ``J`` (N, q): the largest scores ``|w_i| + step ||J_i||``, the members of
    ``previous`` scored ``(1 + hysteresis)`` higher.
    """
    w, J = np.asarray(w, dtype=np.float64), np.asarray(J, dtype=np.float64)
    score = np.abs(w) + step * np.linalg.norm(J.reshape(w.size, -1), axis=1)
    if previous is not None:
        score[np.asarray(previous, dtype=np.int64)] *= 1.0 + hysteresis
    k = min(int(k), w.size)
    return np.sort(np.argsort(-score, kind="stable")[:k])


def rescaled(w, J, idx):
    """Weights and Jacobian of the active set ``idx``, rescaled to the full set's sum:
    ``v = w_S s / sum(w_S)`` (``s = sum(w)``, 1 for a latent point) and its derivative
    ``dv/dx = (s / sum(w_S)) (J_S - v_S 1^T J_S / s)`` (with ``s`` constant, as its
    Jacobian's columns sum to 0). Not rescaled when ``sum(w_S)`` is ~0.
    """
    w, J = np.asarray(w, dtype=np.float64), np.asarray(J, dtype=np.float64)
    ws, Js = w[idx], J[idx]
    total, part = w.sum(), ws.sum()
    if abs(part) < 1e-8 * max(1.0, np.abs(w).sum()):
        return ws, Js
    r = total / part
    v = r * ws
    return v, r * (Js - np.outer(ws / part, Js.sum(axis=0)))


def jitter(x, manifold, scale=1.0, rng=None):
    """``x`` moved by ``scale`` typical steps (:func:`typical_step`) in a random direction, when it lies on a
    training point (where the Shepard weights' Jacobian is 0); otherwise unchanged.
    """
    x = np.asarray(x, dtype=np.float64).copy()
    step = typical_step(manifold.latent)
    if np.min(np.linalg.norm(manifold.latent - x, axis=1)) < 1e-3 * step:
        rng = np.random.default_rng(0) if rng is None else rng
        d = rng.normal(size=x.shape)
        x += scale * step * d / np.linalg.norm(d)
    return x


class LatentWeights(dr.CustomOp):
    """``x (q,) -> v (K,)`` with the analytic Jacobian ``J (K, q)`` computed in ``eval``
    by ``weights_fn(x) -> (v, J)`` (NumPy, detached): forward ``dv = J dx``, backward
    ``dx = J^T dv``.
    """

    def eval(self, x, weights_fn):
        v, self.J = weights_fn(np.array(x, dtype=np.float64))
        return mi.Float(np.asarray(v, dtype=np.float32))

    def forward(self):
        dx = np.array(self.grad_in("x"), dtype=np.float64).ravel()
        dx = np.broadcast_to(dx, (self.J.shape[1],)) if dx.size == 1 else dx
        self.set_grad_out(mi.Float((self.J @ dx).astype(np.float32)))

    def backward(self):
        dv = np.array(self.grad_out(), dtype=np.float64).ravel()
        dv = np.broadcast_to(dv, (self.J.shape[0],)) if dv.size == 1 else dv
        self.set_grad_in("x", mi.Float((self.J.T @ dv).astype(np.float32)))

    def name(self):
        return "manifold latent weights"


def latent_weights(x, weights_fn):
    """Differentiable ``mi.Float`` weights of the active set at ``x`` (:class:`LatentWeights`)."""
    return dr.custom(LatentWeights, x, weights_fn)


class ActiveSet:
    """The K device slots of AD mode: which materials sit in them, their packed tables (one
    ``mi.Float`` of ``K * bins * 3`` values, never grad-enabled) and sampling densities.

    :meth:`update` prunes the weights at ``x`` exactly as the combined table does
    (:meth:`Manifold.prune`), puts the kept materials in slots with their rescaled weights and
    Jacobian (:func:`rescaled`), and fills the remaining slots with the materials of largest
    score (:func:`choose_active`) at weight 0, so that a material entering the kept set is
    usually in a slot already. Only the slots whose material changed are replaced; K grows
    (and the kernels recompile once) only when more materials are kept than there are slots.
    ``tables(names) -> {name: (3, nh, nd, nphi)}`` and ``density(name) -> (n_t, n_v, n_u)``
    read what is not in memory yet.
    """

    def __init__(self, manifold, k, tables, density, prune):
        self.manifold = manifold
        self.k = min(int(k), manifold.n)
        self.prune = float(prune)
        self.step = typical_step(manifold.latent)
        self._read, self._density = tables, density
        self.idx = None  # (k,) material per slot
        self.dims = None  # table resolution
        self.host = None  # (k, bins, 3) float32
        self.slots = None  # mi.Float
        self.densities = None  # (k, n_t, n_v, n_u)
        self.switches = 0  # number of slot replacements so far
        self.keep = None  # materials kept by pruning (sorted)

    def update(self, x):
        """Prune at ``x`` and fill the slots; returns ``(idx, v, J_v, w_full)`` (NumPy): the
        material of each slot, its weight (0 outside the kept set) and Jacobian, the full
        weights.
        """
        _, w = self.manifold.weights(x)
        J = self.manifold.weights_jacobian(x)
        keep = np.sort(np.asarray(self.manifold.prune(w, self.prune).keep, dtype=np.int64))
        self.k = max(self.k, keep.size)
        score_w = np.where(np.isin(np.arange(w.size), keep), np.inf, w)  # the kept ones first
        prev = None if self.idx is None else np.sort(self.idx)
        self._place(choose_active(score_w, J, self.k, self.step, prev))
        v_keep, J_keep = rescaled(w, J, keep)
        slot = {int(i): s for s, i in enumerate(self.idx)}
        v, Jv = np.zeros(self.k), np.zeros((self.k,) + J.shape[1:])
        for i, vi, Ji in zip(keep, v_keep, J_keep):
            v[slot[int(i)]], Jv[slot[int(i)]] = vi, Ji
        self.keep = keep
        return self.idx.copy(), v, Jv, w

    def _place(self, idx):
        """Keep materials already in a slot where they are; put the new ones in the freed slots
        (new slots at the end when K grew).
        """
        if self.idx is None:
            order = np.asarray(idx)
            names = [self.manifold.names[i] for i in order]
            t = self._read(names)
            self.dims = tuple(int(d) for d in t[names[0]].shape[1:])
            self.host = np.stack([_packed(t[n]) for n in names])
            self.densities = np.stack([self._density(n) for n in names])
        else:
            wanted, held = set(np.asarray(idx).tolist()), self.idx.tolist()
            new = [i for i in idx if i not in set(held)]
            if not new:
                return
            grow = len(idx) - len(held)
            if grow > 0:  # more kept materials than slots: new slots (filled below)
                held = held + [-1] * grow
                self.host = np.concatenate([self.host, np.repeat(self.host[:1], grow, axis=0)])
                self.densities = np.concatenate(
                    [self.densities, np.repeat(self.densities[:1], grow, axis=0)]
                )
            order = np.asarray(held)
            free = [s for s, i in enumerate(held) if i not in wanted]
            t = self._read([self.manifold.names[i] for i in new])
            for s, i in zip(free, new):
                order[s] = i
                self.host[s] = _packed(t[self.manifold.names[i]])
                self.densities[s] = self._density(self.manifold.names[i])
            self.switches += len(new)
        self.idx = np.asarray(order)
        self.slots = mi.Float(self.host.ravel())


def _packed(table):
    """A (3, nh, nd, nphi) table as (bins, 3) float32 (the BSDF's packing)."""
    table = np.asarray(table, dtype=np.float32)
    return np.ascontiguousarray(table.reshape(3, -1).T)


def traced_weights(x, v, J):
    """The K weights as Dr.Jit expressions of ``x``: ``w_k = v_k + sum_j J_kj (x_j - detach(x_j))``
    (``v`` (K,) and ``J`` (K * q,) row-major: detached ``mi.Float``), a list of K ``mi.Float``.

    Their value is ``v`` exactly, their derivative the analytic Jacobian's ``J dx`` (forward) or
    ``J^T dw`` (backward): the same map as :class:`LatentWeights`, made of ordinary operations so that
    it can be recorded where the lookup is, inside an integrator's symbolic loop and its isolated AD
    scope (``prb``'s ``render_forward`` refuses an edge made outside it, and a ``dr.CustomOp``'s
    callbacks cannot read arrays inside a symbolic region). Every value is gathered from device
    arrays (no literal), so new weights compile nothing.
    """
    k = dr.width(v)
    q = dr.width(J) // max(k, 1)
    d = []
    for j in range(q):
        xj = dr.gather(mi.Float, x, mi.UInt32(j))
        d.append(xj - dr.detach(xj))
    out = []
    for i in range(k):
        wi = dr.gather(mi.Float, v, mi.UInt32(i))
        for j in range(q):
            wi = dr.fma(dr.gather(mi.Float, J, mi.UInt32(i * q + j)), d[j], wi)
        out.append(wi)
    return out


def mixture_gather(slots, weights, n_bins, k):
    """A ``gather(table, idx, active)`` for :func:`.lookups.table_value` that returns
    ``max(0, sum_k w_k slot_k[idx])`` (clamped per bin, as the combined table is). ``weights``: a
    ``mi.Float`` of size K, or a callable returning K ``mi.Float`` (:func:`traced_weights`), called
    at every lookup (so that the weights' AD edges are made where the lookup is).
    """

    def gather(_table, idx, active):
        if callable(weights):
            wk = weights()
        else:
            wk = [dr.gather(mi.Float, weights, mi.UInt32(j)) for j in range(k)]
        out = mi.Color3f(0.0)
        for j in range(k):
            out += wk[j] * dr.gather(mi.Color3f, slots, idx + j * n_bins, active)
        return dr.maximum(out, 0.0)

    return gather


def combination(manifold, active, state, distr, black):
    """The :class:`.material.Combination` describing AD mode's material (``state``: ``idx`` of the
    slots, their weights ``v``, the full weights ``w``, the point ``x``, the pruned set ``keep``);
    ``table`` None (the slots are in ``active``), clamping counted nowhere (it happens per
    lookup).
    """
    full = np.zeros(manifold.n)
    full[state["idx"]] = state["v"]
    keep = np.asarray(state["keep"])
    w = state["w"]
    return Combination(
        w=full,
        x=state["x"],
        material=None,
        keep=keep,
        dropped=float(np.abs(w).sum() - np.abs(w[keep]).sum()),
        prune_error=manifold.prune_error(w, keep),
        pruning=manifold.prune_report(w, active.prune, keep=keep),
        n_clamped=0,
        n_values=active.host.size,
        black=black,
        dims=active.dims,
        distr=distr,
        table=None,
    )


def forward_leaf(x, w, dx):
    """Forward mode: ``J dx`` pushed from ``x`` to the weights ``w`` (through :class:`LatentWeights`,
    which clears the edges ``x -> w``), returned on a new AD leaf with ``w``'s value.
    """
    dr.set_grad(x, mi.Float(np.asarray(dx, dtype=np.float32).ravel()))
    dw = dr.forward_to(w)
    leaf = dr.detach(w)
    dr.enable_grad(leaf)
    dr.set_grad(leaf, dw)
    return leaf
