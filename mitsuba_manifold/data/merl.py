"""The MERL ``.binary`` BRDF format and its half/diff (Rusinkiewicz) bin mapping.

A MERL file holds three int32 dimensions ``(n_theta_h, n_theta_d, n_phi_d)`` (90, 90,
180 for the MERL database), then three float64 blocks R, G, B of ``prod(dims)`` values
each, ``phi_d`` varying fastest. Stored values times :data:`SCALE` give reflectance
(1/sr); a negative stored value means "not measured".

Tables are handled as arrays of shape ``(3, n_theta_h, n_theta_d, n_phi_d)``.
Bin indexing follows MERL's reference code: ``theta_h`` bins are uniform in
``sqrt(theta_h / (pi/2))``, ``theta_d`` bins are linear, ``phi_d`` is folded to
``[0, pi)`` by reciprocity; indices are clamped to range.
"""

from __future__ import annotations

import math
import os

import numpy as np

from .._util import checks
from .._util.atomic import atomic_write
from ..errors import FormatError, InputError

MERL_DIMS = (90, 90, 180)
#: Stored value -> reflectance, per channel (MERL's RED/GREEN/BLUE_SCALE).
SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])
#: Value written for bins that were not measured.
NOT_MEASURED = -1.0

_HEADER = np.dtype("<i4")
_VALUES = np.dtype("<f8")
MAX_BINS = 1 << 28  # far above MERL's 1.46M bins; guards against garbage headers


# --------------------------------------------------------------------------- I/O


def table_names(folder) -> list:
    """Names of the MERL tables in ``folder`` (``<name>.binary``), sorted; hidden files, among
    them the temporaries of writers (:func:`~mitsuba_manifold._util.atomic.is_temporary`), skipped.
    """
    return sorted(
        f[:-7] for f in os.listdir(folder) if f.endswith(".binary") and not f.startswith(".")
    )


def read_header(path) -> tuple[int, ...]:
    """Dimensions ``(n_theta_h, n_theta_d, n_phi_d)`` from a file's header, validated.

    Raises
    ------
    FormatError
        If the file is too short, the dimensions are not positive or do not match the size.
    """
    path = os.fspath(path)
    size = os.path.getsize(path)
    if size < 12:
        raise FormatError(f"{path}: not a MERL .binary file ({size} bytes, header needs 12)")
    with open(path, "rb") as f:
        dims = tuple(int(v) for v in np.frombuffer(f.read(12), dtype=_HEADER))
    n = dims[0] * dims[1] * dims[2]
    if min(dims) <= 0 or n > MAX_BINS:
        raise FormatError(f"{path}: not a MERL .binary file (header dimensions {dims})")
    expected = 12 + 3 * n * _VALUES.itemsize
    if size != expected:
        what = "truncated" if size < expected else "has trailing data"
        raise FormatError(
            f"{path}: {what}: header says {dims[0]}x{dims[1]}x{dims[2]} bins "
            f"({expected} bytes) but the file has {size} bytes"
        )
    return dims


def resolution_mismatch(dims, show=5) -> str:
    """Why tables of resolutions ``dims`` ({name: (n_theta_h, n_theta_d, n_phi_d)}) cannot go
    together, naming the files ``<name>.binary`` that differ from the most common resolution
    (every group when no resolution is the most common).
    """
    groups: dict = {}
    for name, d in dims.items():
        groups.setdefault(tuple(d), []).append(name + ".binary")
    ranked = sorted(groups.items(), key=lambda kv: -len(kv[1]))

    def files(names) -> str:
        return ", ".join(names[:show]) + (
            f" and {len(names) - show} more" if len(names) > show else ""
        )

    def size(d) -> str:
        return "x".join(map(str, d))

    (common, members), rest = ranked[0], ranked[1:]
    if len(members) > len(rest[0][1]):
        odd = "; ".join(f"{files(n)} {'is' if len(n) == 1 else 'are'} {size(d)}" for d, n in rest)
        return (
            f"tables have different resolutions: {len(members)} are {size(common)}, but {odd}; "
            f"remove the odd file(s) out or remake them at {size(common)}"
        )
    return (
        "tables have different resolutions: "
        + "; ".join(f"{size(d)}: {files(n)}" for d, n in ranked)
        + "; keep tables of one resolution only"
    )


