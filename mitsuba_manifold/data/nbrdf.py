"""Neural BRDF networks (NBRDF): reading them and tabulating them on the MERL grid.

An NBRDF (Sztrajman, Rainer, Ritschel and Weyrich, *Neural BRDF Representation and Importance
Sampling*, CGF 40(6), 2021) is a 6-21-21-3 multilayer perceptron trained on one measured
material. For Rusinkiewicz coordinates ``(theta_h, theta_d, phi_d)`` (``phi_h = 0``) its input is
the half and difference vectors

    ``v = (sin th, 0, cos th, sin td cos pd, sin td sin pd, cos td)``,

its layers ``h1 = relu(v W1 + b1)``, ``h2 = relu(h1 W2 + b2)``, ``y = h2 W3 + b3`` (row vectors),
and its output the reflectance ``f = exp(y) - 1`` (1/sr, linear RGB), clamped at 0 here.

:class:`NetworkSet` holds networks in stacked arrays. It is read from the package's ``.npz``
format (:meth:`NetworkSet.load`: arrays ``S_names``, ``S_w1`` ... ``S_b3`` of a set ``S``; the
shipped :data:`WEIGHTS_PATH` holds the sets ``merl``, ``rgl`` and ``nielsen``) or from the
authors' Keras files (:func:`read_keras`: an ``.h5`` of weights beside its ``.json`` model).
:func:`tabulate` evaluates one network at the bins of a MERL grid and :func:`tabulate_many`
several, returning reflectance tables ``(3, n_h, n_d, n_p)`` (0 below the horizon, as
:func:`.merl.filled_reflectance` makes tables).
"""

from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .._util.cache import key_hash
from ..errors import FormatError, InputError, UnknownMaterialError, did_you_mean
from . import merl

if TYPE_CHECKING:
    from typing import Any


__all__ = [
    "DEFAULT_POSITIONS",
    "POSITIONS",
    "SETS",
    "WEIGHTS_PATH",
    "NetworkSet",
    "features",
    "grid_positions",
    "read_keras",
    "tabulate",
    "tabulate_many",
]

#: The weights of the published networks, shipped with the package (MIT licence, ``NBRDF_LICENSE``).
WEIGHTS_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "nbrdf_weights.npz")
#: The sets of :data:`WEIGHTS_PATH`: the measuring device's database of each.
SETS = ("merl", "rgl", "nielsen")

#: Where a bin's network value is taken: ``"centres"`` (the bin centres this package uses for
#: every table) or ``"starts"`` (MERL sample ``(i, j, k)`` at ``th = (i/n)^2 pi/2``,
#: ``td = j/n pi/2``, ``pd = k/n pi``: the positions the published networks were trained at).
POSITIONS = ("centres", "starts")
#: The positions the package tabulates networks at (``docs/`` has the comparison with real
#: measurements that chose it).
DEFAULT_POSITIONS = "centres"

#: Array names of one set ``S`` in a weights file: ``S_names`` and these, stacked over materials.
LAYERS = ("w1", "b1", "w2", "b2", "w3", "b3")
SHAPES = {"w1": (6, 21), "b1": (21,), "w2": (21, 21), "b2": (21,), "w3": (21, 3), "b3": (3,)}
#: Rows of network inputs evaluated at a time (the hidden layers of a block stay in the CPU's cache).
BLOCK = 1 << 15


