"""Tabulated importance sampling of measured tables (paper Sec. 5.3).

Every measured material has, for a grid of incident elevations, a tabulated
unnormalised density of outgoing directions over the half-vector parameterisation
(cached beside the database, keyed by the table's content hash). By linearity the
density of an affine combination is ``sum_i w_i P_i``, clamped at 0
(:func:`combined_density`), which ``manifold_brdf`` samples with Mitsuba's
``MarginalContinuous2D1`` (:func:`sample_half_vector`, :func:`half_vector_pdf`).
"""

import functools
import os

import drjit as dr
import mitsuba as mi
import numpy as np

from ..._util.cache import npy_cache
from ...data import merl

PLUGIN_NAME = "manifold_brdf"


def prefixed(error, suffix=""):
    """``error``'s message led by the plugin's name once (a nested plugin error already has it)."""
    text = str(error)
    return (text if text.startswith(PLUGIN_NAME + ":") else f"{PLUGIN_NAME}: {text}") + suffix


#: Sampling grid: incident elevations, half-vector azimuth vertices (over [0, pi]),
#: half-vector elevation vertices (uniform in ``u = sqrt(theta_h / (pi/2))``), and
#: sub-samples per axis averaged into each vertex.
SAMPLING_GRID = (32, 33, 65, 4)
#: Version of the cached sampling densities (bump when their definition changes).
SAMPLING_CACHE_VERSION = 2

_HALF_PI = 0.5 * np.pi


@functools.lru_cache(maxsize=4)
def _sampling_geometry(dims, grid=SAMPLING_GRID):
    """Bins and weights turning a table into its sampling densities.

    For each incident elevation ``theta_i`` (``wi`` in the xz plane) and grid vertex
    ``(v, u)``, ``s*s`` sub-samples of the half vector ``h`` (``theta_h = u^2 pi/2``,
    azimuth ``v pi``) spread over the vertex's cell: their MERL bin (of ``wo``, ``wi``
    reflected about ``h``) and weight ``cos(theta_o) J / s^2`` (0 below the horizon),
    where ``J = |d wo / d(u, v)|`` is taken at the vertex itself so that the density
    vanishes on the ``u = 0`` edge (the mirror direction) as the true one does.

    Returns
    -------
    theta_i : ndarray (n_t,)
    index : ndarray int32 (n_t, n_v, n_u, s*s)
    weight : ndarray float32 (n_t, n_v, n_u, s*s)
    """
    n_t, n_v, n_u, s = grid
    theta_i = np.linspace(0.0, _HALF_PI, n_t)
    off = (np.arange(s) + 0.5) / s - 0.5
    u = np.clip(np.arange(n_u)[:, None] / (n_u - 1) + off / (n_u - 1), 0.0, 1.0)  # (n_u, s)
    v = np.clip(np.arange(n_v)[:, None] / (n_v - 1) + off / (n_v - 1), 0.0, 1.0)  # (n_v, s)
    ti = theta_i[:, None, None, None, None]
    uu = u[None, None, None, :, :]
    vv = v[None, :, :, None, None]
    shape = (n_t, n_v, s, n_u, s)
    theta_h = np.broadcast_to(uu * uu * _HALF_PI, shape)
    phi = np.broadcast_to(vv * np.pi, shape)
    wi = np.stack(np.broadcast_arrays(np.sin(ti), 0.0 * ti, np.cos(ti)), axis=-1)
    wi = np.broadcast_to(wi, shape + (3,))
    h = np.stack(
        [np.sin(theta_h) * np.cos(phi), np.sin(theta_h) * np.sin(phi), np.cos(theta_h)], axis=-1
    )
    cos_d = np.sum(wi * h, axis=-1)
    wo = 2.0 * cos_d[..., None] * h - wi
    valid = (wi[..., 2] > 0) & (wo[..., 2] > 1e-9) & (cos_d > 0)
    u_vertex = np.arange(n_u) / (n_u - 1)
    theta_v = u_vertex * u_vertex * _HALF_PI
    jac = np.broadcast_to((np.sin(theta_v) * u_vertex)[None, None, None, :, None], shape)
    jac = 4.0 * cos_d * jac * np.pi * np.pi
    weight = np.where(valid, wo[..., 2] * jac, 0.0) / (s * s)
    wo_safe = np.where(valid[..., None], wo, np.array([0.0, 0.0, 1.0]))
    wi_safe = np.where(valid[..., None], wi, np.array([0.0, 0.0, 1.0]))
    index = np.where(valid, merl.flat_index(wi_safe, wo_safe, dims), 0)
    order = (0, 1, 3, 2, 4)
    index = index.transpose(order).reshape(n_t, n_v, n_u, s * s).astype(np.int32)
    weight = weight.transpose(order).reshape(n_t, n_v, n_u, s * s).astype(np.float32)
    return theta_i, index, weight


