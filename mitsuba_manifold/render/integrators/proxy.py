"""The sampling proxy of a one-pass render (:mod:`.onepass`): a ``manifold_brdf`` whose density
covers every rendered material (paper Sec. 5.3), or a point's blend of them, and the point's own
material as one more column of the interleaved tables (:func:`with_point`).
"""

import os
import threading

import mitsuba as mi
import numpy as np

from ..._util.cache import Eviction, key_hash, npy_cache
from .splats import PACKET

#: Name of the point's own material in a render with ``point`` weights (:func:`.onepass.render_onepass_gi`).
POINT = "(point)"


def rows_key(rows):
    """The content hash naming interleaved tables: the cached file's name, or the key of tables
    made in memory (:class:`~mitsuba_manifold.data.database.TableRows`).
    """
    return getattr(rows, "key", None) or os.path.basename(rows.filename).split(".")[0]


def _mixture_table(db, rows, mix, keep=2):
    """``sum_k mix_k table_k`` from the interleaved tables ``rows``, as ``(bins, 3)`` float32.

    Cached beside ``rows`` (keyed by them and the weights; the ``keep`` newest kept), so
    that a later render need not read every table before it starts tracing.
    """
    key = rows_key(rows)
    digest = key_hash(np.asarray(mix, dtype=np.float64), length=16)
    path = os.path.join(db.cache_dir, f"{key}.mixture-v1-{digest}.npy")
    shape = (rows.shape[0], 3)

    def build():
        w = np.zeros(rows.shape[2], dtype=np.float32)
        w[: len(mix)] = mix
        return (np.asarray(rows).reshape(-1, rows.shape[2]) @ w).reshape(shape)

    return npy_cache(
        path,
        build,
        shape=shape,
        dtype=np.float32,
        finite=True,
        eviction=Eviction(keep, ".mixture-v1-"),
    )


def _with_point(target, db, names, rows, w):
    """``(rows, names, proxy)``: the ``(bins, 3, n)`` tables of the materials ``names`` and, after
    them, the column ``sum_k w_k table_k`` (the point's material, :data:`POINT`), padded to
    PACKET; the names with :data:`POINT`; the proxy sampling ``|w|`` (:func:`_sampling_proxy`).
    """
    k = len(w)
    out = np.zeros(rows.shape[:2] + (-(-(k + 1) // PACKET) * PACKET,), np.float32)
    out[:, :, :k] = rows[:, :, :k]
    out[:, :, k] = out[:, :, :k] @ np.asarray(w, np.float32)
    mix = np.abs(w) / float(np.abs(w).sum())
    # convex weights: the proxy's table is the point's column (scaled to sum 1), not a second product
    table = (
        out[:, :, k] / float(w.sum())
        if np.all(w >= 0)
        else out[:, :, :k].reshape(-1, k) @ mix.astype(np.float32)
    )
    return (
        out,
        names + [POINT],
        sampling_proxy(target, db, names, out, mix, table.reshape(out.shape[0], 3)),
    )


class _LastPoint:
    """The last point's ``_with_point`` result, kept for the next pass of the same point (a
    refinement renders one point in several passes, and the column is built once). Keyed by the
    tables' file, the names and the weights; one entry, locked.
    """

    def __init__(self):
        self.key, self.value, self.lock = None, None, threading.Lock()

    def get(self, args, build):
        target, db, names, rows, w = args
        key = (
            rows_key(rows),
            tuple(names),
            target.path,
            target.sampling,
            target.interpolation,
            np.asarray(w, np.float64).tobytes(),
        )
        with self.lock:
            if key != self.key:
                self.key, self.value = None, None  # free the old column before building the new one
                self.value, self.key = build(*args), key
            rows_out, names_out, proxy = self.value
            return rows_out, list(names_out), proxy

    def clear(self):
        with self.lock:
            self.key, self.value = None, None


_POINT_CACHE = _LastPoint()


def forget_point():
    """Drop the last point's tables (:class:`_LastPoint`): the next point builds its own."""
    _POINT_CACHE.clear()


def with_point(target, db, names, rows, w):
    """:func:`_with_point`, the last point's result reused (:class:`_LastPoint`)."""
    return _POINT_CACHE.get((target, db, names, rows, w), _with_point)


def sampling_proxy(target, db, names, rows, mix=None, table=None):
    """A ``manifold_brdf`` sampling a density that covers every material: the mixture
    ``sum_i P_i / |P_i|`` of the per-material sampling densities (paper Sec. 5.3), or ``mix``
    (a point's weights, their absolute values normalised) with its ``table`` ``sum_i mix_i f_i``
    (``(bins, 3)``; for convex weights the point's own material: its paths are sampled as a
    direct render's).
    """
    from ..plugin.sampling import material_density

    if mix is None:
        mass = np.array([material_density(db, n).sum() for n in names], float)
        top = mass.max()
        mix = 1.0 / np.maximum(mass, 1e-3 * top) if top > 0 else np.ones(len(names))
        mix /= mix.sum()
    spec = {
        "type": "manifold_brdf",
        "manifold": target.path,
        "prune": 0.0,
        "sampling": target.sampling,
        **target.options(),
    }
    if rows is None:
        return mi.load_dict(
            {**spec, "weights": ", ".join(f"{n}:{float(w)!r}" for n, w in zip(names, mix))}
        )
    dims = tuple(int(d) for d in db.dims)
    if table is None:  # the mixture's table from the interleaved tables (cached)
        table = _mixture_table(db, rows, mix)
    table = table.T.reshape((3,) + dims)
    proxy = mi.load_dict({**spec, "material": names[0]})
    proxy.set_weights(dict(zip(names, mix)), table=table)
    return proxy