@dataclass(frozen=True, eq=False)
class NetworkSet:
    """Networks of materials, stacked (``w1`` is ``(n, 6, 21)``, ...).

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

    def __post_init__(self) -> None:
        n = len(self.names)
        for layer in LAYERS:
            a = getattr(self, layer)
            if a.shape != (n,) + SHAPES[layer]:
                raise FormatError(
                    f"NBRDF layer {layer!r} has shape {a.shape}, expected {(n,) + SHAPES[layer]} "
                    f"for {n} networks of 6-21-21-3 units"
                )
            if not np.all(np.isfinite(a)):
                raise FormatError(f"NBRDF layer {layer!r} holds non-finite values")

    @classmethod
    def load(cls, path, prefix) -> NetworkSet:
        """Read the set ``prefix`` (``S_names``, ``S_w1``, ...) from a ``.npz`` weights file."""
        with np.load(path, allow_pickle=False) as f:
            keys = set(f.files)
            missing = [f"{prefix}_{k}" for k in ("names",) + LAYERS if f"{prefix}_{k}" not in keys]
            if missing:
                raise FormatError(f"{path}: no NBRDF set {prefix!r} (missing {', '.join(missing)})")
            names = tuple(str(s) for s in f[f"{prefix}_names"])
            layers = {k: np.ascontiguousarray(f[f"{prefix}_{k}"], dtype=np.float32) for k in LAYERS}
        return cls(names, **layers)

    @staticmethod
    def positions(path, prefix, default) -> Any:
        """The positions a ``.npz`` file records for its set ``prefix`` (``default`` when none)."""
        with np.load(path, allow_pickle=False) as f:
            key = f"{prefix}_positions"
            value = str(f[key]) if key in f.files else default
        if value not in POSITIONS:
            raise FormatError(f"{path}: {key} is {value!r}, not one of {', '.join(POSITIONS)}")
        return value

    @staticmethod
    def prefixes(path) -> list:
        """The sets of a ``.npz`` weights file (``S`` of every ``S_names`` array), in file order."""
        try:
            with np.load(path, allow_pickle=False) as f:
                return [k[: -len("_names")] for k in f.files if k.endswith("_names")]
        except (OSError, ValueError) as e:
            raise FormatError(f"{path}: not an NBRDF .npz weights file ({e})") from None

    def save(self, path, prefix="nbrdf", positions=None) -> None:
        """Write the set as ``prefix_names``, ``prefix_w1`` ... in a ``.npz`` file (atomically),
        with ``prefix_positions`` when given: where its tables are taken (:data:`POSITIONS`).
        """
        from .._util.atomic import atomic_write

        arrays = {f"{prefix}_names": np.array(self.names, dtype=str)}
        if positions is not None:
            if positions not in POSITIONS:
                raise InputError(f"positions={positions!r}: expected one of {', '.join(POSITIONS)}")
            arrays[f"{prefix}_positions"] = np.array(positions)
        arrays.update({f"{prefix}_{k}": getattr(self, k) for k in LAYERS})
        atomic_write(os.fspath(path), lambda f: np.savez(f, **arrays))

    @classmethod
    def concat(cls, sets, names=None) -> NetworkSet:
        """One set of the networks of ``sets`` in order, renamed ``names`` when given."""
        sets = list(sets)
        names = tuple(n for s in sets for n in s.names) if names is None else tuple(names)
        return cls(names, **{k: np.concatenate([getattr(s, k) for s in sets]) for k in LAYERS})

    def subset(self, names) -> NetworkSet:
        """The networks of ``names``, in that order."""
        idx = [self.index(n) for n in names]
        return NetworkSet(tuple(names), **{k: getattr(self, k)[idx] for k in LAYERS})

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name) -> int:
        """Position of the material ``name`` in the set."""
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownMaterialError(
                f"no NBRDF network named {name!r}{did_you_mean(name, self.names)}"
            ) from None

    def digest(self, name) -> str:
        """SHA-256 of the network ``name``'s weights (what its tables are derived from)."""
        i = self.index(name)
        return key_hash(
            "nbrdf-6-21-21-3",
            *(np.ascontiguousarray(getattr(self, k)[i], dtype="<f4") for k in LAYERS),
        )

    def evaluate(self, name, v) -> np.ndarray:
        """Reflectance ``(m, 3)`` (1/sr, clamped at 0) of the network ``name`` at inputs ``v`` ``(m, 6)``."""
        return _evaluate(self, self.index(name), np.asarray(v, dtype=np.float32))