def read_binary(path) -> np.ndarray:
    """Stored values of a MERL file, float64, shape ``(3, n_theta_h, n_theta_d, n_phi_d)``.

    Values are as stored (multiply by :data:`SCALE` for reflectance, see
    :func:`reflectance`); negative values mark unmeasured bins.

    Raises
    ------
    FormatError
        Truncated file, header/size mismatch, non-MERL file, NaN or Inf values.
    """
    path = os.fspath(path)
    dims = read_header(path)
    raw = np.fromfile(path, dtype=_VALUES, offset=12).reshape((3,) + dims)
    bad = ~np.isfinite(raw)
    if bad.any():
        raise FormatError(f"{path}: {int(bad.sum())} values are NaN or Inf")
    return raw.astype(np.float64, copy=False)


def write_binary(path, raw) -> None:
    """Write stored values ``raw`` (shape ``(3, nh, nd, nphi)``) as a MERL file, atomically."""
    raw = np.asarray(raw, dtype=np.float64)
    if raw.ndim != 4 or raw.shape[0] != 3:
        raise FormatError(
            f"{path}: MERL table must have shape (3, n_theta_h, n_theta_d, n_phi_d), got {raw.shape}"
        )
    if not np.isfinite(raw).all():
        raise FormatError(f"{path}: refusing to write NaN or Inf values")
    header = np.array(raw.shape[1:], dtype=_HEADER)

    def write(f) -> None:
        f.write(header.tobytes())
        f.write(np.ascontiguousarray(raw, dtype=_VALUES).tobytes())

    atomic_write(path, write)


def reflectance(raw, dtype=np.float32) -> np.ndarray:
    """Stored values to reflectance (1/sr); unmeasured bins stay negative."""
    raw = np.asarray(raw)
    return (raw * SCALE.reshape(3, 1, 1, 1)).astype(dtype, copy=False)


def to_stored(refl) -> np.ndarray:
    """Reflectance to stored values (the inverse of :func:`reflectance`)."""
    return np.asarray(refl, dtype=np.float64) / SCALE.reshape(3, 1, 1, 1)


# ------------------------------------------------------------- half/diff mapping


def _rotate(v, axis, angle) -> np.ndarray:
    """Rotate vectors ``v`` (..., 3) about the z (axis=2) or y (axis=1) axis by ``angle``."""
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    if axis == 2:
        return np.stack([c * x - s * y, s * x + c * y, z], axis=-1)
    return np.stack([c * x + s * z, y, c * z - s * x], axis=-1)


def half_diff(wi, wo) -> tuple:
    """Rusinkiewicz coordinates of direction pairs in the local frame (normal = +z).

    Parameters
    ----------
    wi, wo : array_like, shape (..., 3)
        Unit directions.

    Returns
    -------
    theta_h, theta_d, phi_d : ndarray
        Half-vector elevation, difference elevation and difference azimuth in ``(-pi, pi]``.
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    theta_h = np.arccos(np.clip(h[..., 2], -1.0, 1.0))
    phi_h = np.arctan2(h[..., 1], h[..., 0])
    d = _rotate(_rotate(wi, 2, -phi_h), 1, -theta_h)
    theta_d = np.arccos(np.clip(d[..., 2], -1.0, 1.0))
    phi_d = np.arctan2(d[..., 1], d[..., 0])
    return theta_h, theta_d, phi_d


def directions(theta_h, theta_d, phi_d, phi_h=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`half_diff`: unit ``wi, wo`` (..., 3) for Rusinkiewicz coordinates."""
    theta_h, theta_d, phi_d, phi_h = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (theta_h, theta_d, phi_d, phi_h))
    )
    st = np.sin(theta_d)
    d = np.stack([st * np.cos(phi_d), st * np.sin(phi_d), np.cos(theta_d)], axis=-1)
    d_out = d * np.array([-1.0, -1.0, 1.0])
    wi = _rotate(_rotate(d, 1, theta_h), 2, phi_h)
    wo = _rotate(_rotate(d_out, 1, theta_h), 2, phi_h)
    return wi, wo


