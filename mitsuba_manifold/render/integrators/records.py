"""What :meth:`ManifoldPathIntegrator.trace_paths` records of a path's vertices on the target
(one-pass rendering, :mod:`.onepass`), for paths touching it up to ``levels`` times.

A path's vertices on the target ``v_1 .. v_k`` are sampled with the proxy (density ``q``),
and everything the material contributes is left out of the recorded amplitudes: a
material ``f`` then adds, per level ``j`` (the contributions made after ``v_j`` and before
``v_{j+1}``), ``f(bin(wi_1, wo_1)) ... f(bin(wi_{j-1}, wo_{j-1})) f(bin(wi_j, wo_nee_j)) e_nee_j
cos`` (the light connection made at ``v_j``) and ``f(bin(wi_1, wo_1)) ... f(bin(wi_j, wo_j))
g_j cos`` (what came back along the sampled direction). ``e_nee_j`` and ``g_j`` hold the
material-free throughput up to ``v_j`` (``T_j``: the other vertices' BSDF weights, the
cosines and ``1 / q`` of the earlier target vertices, Russian roulette). With one level this
is the touch image; levels ``2 ..`` make the ``L2+`` image of the material (paper Sec. 5.2:
the one-pass weight becomes the product of ``f_i / proxy`` over those vertices).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import drjit as dr
import mitsuba as mi

if TYPE_CHECKING:
    from typing import Any


class RecordState:
    """Per-path loop state: ``n`` (vertices on the target so far), ``acc`` (radiance since the
    last one, in units of ``beta``), ``tn`` (``T_n``), ``u`` (``T_n / q_n``) and ``c`` (the
    cosine of the last sampled direction).
    """

    DRJIT_STRUCT = {
        "n": mi.UInt32,
        "acc": mi.Spectrum,
        "tn": mi.Spectrum,
        "u": mi.Spectrum,
        "c": mi.Float,
    }

    def __init__(self, n=None, acc=None, tn=None, u=None, c=None) -> None:
        self.n = mi.UInt32(0) if n is None else n
        self.acc = mi.Spectrum(0) if acc is None else acc
        self.tn = mi.Spectrum(0) if tn is None else tn
        self.u = mi.Spectrum(1) if u is None else u
        self.c = mi.Float(1) if c is None else c


class Records:
    """The per-level buffers of ``width`` paths, written by scatters while tracing; the loop
    state is a :class:`RecordState` (``self.state``, passed through every call).
    """

    def __init__(self, levels, width) -> None:
        self.levels = int(levels)
        self.state = RecordState()
        size = int(width) * self.levels
        self.base = dr.arange(mi.UInt32, int(width)) * self.levels
        up = mi.Vector3f(0, 0, 1)
        self.wi = dr.zeros(mi.Vector3f, size) + up
        self.wo_nee = dr.zeros(mi.Vector3f, size) + up
        self.wo = dr.zeros(mi.Vector3f, size) + up
        self.e_nee = dr.zeros(mi.Spectrum, size)
        self.g = dr.zeros(mi.Spectrum, size)
        dr.make_opaque(self.wi, self.wo_nee, self.wo, self.e_nee, self.g)

    def _flush(self, st, mask) -> None:
        """Write what came back since the last vertex (``u * acc``) to its level."""
        ok = mask & (st.n > 0) & (st.n <= self.levels)
        dr.scatter(self.g, st.u * st.acc, self.base + st.n - 1, ok)

    def arrive(self, st, hit, beta, wi) -> tuple:
        """A vertex on the target (lanes ``hit``); returns the new state and the lanes where it
        is recorded (those with at most ``levels`` vertices on the target so far).
        """
        self._flush(st, hit)
        n = dr.select(hit, st.n + 1, st.n)
        first = hit & (n <= self.levels)
        dr.scatter(self.wi, wi, self.base + n - 1, first)
        st = RecordState(
            n, dr.select(hit, 0, st.acc), dr.select(first, st.u * st.c * beta, st.tn), st.u, st.c
        )
        return st, first

    def light(self, st, first, wo, e) -> None:
        """The light connection made there: direction ``wo``, ``e`` = radiance / light pdf, MIS."""
        idx = self.base + st.n - 1
        dr.scatter(self.wo_nee, wo, idx, first)
        dr.scatter(self.e_nee, st.tn * e, idx, first)

    def leave(self, st, first, wo, inv_q) -> RecordState:
        """The direction sampled there (``1 / q``; 0 where the path cannot go on); the new state."""
        dr.scatter(self.wo, wo, self.base + st.n - 1, first)
        return RecordState(
            st.n, st.acc, st.tn, dr.select(first, st.tn * inv_q, st.u), dr.select(first, wo.z, st.c)
        )

    def finish(self, st) -> dict[str, Any]:
        """The records: per level ``j`` (0-based) a dict ``wi, wo_nee, e_nee, wo, g`` in
        ``"levels"``; level 1's also at the top level, with ``beta`` = 1 (the earlier layout),
        and ``count`` (each path's vertices on the target, ``levels + 1`` where it was cut).
        """
        self._flush(st, mi.Bool(True))
        levels = []
        for j in range(self.levels):
            levels.append(
                {
                    k: dr.gather(type(v), v, self.base + j)
                    for k, v in (
                        ("wi", self.wi),
                        ("wo_nee", self.wo_nee),
                        ("e_nee", self.e_nee),
                        ("wo", self.wo),
                        ("g", self.g),
                    )
                }
            )
        return dict(
            levels[0],
            beta=dr.full(mi.Spectrum, 1.0, dr.width(self.base)),
            levels=levels,
            count=st.n,
        )
