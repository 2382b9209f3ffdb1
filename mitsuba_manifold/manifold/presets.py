"""Named fit settings of a manifold: the paper's exact formulation and the measured default.

A setting dict holds ``q``, ``features``, ``method``, ``length_scale``, ``noise`` (the GPLVM
layout, paper Sec. 3), ``stress`` and ``stress_neighbours`` (the weight and pairs of the
layout's optional stress term towards the tables' perceptual distances, :mod:`gp.stress`; 0:
none) and ``interpolant`` (the weight function, :mod:`interpolant`).
``Manifold.fit`` and ``tools/bench.py space`` both go through :func:`settings`,
:func:`fit_layout` and :func:`make_interpolant`, so the benchmark measures what users get.
"""

from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import numpy as np

from .._util import checks
from ..data.distance import distance_matrix
from ..errors import InputError
from ..gp import gplvm
from . import interpolant as interpolants

if TYPE_CHECKING:
    from typing import Any

    from ..gp.gplvm import FitResult
    from ..gp.stress import Stress
    from .interpolant import GaussianProcessWeights, ShepardWeights


#: Fit settings by name. ``paper``: the paper's exact formulation (raw features, l = 1,
#: mu = 1e-4, Hooke-Jeeves, Eq. 4 weights). ``default``: the measured best
#: (``tools/bench.py space``; README, "The material space").
PRESETS = {
    "paper": {
        "q": 2,
        "features": "raw",
        "method": "hooke-jeeves",
        "length_scale": 1.0,
        "noise": 1e-4,
        "stress": 0.0,
        "stress_neighbours": None,
        "interpolant": {"kind": "gp", "exact": True},
    },
    "default": {
        "q": 4,
        "features": "log",
        "method": "newton",
        "length_scale": 1.0,
        "noise": 1e-4,
        "stress": 20.0,
        "stress_neighbours": None,
        "interpolant": {
            "kind": "shepard",
            "power": 2.0,
            "taper": 0.2,
            "spread": 0.1,
            "beyond": "continue",
        },
    },
}


def settings(preset="default", **overrides) -> "dict[str, Any]":
    """Fit settings of ``preset`` (:data:`PRESETS`) with the non-None ``overrides`` applied.

    An ``interpolant`` override of the preset's kind (or without ``kind``) changes only the
    parameters it names (``{"taper": 0.3}``); one of another kind replaces it whole.
    """
    if preset not in PRESETS:
        raise InputError(f"unknown `preset` {preset!r}; use one of {', '.join(PRESETS)}")
    unknown = set(overrides) - set(PRESETS[preset])
    if unknown:
        raise InputError(
            f"unknown setting(s) {sorted(unknown)}; settings are {sorted(PRESETS[preset])}"
        )
    out = {**PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None}}
    given, base = overrides.get("interpolant"), PRESETS[preset]["interpolant"]
    if isinstance(given, dict) and given.get("kind", base["kind"]) == base["kind"]:
        out["interpolant"] = {**base, **given}
    return out


@dataclass(frozen=True)
class FitOptions:
    """What a user sets of a fit (``Manifold.fit``'s parameters; None: the ``preset``'s).

    Parameters
    ----------
    preset : str
        A name of :data:`PRESETS`.
    q, names, method, features, length_scale, noise, stress
        As ``Manifold.fit``.
    """

    preset: str = "default"
    q: Optional[int] = None
    names: Optional[list] = None
    method: Optional[str] = None
    features: Optional[str] = None
    length_scale: Optional[float] = None
    noise: Optional[float] = None
    stress: Optional[float] = None

    def given(self) -> list:
        """The options set (a preset other than the default counts), as backquoted names."""
        fields = ("q", "names", "method", "features", "length_scale", "noise", "stress")
        given = [f"`{k}`" for k in fields if getattr(self, k) is not None]
        preset = [] if self.preset == "default" else ["`preset`"]
        return given + preset

    def check(self) -> "FitOptions":
        """Raise :class:`InputError` for a value out of range, or a method that cannot fit the
        preset's (or the given) stress term; returns ``self``.
        """
        if self.q is not None and not 1 <= self.q <= 8:
            raise InputError(f"`q` must be an integer from 1 to 8, got {self.q}")
        if self.length_scale is not None:
            checks.finite("`length_scale`", self.length_scale, 0.0, 1e6, lo_open=True)
        if self.noise is not None:
            checks.finite("`noise`", self.noise, 0.0, 1e6, lo_open=True)
        if self.stress is not None:
            checks.finite("`stress`", self.stress, 0.0, 1e6)
        method = self.method or PRESETS[self.preset]["method"]
        stress = PRESETS[self.preset]["stress"] if self.stress is None else self.stress
        if method == "hooke-jeeves" and stress > 0:
            raise InputError(
                f"`method` {method} cannot fit the layout's stress term (weight {stress:g}, "
                f"{'`stress`' if self.stress is not None else 'the ' + self.preset + ' preset'}): "
                "add `stress` 0, or use `method` newton (or lbfgs)"
            )
        return self


