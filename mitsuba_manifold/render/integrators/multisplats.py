"""The splats of paths that touch the target two to ``levels`` times (one-pass ``L2+``).

Level ``k`` of a path (:mod:`.records`) gives two splats (light connection, sampled
direction), each with ``k`` MERL bins ``b_1 .. b_k`` and an RGB amplitude ``a``: a material
``f`` adds ``a prod_j f(b_j)`` to the pixel (paper Sec. 5.2, the one-pass weight is the
product of ``f / proxy`` over the path's vertices on the material). :class:`MultiSplats`
sums that for every material (the ``L2+`` image of each, ``rest_i``) and, for the pairs
asked for, the cross terms through the pair's midpoint ``m = (f_i + f_j) / 2``:

    C_ij = 4 R_m - 2 R_i - 2 R_j = sum a (4 prod_k m(b_k) - 2 prod_k f_i(b_k) - 2 prod_k f_j(b_k)),

over the splats of every level (``R``: the ``L2+`` image of a material). With them the blend
``sum_i w_i I_i + sum_{i<j} w_i w_j C_ij`` is, along the segment between two materials, the
quadratic through its ends and its midpoint: exact there for every number of vertices on the
material, and everywhere on the segment for two-vertex paths, where ``C_ij`` is the paper's
second-order term ``2 L2_ij - L2_ii - L2_jj = - sum a (f_i(b_1) - f_j(b_1)) (f_i(b_2) - f_j(b_2))``
(computed in that form). Where paths touch the material three or more times, a cross term of
two-vertex paths alone leaves the blend of two materials that see themselves differently
(white-paint and blue-rubber on the table's bowl) too bright at their midpoint, with the
noise of the brighter one's ``L2+`` (the measurement: ``docs/benchmarks.md``). Nearest lookups (the table product
of :class:`.splats.TableSplats`); each splat goes into every pixel of its sample's filter
footprint with the filter's weight there (:class:`.splats.FilterTaps`), as the film puts samples.
"""

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..plugin.lookups import merl_angles, merl_bin
from .splats import PACKET, expand

#: Pairs of materials per cross-term kernel (bounds the per-thread copies of the sums).
PAIR_CHUNK = 64
#: Partial sums per channel and candidate pair of the pair selection's pilot (a power of two).
PILOT_BINS = 256


@dataclass(frozen=True)
class PairSelection:
    """Which candidate pairs get a cross term, measured on the first pass (:meth:`MultiSplats.add`).

    ``products``: each candidate's largest weight product in the explored region; a pair is kept
    when ``products * |sum C_ij| >= tol * (R_i + R_j) / 2`` (sums over the image, the largest
    channel; ``C_ij`` from a share ``pilot`` of the first pass's splats, ``R`` the materials'
    ``L2+`` light in that pass): what leaving it out changes of the ``L2+`` light, at most
    ``tol``. Pairs of materials that see themselves alike have cross terms near 0 and are dropped.
    ``keep`` (indices into the candidates) keeps those, unmeasured: a chunk of a chunked basis
    keeps the pairs its first chunk chose (:mod:`mitsuba_manifold.render.jobs.chunks`).
    """

    products: tuple
    tol: float = 0.005
    pilot: float = 0.125
    keep: tuple = None
    #: Smallest share of the splats a kept pair's cross term uses: a pair whose weight product is
    #: at most ``p`` uses the power of two at least ``4 p`` (1 at ``p`` = 1/4, the midpoint), so
    #: its noise in a blend, ``p^2 / share``, stays below the midpoint pair's; a third of the cost
    #: of every pair using every splat, for the products of the built-in database.
    min_share: float = 1 / 16

    def share(self, product):
        """The share of the splats of a pair of weight product ``product``."""
        share = 2.0 ** np.ceil(np.log2(max(4.0 * abs(float(product)), self.min_share)))
        return float(min(1.0, share))