def bin_index(theta_h, theta_d, phi_d, dims=MERL_DIMS) -> tuple:
    """MERL bin indices ``(i_h, i_d, i_phi)`` for Rusinkiewicz coordinates (clamped)."""
    n_h, n_d, n_p = dims
    th = np.clip(np.asarray(theta_h, dtype=np.float64), 0.0, np.pi / 2)
    i_h = np.floor(np.sqrt(th / (np.pi / 2)) * n_h)
    i_d = np.floor(np.asarray(theta_d, dtype=np.float64) / (np.pi / 2) * n_d)
    p = np.mod(np.asarray(phi_d, dtype=np.float64), np.pi)
    i_p = np.floor(p / np.pi * n_p)
    return (
        np.clip(i_h, 0, n_h - 1).astype(np.int64),
        np.clip(i_d, 0, n_d - 1).astype(np.int64),
        np.clip(i_p, 0, n_p - 1).astype(np.int64),
    )


def flat_index(wi, wo, dims=MERL_DIMS) -> np.ndarray:
    """Flat bin index (into one channel of a table) for direction pairs."""
    i_h, i_d, i_p = bin_index(*half_diff(wi, wo), dims=dims)
    return (i_h * dims[1] + i_d) * dims[2] + i_p


def bin_centres(dims=MERL_DIMS) -> tuple:
    """Rusinkiewicz coordinates of bin centres, each of shape ``dims``."""
    n_h, n_d, n_p = dims
    th = ((np.arange(n_h) + 0.5) / n_h) ** 2 * (np.pi / 2)
    td = (np.arange(n_d) + 0.5) / n_d * (np.pi / 2)
    pd = (np.arange(n_p) + 0.5) / n_p * np.pi
    return np.meshgrid(th, td, pd, indexing="ij")


def above_horizon(dims=MERL_DIMS) -> np.ndarray:
    """Boolean mask, shape ``dims``: both directions of the bin centre lie above the surface.

    Elevations do not depend on ``phi_h`` (a rotation about the normal), so the
    test at ``phi_h = 0`` holds for every configuration that maps to the centre.
    """
    th, td, pd = bin_centres(dims)
    a = np.cos(th) * np.cos(td)
    b = np.sin(th) * np.sin(td) * np.abs(np.cos(pd))
    return a - b > 0.0


def filled_reflectance(raw, dtype=np.float32) -> np.ndarray:
    """Reflectance with every bin defined, the convention shared by the fit and the plugin.

    Bins below the horizon (see :func:`above_horizon`) are 0. Unmeasured bins above the
    horizon (real MERL files miss some near grazing angles) take the value of the
    nearest measured bin in index space, per channel.

    Raises
    ------
    ValueError
        If a channel has no measured bin above the horizon.
    """
    from scipy import ndimage

    refl = reflectance(raw, dtype=np.float64)
    above = above_horizon(refl.shape[1:])
    out = np.empty(refl.shape, dtype=dtype)
    for c in range(3):
        missing = (refl[c] < 0) & above
        if missing.any():
            usable = (refl[c] >= 0) & above
            if not usable.any():
                raise FormatError(f"channel {'RGB'[c]} has no measured bin above the horizon")
            _, idx = ndimage.distance_transform_edt(~usable, return_indices=True)
            channel = refl[c][tuple(idx)]
        else:
            channel = refl[c]
        out[c] = np.where(above, np.maximum(channel, 0.0), 0.0)
    return out


def table_resolution(dims, name="`dims`", bytes_per_bin=None, workers=1) -> tuple[int, int, int]:
    """MERL dimensions ``(n_theta_h, n_theta_d, n_phi_d)``, readable by this package and small
    enough to tabulate in the memory available.

    ``bytes_per_bin``: peak memory of one worker per bin (default: that of the SGD tabulation).
    """
    try:
        dims = tuple(int(v) for v in dims)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be three positive integers, got {dims!r}") from None
    if len(dims) != 3 or min(dims) < 1:
        raise InputError(f"{name} must be three positive integers like 90,90,180, got {dims}")
    bins = math.prod(dims)
    if bins > MAX_BINS:
        raise InputError(
            f"{name} {'x'.join(map(str, dims))} has {bins:.3g} bins; MERL files of more than "
            f"{MAX_BINS:.3g} bins (MERL itself: 1.46e6) are not read by this package"
        )
    # SGD tabulation peaks at about 200 bytes per bin; twice that leaves room for the writer's copy.
    per_bin = 400 if bytes_per_bin is None else bytes_per_bin
    checks.fits_in_memory(
        name,
        bins * per_bin * max(1, workers),
        f"tabulating {'x'.join(map(str, dims))} tables ({max(1, workers)} at a time)",
    )
    return dims