def _evaluate(nets, i, v, out=None) -> np.ndarray:
    """The network ``i`` of ``nets`` at the rows of ``v`` ``(m, 6)`` float32, into ``out`` ``(m, 3)``.

    Evaluated in blocks of :data:`BLOCK` rows with float32 matrix products.
    """
    m = len(v)
    out = np.empty((m, 3), dtype=np.float32) if out is None else out
    w1, b1, w2, b2, w3, b3 = (getattr(nets, k)[i] for k in LAYERS)
    for s in range(0, m, BLOCK):
        h = v[s : s + BLOCK] @ w1
        h += b1
        np.maximum(h, 0.0, out=h)
        h2 = h @ w2
        h2 += b2
        np.maximum(h2, 0.0, out=h2)
        y = h2 @ w3
        y += b3
        out[s : s + BLOCK] = y
    np.expm1(out, out=out)
    np.maximum(out, 0.0, out=out)
    return out


def grid_positions(dims=merl.MERL_DIMS, positions="centres") -> tuple:
    """Rusinkiewicz coordinates ``(theta_h, theta_d, phi_d)`` of a grid's bins, each of shape ``dims``."""
    if positions == "centres":
        return merl.bin_centres(dims)
    if positions != "starts":
        raise InputError(f"positions={positions!r}: expected one of {', '.join(POSITIONS)}")
    n_h, n_d, n_p = dims
    th = (np.arange(n_h) / n_h) ** 2 * (np.pi / 2)
    td = np.arange(n_d) / n_d * (np.pi / 2)
    pd = np.arange(n_p) / n_p * np.pi
    return np.meshgrid(th, td, pd, indexing="ij")


def features(theta_h, theta_d, phi_d, dtype=np.float32) -> np.ndarray:
    """Network inputs ``(m, 6)`` for Rusinkiewicz coordinates (flattened), ``phi_h = 0``."""
    th, td, pd = (np.ravel(np.asarray(a, dtype=np.float64)) for a in (theta_h, theta_d, phi_d))
    v = np.stack(
        [
            np.sin(th),
            np.zeros_like(th),
            np.cos(th),
            np.sin(td) * np.cos(pd),
            np.sin(td) * np.sin(pd),
            np.cos(td),
        ],
        axis=1,
    )
    return v.astype(dtype)


@functools.lru_cache(maxsize=4)
def _grid(dims, positions) -> tuple[np.ndarray, np.ndarray]:
    """The flat indices of a grid's bins above the horizon and the network inputs there (read-only)."""
    above = np.flatnonzero(merl.above_horizon(dims))
    coords = [c.reshape(-1)[above] for c in grid_positions(dims, positions)]
    v = features(*coords)
    for a in (above, v):
        a.setflags(write=False)
    return above, v


def tabulate(
    networks, name, dims=merl.MERL_DIMS, positions=DEFAULT_POSITIONS, dtype=np.float32
) -> np.ndarray:
    """Reflectance table ``(3, n_h, n_d, n_p)`` of one network at a MERL grid's bins.

    Bins whose centre lies below the horizon (:func:`.merl.above_horizon`) are 0; the others
    hold the network's value at ``positions`` (see :data:`POSITIONS`).
    """
    return tabulate_many(networks, [name], dims, positions, dtype)[0]


