"""What a ``manifold_brdf`` renders: its plugin properties checked, and the combined material.

:func:`read_properties` turns the properties of a scene (or ``mi.load_dict``) into a
:class:`BRDFOptions` and the loaded :class:`~mitsuba_manifold.manifold.model.Manifold`;
:func:`combine` computes, for weights ``w``, the table ``sum_i w_i table_i`` over the materials
kept by pruning (negative values clamped to 0, uploaded as one packed table) and, for
``sampling="cdf"``, the sampling density ``max(0, sum_i w_i P_i)`` of paper Sec. 5.3 as a
``MarginalContinuous2D1`` (:mod:`.sampling`).
"""

import os
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ...data.sources import BUILTIN_PREFIX, SET_NAMES
from ...errors import InputError
from ...manifold.file.shipped import SHIPPED, ambiguity, resolve_manifold, shipped_path
from ...manifold.model import DEFAULT_PRUNE, Manifold
from .overrides import database_folder
from .sampling import PLUGIN_NAME, combined_distribution, material_density

SAMPLING_MODES = ("cdf", "cosine")
INTERPOLATION_MODES = ("nearest", "linear")
#: The properties that choose the material; exactly one is given.
CHOOSERS = ("x", "material", "weights")


@dataclass(frozen=True)
class BRDFOptions:
    """The checked plugin properties of one ``manifold_brdf`` (see :class:`.bsdf.ManifoldBRDF`)."""

    manifold_path: str
    database: object  # str, or None: the manifold's own
    prune: float
    sampling: str
    interpolation: str
    chooser: str  # which of CHOOSERS was given
    value: object  # its value


@dataclass(frozen=True)
class Combination:
    """The material rendered for weights ``w`` (from :func:`combine`)."""

    w: np.ndarray
    x: object  # latent point, or None
    material: object  # training material's name, or None
    keep: np.ndarray  # indices of the materials in the table
    dropped: float  # sum |w_i| of the materials pruned
    prune_error: float  # relative change of the table made by pruning, in the rule's norm
    pruning: object  # what pruning kept and the bounds it reached (a PruneReport)
    n_clamped: int  # (channel, bin) values clamped below 0
    n_values: int
    black: bool  # the sampling density has no mass (the material reflects nothing)
    dims: tuple
    distr: object  # MarginalContinuous2D1, or None (sampling="cosine")
    table: object  # (bins, 3) RGB, a Dr.Jit Float in JIT variants, NumPy in scalar ones


def resolve(path, what):
    """A path as given in a scene, resolved with Mitsuba's file resolver (which knows
    the folder of the scene being loaded); error naming the folders searched.
    """
    path = os.fspath(path)
    found = str(mi.file_resolver().resolve(path))
    if not os.path.exists(found):
        fr = mi.file_resolver()
        where = ", ".join(str(fr[i]) for i in range(len(fr)))
        if what == "manifold file" and path.partition("@")[0] in SET_NAMES:
            raise InputError(
                f"{PLUGIN_NAME}: {what} '{path}' not found; '{path}' is a built-in database, not "
                f"a manifold: name a shipped manifold ({', '.join(SHIPPED)}), or fit one "
                f"(python3 tools/fit_manifold.py {path} --out {path.partition('@')[0]}.npz) and "
                "name that file"
            )
        raise InputError(f"{PLUGIN_NAME}: {what} '{path}' not found (searched {where})")
    return found


def _choice(props, key, default, modes):
    value = str(props.get(key, default)).strip().lower()
    if value not in modes:
        raise InputError(f"{PLUGIN_NAME}: {key} must be one of {modes}, got {value!r}")
    return value


