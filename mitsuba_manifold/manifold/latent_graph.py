"""The graph of latent samples that geodesics start from (:mod:`paths`), and its disk cache.

A geodesic between two points of the material space (``paths.geodesic``) starts from the
shortest path through a :class:`LatentGraph`: latent samples where the data is, edges
weighted by the perceptual distance of their tables. Weighing its ~23 000 edges is the one
costly step (its time: ``tools/bench.py paths``, ``docs/benchmarks.md``); the
edges are saved once per manifold and metric in the database's cache folder
(:func:`database.cache_folder`), named by a content hash of everything they depend on
(:func:`cache_key`: the latent points, the interpolant, the recorded hashes of the tables,
the metric's bins and the graph's settings), so a later process reads them back
instead. The nodes are recomputed (cheap, deterministic).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .._util.cache import Eviction, key_hash, npy_cache
from ..errors import InputError

if TYPE_CHECKING:
    from typing import Any


#: Version of the cached edges' layout and of the graph's construction (part of the cache key).
VERSION = "latent-graph-v2"
#: The graph's settings: latent neighbours per material, samples per segment, node neighbours.
NEIGHBOURS, PER_EDGE, K = 8, 7, 10
#: Edges weighed per block (memory: two gathered blocks of features).
EDGE_BLOCK = 2048


def cache_key(metric, *parts) -> str:
    """Content hash naming a cache file of ``metric`` (a :class:`paths.PathMetric`) and ``parts``:
    the manifold's latent points, interpolant and recorded table hashes, and the metric's bins.
    """
    m = metric.manifold
    return key_hash(
        *map(str, parts),
        np.ascontiguousarray(m.latent, dtype=np.float64),
        json.dumps(m.interpolant.params(), sort_keys=True),
        repr(tuple(metric.quad.dims)),
        repr(tuple(metric.quad.stride)),
        *m.hashes,
        length=40,
    )


def cache_folder(manifold) -> str | None:
    """The cache folder of ``manifold``'s database (a built-in set's: the user's cache), or None
    when that folder is gone (no caching: creating it would make an empty database folder).
    """
    from ..data.database import database_cache

    return database_cache(manifold.database)


def cached(metric, name, build, shape=None, dtype=None, keep=4, settings=()) -> np.ndarray:
    """``build()`` cached as ``<key>.<name>.npy`` in the manifold's cache folder (:func:`cache_key`
    of ``name`` and ``settings``); only the ``keep`` most recently used files of ``name`` are kept.
    """
    folder = cache_folder(metric.manifold)
    if folder is None:
        return build()
    path = os.path.join(folder, f"{cache_key(metric, name, *settings)}.{name}.npy")
    return npy_cache(
        path,
        build,
        shape=shape,
        dtype=dtype,
        finite=True,
        eviction=Eviction(keep, f".{name}."),
    )


@dataclass
class LatentGraph:
    """A graph of latent samples where the data is, edges weighted by perceptual distance.

    Nodes: the (distinct) latent points and ``per_edge`` points along each segment from a
    material to each of its ``neighbours`` nearest latent neighbours and along the segments
    of their minimum spanning tree (the blends the space offers; the tree keeps the graph
    connected); edges: consecutive nodes along each segment and each node to its ``k``
    nearest nodes in latent space, weighted by the distance between their tables.
    """

    nodes: np.ndarray
    graph: object

    @staticmethod
    def layout(X, neighbours=NEIGHBOURS, per_edge=PER_EDGE, k=K) -> tuple[np.ndarray, Any]:
        """Nodes ``(n, q)`` and candidate edges ``(E, 2)`` (``i < j``) of the graph over latent points ``X``."""
        from scipy.sparse.csgraph import minimum_spanning_tree
        from scipy.spatial import cKDTree

        n, q = X.shape
        nn = cKDTree(X).query(X, k=min(neighbours, n - 1) + 1)[1][:, 1:]
        tree = minimum_spanning_tree(np.linalg.norm(X[:, None] - X[None], axis=-1) + 1e-12).tocoo()
        pairs = np.concatenate(
            [
                np.stack([np.repeat(np.arange(n), nn.shape[1]), nn.ravel()], 1),
                np.stack([tree.row, tree.col], 1),
            ]
        )
        pairs = np.unique(np.sort(pairs, axis=1), axis=0)
        t = np.linspace(0.0, 1.0, per_edge + 2)
        chains = (
            X[pairs[:, 0], None] + t[None, :, None] * (X[pairs[:, 1]] - X[pairs[:, 0]])[:, None]
        )
        nodes, inverse = np.unique(chains.reshape(-1, q), axis=0, return_inverse=True)
        inverse = inverse.reshape(chains.shape[:2])
        idx = cKDTree(nodes).query(nodes, k=min(k, len(nodes) - 1) + 1)[1]
        rows = np.concatenate(
            [np.repeat(np.arange(len(nodes)), idx.shape[1] - 1), inverse[:, :-1].ravel()]
        )
        cols = np.concatenate([idx[:, 1:].ravel(), inverse[:, 1:].ravel()])
        edges = np.unique(np.sort(np.stack([rows, cols], 1), axis=1), axis=0)
        return nodes, edges[edges[:, 0] != edges[:, 1]]

    @staticmethod
    def weigh(metric, nodes, edges) -> np.ndarray:
        """Perceptual lengths of ``edges`` between ``nodes`` (blockwise, float32 features)."""
        F = np.concatenate(
            [metric.features(nodes[s : s + 1024]) for s in range(0, len(nodes), 1024)]
        )
        w = np.empty(len(edges))
        for s in range(0, len(edges), EDGE_BLOCK):
            e = edges[s : s + EDGE_BLOCK]
            diff = F[e[:, 0]] - F[e[:, 1]]
            w[s : s + EDGE_BLOCK] = np.sqrt(np.einsum("ek,ek->e", diff, diff, dtype=np.float64))
        return w

    @classmethod
    def build(cls, metric, cache=True) -> LatentGraph:
        """The graph of ``metric``'s manifold; edge lengths read from the cache when ``cache`` (module doc)."""
        from scipy import sparse

        nodes, edges = cls.layout(metric.manifold.latent)

        def weigh() -> np.ndarray:
            return cls.weigh(metric, nodes, edges)

        w = (
            cached(
                metric,
                VERSION,
                weigh,
                shape=(len(edges),),
                dtype=np.float64,
                settings=(NEIGHBOURS, PER_EDGE, K),
            )
            if cache
            else weigh()
        )
        g = sparse.coo_matrix(
            (np.asarray(w) + 1e-12, (edges[:, 0], edges[:, 1])), shape=(len(nodes),) * 2
        ).tocsr()
        return cls(nodes, (g + g.T).tocsr())

    def shortest(self, metric, xa, xb, k=K) -> np.ndarray:
        """Latent polyline of the shortest graph path from ``xa`` to ``xb`` (ends joined to their
        ``k`` nearest nodes).
        """
        from scipy import sparse
        from scipy.sparse.csgraph import dijkstra
        from scipy.spatial import cKDTree

        n = len(self.nodes)
        ends = np.stack([xa, xb])
        near = cKDTree(self.nodes).query(ends, k=min(k, n))[1]
        Fe, Fn = metric.features(ends), metric.features(self.nodes[near.ravel()])
        diff = np.repeat(Fe, near.shape[1], axis=0) - Fn
        w = np.sqrt(np.einsum("ek,ek->e", diff, diff, dtype=np.float64)) + 1e-12
        rows = np.repeat([n, n + 1], near.shape[1])
        extra = sparse.coo_matrix((w, (rows, near.ravel())), shape=(n + 2, n + 2)).tocsr()
        g = (
            sparse.bmat([[self.graph, None], [None, sparse.csr_matrix((2, 2))]]).tocsr()
            + extra
            + extra.T
        )
        _, pred = dijkstra(g, indices=n, return_predecessors=True)
        chain, v = [n + 1], n + 1
        while v != n:
            v = pred[v]
            if v < 0:
                raise InputError("the path's ends are not connected through the latent graph")
            chain.append(v)
        pts = np.concatenate([self.nodes, ends])
        return pts[chain[::-1]]
