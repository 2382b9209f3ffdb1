"""MERL half/diff bin lookups of direction pairs in Dr.Jit (the BSDF's and the one-pass
renderer's table indexing; :mod:`merl` holds the NumPy versions), and table values at them.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

HALF_PI = 0.5 * np.pi


def merl_angles(wi, wo):
    """Rusinkiewicz angles ``(theta_h, theta_d, phi_d)`` of direction pairs, in Dr.Jit.

    The same mapping as :func:`merl.half_diff` (``phi_d`` folded to ``[0, pi)``),
    written with ``atan2`` so that small angles keep full single precision: the first
    MERL ``theta_h`` bin is 2e-4 rad wide, below what ``acos`` resolves in float32.
    Works on scalar and JIT Mitsuba types.
    """
    h = wi + wo
    rh = dr.sqrt(dr.square(h.x) + dr.square(h.y))
    theta_h = dr.atan2(rh, h.z)
    inv_len = dr.rsqrt(dr.square(rh) + dr.square(h.z))
    # Frame of the half vector: rotate by -phi_h about z, then by -theta_h about y.
    has_az = rh > 0
    inv_rh = dr.select(has_az, dr.rcp(dr.select(has_az, rh, 1.0)), 0.0)
    cos_ph = dr.select(has_az, h.x * inv_rh, 1.0)
    sin_ph = dr.select(has_az, h.y * inv_rh, 0.0)
    cos_th = h.z * inv_len
    sin_th = rh * inv_len
    dx = (wi.x * cos_ph + wi.y * sin_ph) * cos_th - wi.z * sin_th
    dy = wi.y * cos_ph - wi.x * sin_ph
    dz = (wi.x * cos_ph + wi.y * sin_ph) * sin_th + wi.z * cos_th
    theta_d = dr.atan2(dr.sqrt(dr.square(dx) + dr.square(dy)), dz)
    phi_d = dr.atan2(dy, dx)
    phi_d = dr.select(phi_d < 0, phi_d + dr.pi, phi_d)
    phi_d = dr.select(phi_d >= dr.pi, phi_d - dr.pi, phi_d)
    return theta_h, theta_d, phi_d


def _clamp_index(c, n):
    return dr.clip(mi.Int32(dr.floor(c)), 0, n - 1)


def merl_bin(theta_h, theta_d, phi_d, dims):
    """Flat MERL bin index (as :func:`merl.flat_index`) of Rusinkiewicz angles, in Dr.Jit."""
    n_h, n_d, n_p = dims
    th = dr.clip(theta_h, 0.0, HALF_PI)
    i_h = _clamp_index(dr.sqrt(th * (1.0 / HALF_PI)) * n_h, n_h)
    i_d = _clamp_index(theta_d * (n_d / HALF_PI), n_d)
    i_p = _clamp_index(phi_d * (n_p / np.pi), n_p)
    return mi.UInt32((i_h * n_d + i_d) * n_p + i_p)


def linear_axis(c, n):
    """Neighbouring bins and weight of the upper one along a clamped axis."""
    c = dr.clip(c - 0.5, 0.0, float(n - 1))
    i0 = dr.minimum(mi.Int32(dr.floor(c)), n - 1)
    t = c - mi.Float(i0)
    return i0, dr.minimum(i0 + 1, n - 1), t


def gather_rgb(table, idx, active):
    """RGB of bins ``idx`` of a packed table: a Dr.Jit array of ``(bins, 3)`` floats in JIT
    variants, a NumPy ``(bins, 3)`` array in scalar ones.
    """
    if dr.is_jit_v(mi.Float):
        return dr.gather(mi.Color3f, table, idx, active)
    if not active:
        return mi.Color3f(0.0)
    r, g, b = table[int(idx)]
    return mi.Color3f(float(r), float(g), float(b))


def table_value(table, dims, interpolation, wi, wo, active, gather=gather_rgb):
    """Table value ``f(wi, wo)`` (no cosine) of a packed table (:func:`gather_rgb`) of MERL
    ``dims``: the bin of the pair (``"nearest"``) or trilinear interpolation between bin centres
    (``"linear"``, periodic in ``phi_d`` over ``pi``). ``gather(table, idx, active)`` reads the
    bins (:func:`.ad.mixture_gather`: a weighted sum of several tables).
    """
    n_h, n_d, n_p = dims
    theta_h, theta_d, phi_d = merl_angles(wi, wo)
    if interpolation == "nearest":
        return gather(table, merl_bin(theta_h, theta_d, phi_d, dims), active)
    th = dr.clip(theta_h, 0.0, HALF_PI)
    h0, h1, th_t = linear_axis(dr.sqrt(th * (1.0 / HALF_PI)) * n_h, n_h)
    d0, d1, td_t = linear_axis(theta_d * (n_d / HALF_PI), n_d)
    c = phi_d * (n_p / np.pi) - 0.5
    fc = dr.floor(c)
    tp_t = c - fc
    p0 = mi.Int32(fc)
    p0 = dr.select(p0 < 0, p0 + n_p, p0)
    p1 = p0 + 1
    p1 = dr.select(p1 >= n_p, p1 - n_p, p1)
    result = mi.Color3f(0.0)
    for ih, wh in ((h0, 1.0 - th_t), (h1, th_t)):
        for id_, wd in ((d0, 1.0 - td_t), (d1, td_t)):
            for ip, wp in ((p0, 1.0 - tp_t), (p1, tp_t)):
                idx = mi.UInt32((ih * n_d + id_) * n_p + ip)
                result += gather(table, idx, active) * (wh * wd * wp)
    return result
