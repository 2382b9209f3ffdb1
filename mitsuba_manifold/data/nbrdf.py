"""Neural BRDF networks (NBRDF) and their tabulation on the MERL grid.

An NBRDF (Sztrajman, Rainer, Ritschel and Weyrich, *Neural BRDF Representation and Importance
Sampling*, CGF 40(6), 2021) is a 6-21-21-3 multilayer perceptron trained on one measured
material. For Rusinkiewicz coordinates ``(theta_h, theta_d, phi_d)`` (``phi_h = 0``) its input is
the half and difference vectors

    ``v = (sin th, 0, cos th, sin td cos pd, sin td sin pd, cos td)``,

its layers ``h1 = relu(v W1 + b1)``, ``h2 = relu(h1 W2 + b2)``, ``y = h2 W3 + b3`` (row vectors),
and its output the reflectance ``f = exp(y) - 1`` (1/sr, linear RGB), clamped at 0 here.

:class:`NetworkSet` holds the networks of one set in stacked arrays; :func:`tabulate` evaluates
one network at the bins of a MERL grid and returns a reflectance table ``(3, n_h, n_d, n_p)``
(0 below the horizon, as :func:`.merl.filled_reflectance` makes tables).
"""

from dataclasses import dataclass

import numpy as np

from . import merl
from ..errors import FormatError, UnknownMaterialError, did_you_mean

__all__ = ["NetworkSet", "POSITIONS", "features", "grid_positions", "tabulate"]

#: Where a bin's network value is taken: ``"centres"`` (the bin centres this package uses for
#: every table) or ``"starts"`` (MERL sample ``(i, j, k)`` at ``th = (i/n)^2 pi/2``,
#: ``td = j/n pi/2``, ``pd = k/n pi``: the positions the published networks were trained at).
POSITIONS = ("centres", "starts")

#: Array names of one set ``S`` in a weights file: ``S_names`` and these, stacked over materials.
LAYERS = ("w1", "b1", "w2", "b2", "w3", "b3")
SHAPES = {"w1": (6, 21), "b1": (21,), "w2": (21, 21), "b2": (21,), "w3": (21, 3), "b3": (3,)}


@dataclass(frozen=True)
class NetworkSet:
    """The networks of one set of materials, stacked (``w1`` is ``(n, 6, 21)``, ...).

    Attributes
    ----------
    names : tuple of str
        Material names, in the order of the stacked arrays.
    w1, b1, w2, b2, w3, b3 : numpy.ndarray
        Layer weights and biases, float32, first axis over materials.
    """

    names: tuple
    w1: np.ndarray
    b1: np.ndarray
    w2: np.ndarray
    b2: np.ndarray
    w3: np.ndarray
    b3: np.ndarray

    def __post_init__(self):
        n = len(self.names)
        for layer in LAYERS:
            a = getattr(self, layer)
            if a.shape != (n,) + SHAPES[layer]:
                raise FormatError(
                    f"NBRDF layer {layer!r} has shape {a.shape}, expected {(n,) + SHAPES[layer]} "
                    f"for {n} networks of 6-21-21-3 units")
            if not np.all(np.isfinite(a)):
                raise FormatError(f"NBRDF layer {layer!r} holds non-finite values")

    @classmethod
    def load(cls, path, prefix):
        """Read the set ``prefix`` (``S_names``, ``S_w1``, ...) from a ``.npz`` weights file."""
        with np.load(path, allow_pickle=False) as f:
            keys = set(f.files)
            missing = [f"{prefix}_{k}" for k in ("names",) + LAYERS if f"{prefix}_{k}" not in keys]
            if missing:
                raise FormatError(f"{path}: no NBRDF set {prefix!r} (missing {', '.join(missing)})")
            names = tuple(str(s) for s in f[f"{prefix}_names"])
            layers = {k: np.ascontiguousarray(f[f"{prefix}_{k}"], dtype=np.float32) for k in LAYERS}
        return cls(names, **layers)

    def __len__(self):
        return len(self.names)

    def index(self, name):
        """Position of the material ``name`` in the set."""
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownMaterialError(
                f"no NBRDF network named {name!r}{did_you_mean(name, self.names)}") from None

    def evaluate(self, name, v):
        """Reflectance ``(m, 3)`` (1/sr, clamped at 0) of the network ``name`` at inputs ``v`` ``(m, 6)``."""
        i = self.index(name)
        h = np.maximum(v @ self.w1[i] + self.b1[i], 0.0)
        h = np.maximum(h @ self.w2[i] + self.b2[i], 0.0)
        return np.maximum(np.expm1(h @ self.w3[i] + self.b3[i]), 0.0)


def grid_positions(dims=merl.MERL_DIMS, positions="centres"):
    """Rusinkiewicz coordinates ``(theta_h, theta_d, phi_d)`` of a grid's bins, each of shape ``dims``."""
    if positions == "centres":
        return merl.bin_centres(dims)
    if positions != "starts":
        raise ValueError(f"positions={positions!r}: expected one of {', '.join(POSITIONS)}")
    n_h, n_d, n_p = dims
    th = (np.arange(n_h) / n_h) ** 2 * (np.pi / 2)
    td = np.arange(n_d) / n_d * (np.pi / 2)
    pd = np.arange(n_p) / n_p * np.pi
    return np.meshgrid(th, td, pd, indexing="ij")


def features(theta_h, theta_d, phi_d, dtype=np.float32):
    """Network inputs ``(m, 6)`` for Rusinkiewicz coordinates (flattened), ``phi_h = 0``."""
    th, td, pd = (np.ravel(np.asarray(a, dtype=np.float64)) for a in (theta_h, theta_d, phi_d))
    v = np.stack([np.sin(th), np.zeros_like(th), np.cos(th),
                  np.sin(td) * np.cos(pd), np.sin(td) * np.sin(pd), np.cos(td)], axis=1)
    return v.astype(dtype)


def tabulate(networks, name, dims=merl.MERL_DIMS, positions="centres", dtype=np.float32):
    """Reflectance table ``(3, n_h, n_d, n_p)`` of one network at a MERL grid's bins.

    Bins whose centre lies below the horizon (:func:`.merl.above_horizon`) are 0; the others
    hold the network's value at ``positions`` (see :data:`POSITIONS`).
    """
    dims = tuple(int(d) for d in dims)
    above = merl.above_horizon(dims)
    coords = [c[above] for c in grid_positions(dims, positions)]
    out = np.zeros((3,) + dims, dtype=dtype)
    out[:, above] = networks.evaluate(name, features(*coords)).T
    return out