def sampling_density(table, grid=SAMPLING_GRID):
    """Unnormalised sampling density of one table, float32 ``(n_t, n_v, n_u)``.

    The channel mean of ``f(wi, wo) cos(theta_o)`` times the Jacobian of the half-vector
    parameterisation, averaged over each vertex's neighbourhood; linear in ``table``.
    """
    table = np.asarray(table)
    _, index, weight = _sampling_geometry(tuple(table.shape[1:]), tuple(grid))
    mean = table.reshape(3, -1).mean(axis=0, dtype=np.float32)
    return np.einsum("tvus,tvus->tvu", mean[index], weight, dtype=np.float32)


def sampling_cache_path(database, name, grid=SAMPLING_GRID):
    """Cache file of a material's sampling density (keyed by the table's content hash)."""
    tag = f"v{SAMPLING_CACHE_VERSION}-{grid[0]}x{grid[1]}x{grid[2]}s{grid[3]}"
    return os.path.join(database.cache_dir, f"{database.hash(name)}.sampling-{tag}.npy")


def material_density(database, name, grid=SAMPLING_GRID, use_cache=True):
    """Sampling density of one material of ``database``, read from or written to the cache.

    A cache file of the wrong shape or with bad values is recomputed and replaced.
    """
    if not use_cache:
        return sampling_density(database.reflectance(name), grid)

    def warn(path, why):
        mi.Log(mi.LogLevel.Warn, f"{PLUGIN_NAME}: sampling cache {path}: {why}; making it again")

    return npy_cache(
        sampling_cache_path(database, name, grid),
        lambda: sampling_density(database.reflectance(name), grid),
        shape=tuple(grid[:3]),
        dtype=np.float32,
        finite=True,
        on_rebuild=warn,
    )


def combined_density(densities, weights, grid=SAMPLING_GRID):
    """``max(0, sum_i w_i P_i)`` with every incident slice usable by the sampler.

    A slice with no mass (always the one at grazing incidence, ``theta_i = pi/2``)
    takes the values of the nearest slice that has some; if none has (a black
    material), every slice becomes uniform in the half vector's solid angle. Either
    way the density vanishes at ``u = 0``, so that the solid-angle pdf grows no faster
    than ``1 / theta_h`` towards the mirror direction.

    Returns
    -------
    density : ndarray float32 (n_t, n_v, n_u)
    empty : int
        Number of slices that had no mass.
    """
    p = np.tensordot(
        np.asarray(weights, dtype=np.float64), np.asarray(densities, dtype=np.float64), axes=1
    )
    p = np.maximum(p, 0.0)
    good = np.flatnonzero(p.sum(axis=(1, 2)) > 0)
    empty = p.shape[0] - good.size
    if good.size == 0:
        u = np.arange(grid[2]) / (grid[2] - 1)
        p[:] = (np.sin(u * u * _HALF_PI) * u)[None, None, :]
    elif empty:
        for k in range(p.shape[0]):
            nearest = good[np.argmin(np.abs(good - k))]
            if nearest != k:
                p[k] = p[nearest]
    return p.astype(np.float32), int(empty)


def combined_distribution(densities, weights, grid=SAMPLING_GRID):
    """``(MarginalContinuous2D1 over (u, v) conditioned on theta_i, black)`` sampling
    :func:`combined_density` of ``densities`` (n, n_t, n_v, n_u) with ``weights`` (n,);
    ``black``: no slice had mass (the material reflects nothing).
    """
    p, n_empty = combined_density(densities, weights, grid)
    theta_grid = np.linspace(0.0, _HALF_PI, grid[0])
    return mi.MarginalContinuous2D1(p, [theta_grid.tolist()], normalize=True), n_empty == p.shape[0]