def read_properties(props):
    """``(manifold, options)`` of a ``manifold_brdf``'s properties, or an ``InputError``
    naming the property.
    """
    if not mi.is_rgb or mi.is_polarized:
        raise InputError(
            f"{PLUGIN_NAME}: measured RGB tables need an RGB variant "
            f"(scalar_rgb, llvm_ad_rgb, cuda_ad_rgb), not {mi.variant()}"
        )
    if "manifold" not in props:
        raise InputError(
            f"{PLUGIN_NAME}: the 'manifold' parameter (path of a saved manifold) is required"
        )
    given = str(props["manifold"])
    if given in SHIPPED:  # the rule of manifold names, with the scene's folder searched too
        found = str(mi.file_resolver().resolve(given))
        if os.path.lexists(found):
            raise InputError(f"{PLUGIN_NAME}: {ambiguity(given, found)}")
        path = shipped_path(given)
    elif given.startswith(BUILTIN_PREFIX):
        path = resolve_manifold(given)
    else:
        path = resolve(given, "manifold file")
    try:
        manifold = Manifold.load(path)
    except InputError as e:
        raise InputError(f"{PLUGIN_NAME}: {e}") from None
    database = props["database"] if "database" in props else database_folder()
    database = resolve(database, "database folder") if database is not None else None
    if database is not None and not os.path.isdir(database):
        raise InputError(f"{PLUGIN_NAME}: database {database} is not a folder")
    if database is not None:  # this instance's own manifold reads every table from there
        manifold.database = os.path.abspath(database)  # a folder (even one named like a set)
    prune = props.get("prune", DEFAULT_PRUNE)
    try:
        prune = float(prune)
    except (TypeError, ValueError):
        raise InputError(
            f"{PLUGIN_NAME}: prune must be a number in [0, 1), got {prune!r}"
        ) from None
    if not 0.0 <= prune < 1.0:
        raise InputError(f"{PLUGIN_NAME}: prune must be in [0, 1), got {prune}")
    sampling = _choice(props, "sampling", "cdf", SAMPLING_MODES)
    interpolation = _choice(props, "interpolation", "nearest", INTERPOLATION_MODES)
    given = [k for k in CHOOSERS if k in props]
    if len(given) != 1:
        raise InputError(
            f"{PLUGIN_NAME}: give exactly one of 'x', 'material' and 'weights' (got {given or 'none'})"
        )
    return manifold, BRDFOptions(
        path, database, prune, sampling, interpolation, given[0], props[given[0]]
    )


def _checked_table(table):
    """The combined table as float32 ``(bins, 3)`` with negatives clamped; ``(packed, dims, n_clamped)``."""
    table = np.asarray(table, dtype=np.float32)
    if table.ndim != 4 or table.shape[0] != 3:
        raise InputError(
            f"{PLUGIN_NAME}: combined table has shape {table.shape}, expected (3, nh, nd, nphi)"
        )
    if not np.isfinite(table).all():
        raise InputError(f"{PLUGIN_NAME}: the combined table has NaN or Inf values")
    negative = table < 0
    n_clamped = int(negative.sum())
    if n_clamped:
        table = np.where(negative, np.float32(0), table)
    dims = tuple(int(d) for d in table.shape[1:])
    return np.ascontiguousarray(table.reshape(3, -1).T), dims, n_clamped  # (bins, 3): RGB together


def combine(manifold, options, w, x=None, material=None, table=None):
    """The :class:`Combination` of weights ``w`` (the material at latent point ``x``, or training
    material ``material``, when given). ``table``, when the caller already has the sum over the
    materials kept by pruning, is used instead of reading and adding the tables.
    """
    m = manifold
    try:
        if table is None:
            table, keep, dropped = m.combine(w, prune=options.prune, database=options.database)
        else:
            keep, _, dropped = m.prune(w, options.prune)
        db = (
            m.open_database(options.database, [m.names[i] for i in keep])
            if options.sampling == "cdf"
            else None
        )
    except (ValueError, KeyError, OSError) as e:  # InputError, damaged or missing files
        raise InputError(f"{PLUGIN_NAME}: {e}") from None
    packed, dims, n_clamped = _checked_table(table)
    distr, black = None, False
    if options.sampling == "cdf":
        dens = np.stack([material_density(db, m.names[i]) for i in keep])
        distr, black = combined_distribution(dens, np.asarray(w, dtype=np.float64)[keep])
    report = m.prune_report(
        np.asarray(w, dtype=np.float64), options.prune, keep=keep
    )  # pruned once
    return Combination(
        w=np.asarray(w, dtype=np.float64).copy(),
        x=None if x is None else np.asarray(x, dtype=np.float64).copy(),
        material=material,
        keep=np.asarray(keep),
        dropped=float(dropped),
        prune_error=report.cos_error,
        pruning=report,
        n_clamped=n_clamped,
        n_values=int(packed.size),
        black=black,
        dims=dims,
        distr=distr,
        table=mi.Float(packed.ravel()) if dr.is_jit_v(mi.Float) else packed,
    )