def _bins(wi, wo, dims):
    return merl_bin(*merl_angles(wi, wo), dims)


#: The levels whose splats share a kernel: 2 (the cross terms' difference form), 3, and 4 on (few
#: splats each: on the table with white-paint 250k, 115k, 12k, 3k, 1k paths at levels 2 to 6).
LEVEL_SETS = ((2, 2), (3, 3), (4, None))


def _level_sets(levels):
    """:data:`LEVEL_SETS` up to ``levels``: ``(first, last)`` pairs."""
    return [(a, min(levels, b or levels)) for a, b in LEVEL_SETS if a <= levels]


def _merged(parts, k):
    """One splat set ``(k, bins, amplitude, pixel, count)`` from ``parts`` of levels up to ``k`` (the
    highest there: the products run over ``k`` bins):
    the bins past a splat's own level are 0 and ``count`` (None where every splat has ``k`` bins)
    says how many it has; sorted by the first bin, so that the tables are read in order.
    """
    width = [dr.width(p[2]) for p in parts]
    bins = [
        dr.concat(
            [p[0][j] if j < len(p[0]) else dr.zeros(mi.UInt32, w) for p, w in zip(parts, width)]
        )
        for j in range(k)
    ]
    count = (
        None
        if all(len(p[0]) == k for p in parts)
        else dr.concat([dr.full(mi.UInt32, len(p[0]), w) for p, w in zip(parts, width)])
    )
    amp = mi.Color3f(*(dr.concat([p[1][c] for p in parts]) for c in range(3)))
    pix = dr.concat([p[2] for p in parts])
    order = mi.UInt32(np.argsort(bins[0].numpy(), kind="stable").astype(np.uint32))
    take = lambda v, t: dr.gather(t, v, order)  # noqa: E731
    bins, amp, pix = [take(b, mi.UInt32) for b in bins], take(amp, mi.Color3f), take(pix, mi.UInt32)
    count = None if count is None else take(count, mi.UInt32)
    dr.eval(bins, amp, pix, count)
    return k, bins, amp, pix, count