# ------------------------------------------------------------------ the density in Dr.Jit

#: Smallest ``u = sqrt(theta_h / (pi/2))`` at which the solid-angle pdf is evaluated.
U_FLOOR = 1e-4
_SIN_FLOOR = float(np.sin(U_FLOOR**2 * _HALF_PI))


def per_solid_angle(p_uv, u, sin_th, cos_d, active):
    """Density over ``(u, v)`` to density over ``wo``: divide by ``|d wo / d(u, v)|``.

    ``wo = reflect(wi, h)`` gives ``d wo = 4 cos_d d h``, ``d h = sin_th d theta_h d phi``,
    ``theta_h = u^2 pi/2`` and ``phi = +-v pi`` (each sign with probability 1/2):
    ``|d wo / d(u, v)| = 8 pi^2 cos_d sin_th u``. The density grows like 1/theta_h
    towards the mirror direction, and single precision rounds directions within
    ~1e-7 of it onto it (u = 0): those are evaluated at a tiny ``u`` instead of
    letting the Jacobian vanish (which would drop the tabulated part).
    """
    near = u < U_FLOOR
    u = dr.maximum(u, U_FLOOR)
    sin_th = dr.select(near, _SIN_FLOOR, sin_th)
    jac = (8.0 * np.pi * np.pi) * cos_d * sin_th * u
    ok = active & (jac > 0)
    return dr.select(ok, p_uv / dr.select(ok, jac, 1.0), 0.0)


def incident_frame(wi):
    """Unit azimuth ``(ex, ey)`` of ``wi`` (x axis at normal incidence) and its elevation."""
    r = dr.sqrt(dr.square(wi.x) + dr.square(wi.y))
    has = r > 0
    inv_r = dr.select(has, dr.rcp(dr.select(has, r, 1.0)), 0.0)
    ex = dr.select(has, wi.x * inv_r, 1.0)
    ey = dr.select(has, wi.y * inv_r, 0.0)
    return ex, ey, dr.atan2(r, wi.z)


def half_vector_pdf(distr, wi, wo, active):
    """Density (solid angle) at ``wo`` of sampling the half vector from ``distr`` (a
    ``MarginalContinuous2D1`` over ``(u, v)``, conditioned on the incident elevation).
    """
    h = wi + wo
    rh = dr.sqrt(dr.square(h.x) + dr.square(h.y))
    inv_len = dr.rsqrt(dr.square(rh) + dr.square(h.z))
    u = dr.sqrt(dr.atan2(rh, h.z) * (1.0 / _HALF_PI))
    ex, ey, theta_i = incident_frame(wi)
    v = dr.abs(dr.atan2(ex * h.y - ey * h.x, ex * h.x + ey * h.y)) * (1.0 / np.pi)
    p_uv = distr.eval(mi.Point2f(dr.maximum(u, U_FLOOR), v), [theta_i], active)
    return per_solid_angle(p_uv, u, rh * inv_len, dr.dot(wi, h) * inv_len, active)


def sample_half_vector(distr, wi, sample2, flip, active):
    """``(wo, pdf)``: a half vector ``h`` drawn from ``distr`` over ``(u, v)``, its azimuth sign
    ``-`` where ``flip``, and ``wo`` the reflection of ``wi`` about it, with the solid-angle
    density of that strategy.
    """
    ex, ey, theta_i = incident_frame(wi)
    uv, p_uv = distr.sample(sample2, [theta_i], active)
    theta_h = dr.square(uv.x) * _HALF_PI
    phi = dr.select(flip, -uv.y, uv.y) * np.pi
    sin_th, cos_th = dr.sincos(theta_h)
    sin_p, cos_p = dr.sincos(phi)
    hx, hy = sin_th * cos_p, sin_th * sin_p
    h = mi.Vector3f(ex * hx - ey * hy, ey * hx + ex * hy, cos_th)
    return mi.reflect(wi, h), per_solid_angle(p_uv, uv.x, sin_th, dr.dot(wi, h), active)