def canonical_order(hashes, names) -> "np.ndarray":
    """The order a fit sees the materials in: by the content hash of each table (SHA-256,
    :meth:`~..data.database.Database.hash`), then by name for identical tables. It depends on
    the tables only, so the order the user lists them in does not reach the fit.

    Returns
    -------
    (N,) int ndarray
        ``order[k]``: the index, in the given lists, of the ``k``-th material of the fit.
    """
    if len(hashes) != len(names):
        raise InputError(f"{len(hashes)} hashes for {len(names)} names: one per material needed")
    return np.array(
        sorted(range(len(names)), key=lambda i: (str(hashes[i]), str(names[i]))), dtype=np.intp
    )


def fit_layout(
    S, d, cfg, init=None, callback=None, distances=None, order=None, **options
) -> "FitResult":
    """Latent points for the Gram matrix ``S`` under settings ``cfg`` (:class:`gplvm.GPLVM`);
    ``options`` (``max_iter``, ``tol``, ``initial_step``, ``continuation``, ``krylov``) set the
    optimiser (:func:`gplvm.optimiser_options`); ``distances``: the materials' perceptual distances (N, N),
    the stress term's targets (needed when ``cfg["stress"] > 0``).

    ``order`` (:func:`canonical_order`): the order the optimiser sees the materials in; ``S``,
    ``distances``, ``init`` and the result's points stay in the given order (the callback
    gets the optimiser's).
    """
    model = gplvm.GPLVM(
        cfg["q"],
        gplvm.Kernel(cfg["length_scale"], cfg["noise"]),
        cfg["method"],
        gplvm.optimiser_options(cfg["method"], **options),
        stress_of(cfg),
    )
    if order is None:
        return model.fit(S, d, init, callback, distances)
    order = np.asarray(order, dtype=np.intp)
    n = np.shape(S)[0]
    if sorted(order.tolist()) != list(range(n)):
        raise InputError(f"`order` must be a permutation of 0..{n - 1}, got {order.tolist()[:8]}")
    pick = np.ix_(order, order)
    res = model.fit(
        np.asarray(S, dtype=np.float64)[pick],
        d,
        None if init is None else np.asarray(init, dtype=np.float64)[order],
        callback,
        None if distances is None else np.asarray(distances, dtype=np.float64)[pick],
    )
    back = np.empty_like(order)
    back[order] = np.arange(n)
    res.latent = res.latent[back]
    return res


#: The grid of the stress term's distances: tables are compared on every k-th bin along each
#: axis, k their resolution over this one rounded down (one bin a cell, weighted by the cell's
#: measure: :class:`~..data.distance.Quadrature`).
STRESS_GRID = (30, 30, 60)


def stress_stride(dims) -> tuple:
    """The sub-grid stride of :func:`stress_distances` for tables of ``dims`` bins."""
    return tuple(max(1, int(n) // g) for n, g in zip(dims, STRESS_GRID))


def stress_distances(tables, dims) -> "np.ndarray":
    """The stress term's targets: the [PR12] distances between ``tables`` (``(N, 3 * bins)``
    rows of ``dims`` bins; :func:`~..data.distance.distance_matrix`) on the sub-grid of
    :func:`stress_stride`.
    """
    return distance_matrix(tables, dims=dims, stride=stress_stride(dims))


def stress_of(cfg) -> "Stress":
    """The :class:`gplvm.Stress` of settings ``cfg`` (none when they have no stress entries)."""
    return gplvm.Stress(cfg.get("stress", 0.0), cfg.get("stress_neighbours"))


def make_interpolant(latent, cfg) -> "GaussianProcessWeights | ShepardWeights":
    """The interpolant of settings ``cfg`` over ``latent`` (kernel l and mu filled in)."""
    params = dict(cfg["interpolant"])
    params.setdefault("length_scale", cfg["length_scale"])
    if params.get("kind") == "gp":
        params.setdefault("noise", cfg["noise"])
    return interpolants.make(latent, params)