class MultiSplats:
    """Per-pixel sums of ``a prod_j max(f_i(b_j), 0)`` over levels ``2 .. levels`` for every
    material, and of the cross terms of ``pairs`` (index pairs) over every level.

    ``rows`` is the flat ``(bins, 3, n_pad)`` table of :class:`.splats.TableSplats`.
    """

    def __init__(
        self, rows, n_pad, names, dims, pixels, levels, pairs=(), cross_fraction=1.0, select=None
    ):
        self.rows, self.n_pad, self.names, self.dims = rows, int(n_pad), names, dims
        self.cross_fraction = float(cross_fraction)
        self.pixels, self.levels = int(pixels), int(levels)
        self.candidates, self.select = list(pairs), select
        # with a selection, the pairs are chosen on the first pass (:meth:`_choose`)
        self.pairs = list(pairs) if select is None or not pairs else None
        self.groups = self._groups(self.pairs or [], {})
        self.selection = None  # what :meth:`_choose` measured
        self.sums = dr.zeros(mi.Float, self.pixels * 3 * self.n_pad)
        self.splats = []  # (k, [bins], amplitude, pixel, count) per set of levels (:func:`_merged`)
        self.counts = np.zeros(self.levels + 2, np.int64)  # paths by vertices on the target

    def prepare(self, rec, weight, taps, seed=0):
        """Splats of levels ``2 ..`` of one pass (``weight``: the camera sample weight; ``taps``: each
        sample's pixels and filter weights, :meth:`.splats.FilterTaps.taps`; ``seed``:
        of the pass, for the choice of the splats that the cross terms use), in the sets of
        :data:`LEVEL_SETS`: one kernel per set, not per level and kind (each kernel has its fixed
        costs, the per-thread copies of the sums among them, however few splats a high level has).
        """
        self.seed = int(seed)
        levels = rec["levels"]
        self.counts += np.bincount(
            np.minimum(rec["count"].numpy(), self.levels + 1), minlength=self.levels + 2
        )[: self.levels + 2]
        self.splats = []
        for first, last in _level_sets(self.levels):
            parts = [
                part
                for k in range(first, last + 1)
                for part in self._level(levels[:k], weight, taps)
            ]
            if parts:
                self.splats.append(_merged(parts, max(len(p[0]) for p in parts)))

    def _level(self, lv, weight, taps):
        """The splats ``(bins, amplitude, pixel)`` of level ``len(lv)``: light connection, sampled
        direction, each in every pixel of its sample's filter footprint (weighted).
        """
        earlier = [_bins(v["wi"], v["wo"], self.dims) for v in lv[:-1]]
        ok = mi.Bool(True)
        for v in lv[:-1]:
            ok &= (v["wi"].z > 0) & (v["wo"].z > 0)
        last, out = lv[-1], []
        for wo, a in ((last["wo_nee"], last["e_nee"]), (last["wo"], last["g"])):
            a = weight * a * wo.z
            good = ok & (last["wi"].z > 0) & (wo.z > 0) & dr.any(a != 0)
            idx = dr.compress(good)
            if dr.width(idx) == 0:
                continue
            bins = [
                dr.gather(mi.UInt32, b, idx) for b in earlier + [_bins(last["wi"], wo, self.dims)]
            ]
            amp = dr.gather(mi.Color3f, a, idx)
            for take, pix, w in expand(taps, idx):
                if take is None:
                    out.append((bins, amp, pix))
                else:
                    out.append(
                        (
                            [dr.gather(mi.UInt32, b, take) for b in bins],
                            dr.gather(mi.Color3f, amp, take) * w,
                            pix,
                        )
                    )
        return out

    def _sums(self, pairs, pixels=None):
        return [
            dr.zeros(mi.Float, (pixels or self.pixels) * 3 * len(pairs[p0 : p0 + PAIR_CHUNK]))
            for p0 in range(0, len(pairs), PAIR_CHUNK)
        ]

    def _groups(self, pairs, shares):
        """``[(share of the splats, pairs, their sums)]``: the pairs grouped by ``shares`` (pair ->
        share; ``cross_fraction`` times it, 1 where not given).
        """
        by = {}
        for p in pairs:
            by.setdefault(self.cross_fraction * shares.get(p, 1.0), []).append(p)
        return [(f, ps, self._sums(ps)) for f, ps in sorted(by.items(), reverse=True)]

    def add(self):
        """Add the prepared splats to the ``L2+`` sums and the cross terms (on the first pass
        with a :class:`PairSelection`, after choosing the pairs).

        The cross terms use each splat with probability ``cross_fraction`` (weighted by
        its inverse: unbiased), which bounds their cost where many pairs are stored. The picks
        depend on the pass's seed only (the pilot draws from its own stream), so that a chunked
        basis, whose every chunk measures a pilot, picks as the single run does.
        """
        rng = np.random.default_rng([self.seed, 21])
        for _k, bins, amp, pix, count in self.splats:
            self._rest(bins, amp, pix, count)
        if self.pairs is None:
            self._choose(np.random.default_rng([self.seed, 22]))
        for share, pairs, sums in self.groups:
            for _k, bins, amp, pix, count in self.splats:
                self._cross_all(sums, pairs, (bins, amp, pix, count), share, rng)

    def _cross_all(self, sums, pairs, splats, fraction, rng):
        """The cross terms of ``pairs`` into ``sums`` from a share ``fraction`` of the ``splats``
        (``bins, amp, pix, count``).
        """
        bins, amp, pix, count = splats
        if fraction < 1.0:
            pick = np.flatnonzero(rng.random(dr.width(pix)) < fraction).astype(np.uint32)
            if pick.size == 0:
                return
            idx = mi.UInt32(pick)
            bins = [dr.gather(mi.UInt32, b, idx) for b in bins]
            amp = dr.gather(mi.Color3f, amp, idx) * (1.0 / fraction)
            pix = dr.gather(mi.UInt32, pix, idx)
            count = None if count is None else dr.gather(mi.UInt32, count, idx)
        for c, p0 in enumerate(range(0, len(pairs), PAIR_CHUNK)):
            self._cross(sums[c], pairs[p0 : p0 + PAIR_CHUNK], bins, amp, pix, count)

    def _choose(self, rng):
        """Keep the candidate pairs whose cross term matters (:class:`PairSelection`), measured
        on this first pass: every candidate's cross term from a share ``pilot`` of its splats.
        """
        sel = self.select
        if sel.keep is not None:
            keep = np.zeros(len(self.candidates), bool)
            keep[list(sel.keep)] = True
            return self._kept(keep, np.zeros(0))
        # the light a cross term moves, per channel over the image (where per-pixel noise cancels):
        # summed into PILOT_BINS partial sums (pixel index modulo), not per pixel
        pilot = self._sums(self.candidates, PILOT_BINS)
        for _k, bins, amp, pix, count in self.splats:
            self._cross_all(
                pilot, self.candidates, (bins, amp, pix & (PILOT_BINS - 1), count), sel.pilot, rng
            )
        mag = (
            np.concatenate(
                [
                    np.abs(p.numpy().reshape(PILOT_BINS, 3, -1).sum(axis=0)).max(axis=0)
                    for p in pilot
                ]
            )
            if pilot
            else np.zeros(0)
        )
        light = self.sums.numpy().reshape(self.pixels, 3, self.n_pad).sum(axis=0).max(axis=0)
        i, j = (np.array([p[k] for p in self.candidates], dtype=int) for k in (0, 1))
        ref = np.maximum(0.5 * (light[i] + light[j]), 1e-30)
        score = np.asarray(sel.products, float) * mag / ref
        self._kept(score >= sel.tol, score)

    def _kept(self, keep, score):
        """Use the candidates ``keep`` (bool), each with its share of the splats."""
        sel = self.select
        self.pairs = [p for p, k in zip(self.candidates, keep) if k]
        shares = {p: sel.share(w) for p, w, k in zip(self.candidates, sel.products, keep) if k}
        self.groups = self._groups(self.pairs, shares)
        left = score[~keep] if score.size else score
        self.selection = {
            "candidates": len(self.candidates),
            "kept": len(self.pairs),
            "tol": sel.tol,
            "pilot": sel.pilot,
            "largest_left_out": float(left.max()) if left.size else 0.0,
            "splat_share": float(np.mean(list(shares.values()))) if shares else 0.0,
        }

    def _rest(self, bins, amp, pix, count=None):
        packets = self.n_pad // PACKET
        lane = dr.arange(mi.UInt32, dr.width(pix) * packets)
        s, kb = lane // packets, lane % packets
        b = [dr.gather(mi.UInt32, v, s) for v in bins]
        has = _has_bin(count, s, len(b))
        q = dr.gather(mi.UInt32, pix, s)
        a = dr.gather(mi.Color3f, amp, s)
        with _expand(self.sums):
            for c in range(3):
                t = a[c]
                for bj, ok in zip(b, has):
                    f = dr.maximum(
                        dr.gather(
                            mi.ArrayXf,
                            self.rows,
                            (bj * 3 + c) * packets + kb,
                            shape=(PACKET, dr.width(lane)),
                            active=ok,
                        ),
                        0.0,
                    )
                    t = t * (f if ok is True else dr.select(ok, f, 1.0))
                dr.scatter_add(self.sums, t, (q * 3 + c) * packets + kb, mode=dr.ReduceMode.Expand)
            dr.eval(self.sums)

    def _cross(self, sums, pairs, bins, amp, pix, count=None):
        n = len(pairs)
        lane = dr.arange(mi.UInt32, dr.width(pix) * n)
        s, p = lane // n, lane % n
        pi = dr.gather(mi.UInt32, mi.UInt32([i for i, _ in pairs]), p)
        pj = dr.gather(mi.UInt32, mi.UInt32([j for _, j in pairs]), p)
        b = [dr.gather(mi.UInt32, v, s) for v in bins]
        has = _has_bin(count, s, len(b))
        q = dr.gather(mi.UInt32, pix, s)
        a = dr.gather(mi.Color3f, amp, s)
        f = lambda b, c, i: dr.maximum(
            dr.gather(mi.Float, self.rows, (b * 3 + c) * self.n_pad + i), 0.0
        )  # noqa: E731
        with _expand(sums):
            for c in range(3):
                if (
                    len(b) == 2
                ):  # the difference form: exactly 0 for equal materials, no cancellation
                    term = (
                        -a[c]
                        * (f(b[0], c, pi) - f(b[0], c, pj))
                        * (f(b[1], c, pi) - f(b[1], c, pj))
                    )
                else:
                    ti, tj, tm = a[c], a[c], a[c]
                    for bk, ok in zip(b, has):
                        fi, fj = f(bk, c, pi), f(bk, c, pj)
                        if ok is not True:  # past the splat's own level: a factor 1
                            fi, fj = dr.select(ok, fi, 1.0), dr.select(ok, fj, 1.0)
                        ti, tj, tm = ti * fi, tj * fj, tm * (0.5 * (fi + fj))
                    term = 4.0 * tm - 2.0 * ti - 2.0 * tj
                dr.scatter_add(sums, term, (q * 3 + c) * n + p, mode=dr.ReduceMode.Expand)
            dr.eval(sums)

    def release(self):
        self.splats = []

    def images(self, scale, shape):
        """``rest`` (material -> ``L2+`` image) and ``cross`` ((name_i, name_j) -> ``C_ij``),
        scaled by ``scale`` (per pixel: 1 / the filter weights of all samples).
        """
        sums = self.sums.numpy().reshape(self.pixels, 3, self.n_pad) * scale[:, None, None]
        rest = {
            n: np.ascontiguousarray(sums[:, :, k].reshape(shape), np.float32)
            for k, n in enumerate(self.names)
        }
        cross = {}
        for _, pairs, sums in self.groups:
            for c, p0 in enumerate(range(0, len(pairs), PAIR_CHUNK)):
                chunk = pairs[p0 : p0 + PAIR_CHUNK]
                part = sums[c].numpy().reshape(self.pixels, 3, len(chunk)) * scale[:, None, None]
                for k, (i, j) in enumerate(chunk):
                    cross[(self.names[i], self.names[j])] = np.ascontiguousarray(
                        part[:, :, k].reshape(shape), np.float32
                    )
        order = {p: k for k, p in enumerate(self.pairs or [])}  # the candidates' order
        keyed = {(self.names[i], self.names[j]): order[(i, j)] for (i, j) in order}
        return rest, dict(sorted(cross.items(), key=lambda kv: keyed[kv[0]]))


def _has_bin(count, s, k):
    """Per bin position of ``k``, whether the splats ``s`` have it: True, or a mask (``count``)."""
    return (
        [True] * k
        if count is None
        else [True] * 2 + [dr.gather(mi.UInt32, count, s) > j for j in range(2, k)]
    )


class _expand:
    """Let ``ReduceMode.Expand`` scatter-adds keep a copy of ``sums`` per thread."""

    def __init__(self, sums):
        self.width = dr.width(sums)

    def __enter__(self):
        self.threshold = dr.expand_threshold()
        dr.set_expand_threshold(max(self.threshold, self.width))

    def __exit__(self, *exc):
        dr.set_expand_threshold(self.threshold)