def tabulate_many(
    networks, names=None, dims=merl.MERL_DIMS, positions=DEFAULT_POSITIONS, dtype=np.float32
) -> np.ndarray:
    """Reflectance tables ``(len(names), 3, n_h, n_d, n_p)`` of the networks ``names`` (default all).

    The grid's inputs are computed once per resolution and positions (kept for the next call);
    the matrix products run on one BLAS thread (their matrices are 21 wide: more threads cost
    more than they gain).
    """
    from .._util.blas import one_thread

    if positions not in POSITIONS:
        raise InputError(f"positions={positions!r}: expected one of {', '.join(POSITIONS)}")
    dims = merl.table_resolution(dims, "`dims`", bytes_per_bin=40)
    names = list(networks.names) if names is None else list(names)
    idx = [networks.index(n) for n in names]
    above, v = _grid(dims, positions)
    bins = int(np.prod(dims))
    out = np.zeros((len(names), 3, bins), dtype=dtype)
    values = np.empty((len(above), 3), dtype=np.float32)
    with one_thread():
        for k, i in enumerate(idx):
            _evaluate(networks, i, v, values)
            out[k][:, above] = values.T
    return out.reshape((len(names), 3) + dims)


# ----------------------------------------------------------------- the authors' files


def read_keras(h5_path, json_path=None, name=None) -> NetworkSet:
    """One network from the authors' Keras files: the weights ``.h5`` and its model ``.json``.

    The ``.h5`` holds the three dense layers' ``kernel`` (in, out) and ``bias`` arrays, as
    Keras ``save_weights`` writes them (or under ``model_weights`` for a whole saved model);
    the ``.json`` (default: beside the ``.h5``) is the model, checked to be 6-21-21-3 dense
    layers with ReLU hidden units. The material is named ``name`` (default: the file's name).
    """
    h5_path = os.fspath(h5_path)
    json_path = (
        os.path.splitext(h5_path)[0] + ".json" if json_path is None else os.fspath(json_path)
    )
    name = name or os.path.splitext(os.path.basename(h5_path))[0]
    if os.path.exists(json_path):
        _check_keras_model(json_path)
    try:
        import h5py
    except ImportError:
        raise InputError(
            f"{h5_path}: reading the authors' Keras .h5 files needs h5py (pip install h5py)"
        ) from None
    try:
        with h5py.File(h5_path, "r") as f:
            root = f.get("model_weights", f)
            layers = []
            order = [
                n.decode() if isinstance(n, bytes) else str(n)
                for n in root.attrs.get("layer_names", [])
            ]
            for layer in order or sorted(root):
                group = root[layer]
                weight_names = [
                    n.decode() if isinstance(n, bytes) else str(n)
                    for n in group.attrs.get("weight_names", [])
                ]
                arrays = [np.asarray(group[w], dtype=np.float32) for w in weight_names]
                if arrays:
                    layers.append(arrays)
    except (OSError, KeyError) as e:
        raise FormatError(f"{h5_path}: not a Keras weights file of an NBRDF ({e})") from None
    shapes = [tuple(a.shape) for layer in layers for a in layer]
    if shapes != [(6, 21), (21,), (21, 21), (21,), (21, 3), (3,)]:
        raise FormatError(
            f"{h5_path}: expected the weights of a 6-21-21-3 NBRDF (kernel and bias of 3 dense "
            f"layers), found arrays of shapes {shapes}"
        )
    flat = [a[None] for layer in layers for a in layer]
    return NetworkSet((name,), *flat)


def _check_keras_model(path) -> None:
    """Refuse a Keras model ``.json`` that is not the NBRDF's dense 6-21-21-3 with ReLU hidden layers."""
    try:
        with open(path) as f:
            model = json.load(f)
        layers = model["config"]["layers"] if isinstance(model["config"], dict) else model["config"]
        dense = [layer["config"] for layer in layers if layer.get("class_name") == "Dense"]
    except (OSError, ValueError, KeyError, TypeError, RecursionError) as e:
        why = "nested too deeply" if isinstance(e, RecursionError) else e
        raise FormatError(f"{path}: not a Keras model file ({why})") from None
    units = [d.get("units") for d in dense]
    acts = [d.get("activation") for d in dense]
    if units != [21, 21, 3] or acts[:2] != ["relu", "relu"]:
        raise FormatError(
            f"{path}: not an NBRDF model (dense layers of {units} units with activations {acts}; "
            "expected 21, 21, 3 with ReLU hidden layers)"
        )
