"""Mitsuba ``measured`` files (``.bsdf``, RGL-EPFL ``tensor_file``) as MERL tables.

An isotropic measured BSDF is resampled on a MERL grid through Mitsuba's own ``measured``
plugin: at the centre of every bin above the horizon (``phi_h = 0``), ``f = eval(wi, wo) /
cos(theta_o)`` (the plugin's ``eval`` includes the cosine of the outgoing direction), per
linear-RGB channel. Anisotropic files are refused before Mitsuba reads them
(:meth:`~mitsuba_manifold.data.sources.MeasuredFile.check`).

Importing this module registers :func:`resample` as the reader of
:class:`~mitsuba_manifold.data.sources.MeasuredFile` sources, so that a database holding
``.bsdf`` files makes their tables (cached by content hash, :class:`~mitsuba_manifold.data.database.Database`).
"""

import os

import numpy as np

from ..data import merl
from ..data.sources import MeasuredFile, material_name, register_reader
from ..errors import FormatError, plugin_message

__all__ = ["resample", "evaluate", "load_measured"]

#: Direction pairs evaluated per call of the plugin.
BLOCK = 1 << 20
#: Sample points per axis of a bin (:func:`resample`).
SAMPLES = 2


def load_measured(path):
    """Mitsuba's ``measured`` BSDF of the file ``path`` in the active variant (an RGB one, see
    :func:`.scenes.use_variant`), after checking the file is an isotropic tensor file."""
    from .scenes import use_variant

    path = os.path.abspath(os.fspath(path))
    MeasuredFile(material_name(path), path).check()
    mi = use_variant()
    try:
        return mi.load_dict({"type": "measured", "filename": path})
    except Exception as e:   # Mitsuba raises RuntimeError with its own log text
        raise FormatError(f"{path}: Mitsuba's measured plugin cannot read it ({plugin_message(e)})") from None


def evaluate(bsdf, wi, wo, cosine=False):
    """BRDF values ``(m, 3)`` (1/sr) of a Mitsuba BSDF at local direction pairs ``(m, 3)``:
    ``eval(wi, wo) / cos(theta_o)`` (with ``cosine``: ``eval`` itself), 0 where either direction
    is below the surface."""
    import drjit as dr
    import mitsuba as mi

    wi = np.ascontiguousarray(wi, dtype=np.float32)
    wo = np.ascontiguousarray(wo, dtype=np.float32)
    out = np.zeros((len(wi), 3), dtype=np.float32)
    ctx = mi.BSDFContext()
    for s in range(0, len(wi), BLOCK):
        a, b = wi[s:s + BLOCK], wo[s:s + BLOCK]
        si = dr.zeros(mi.SurfaceInteraction3f, len(a))
        si.wi = mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        value = bsdf.eval(ctx, si, mi.Vector3f(b[:, 0], b[:, 1], b[:, 2]))
        out[s:s + BLOCK] = np.array(value, dtype=np.float32).reshape(3, -1).T
    cos_o = wo[:, 2]
    ok = (cos_o > 0) & (wi[:, 2] > 0)
    out[~ok] = 0.0
    if not cosine:
        out[ok] /= cos_o[ok, None]
    return np.maximum(out, 0.0)


def resample(path, dims=merl.MERL_DIMS, samples=SAMPLES):
    """Reflectance table ``(3,) + dims`` float32 of the measured file ``path`` (0 below the horizon).

    A bin's value is the ratio ``sum eval(wi, wo) / sum cos(theta_o)`` over ``samples^3``
    points spread evenly over the bin (in the grid's ``(sqrt(theta_h), theta_d, phi_d)``
    coordinates, ``phi_h = 0``): the BRDF whose cosine-weighted value, looked up in that
    bin, has the plugin's mean there. It stays finite where the bin's centre grazes the
    horizon (a ratio at one point would divide by a cosine near 0), and a sharp highlight
    narrower than a bin keeps its energy.
    """
    dims = tuple(int(v) for v in dims)
    bsdf = load_measured(path)
    above = merl.above_horizon(dims)
    idx = [g[above].astype(np.float64) for g in np.meshgrid(*(np.arange(n) for n in dims), indexing="ij")]
    num = np.zeros((int(above.sum()), 3), dtype=np.float64)
    den = np.zeros(int(above.sum()), dtype=np.float64)
    offsets = (np.arange(samples) + 0.5) / samples
    for a in offsets:
        th = ((idx[0] + a) / dims[0]) ** 2 * (np.pi / 2)
        for b in offsets:
            td = (idx[1] + b) / dims[1] * (np.pi / 2)
            for c in offsets:
                pd = (idx[2] + c) / dims[2] * np.pi
                wi, wo = merl.directions(th, td, pd)
                num += evaluate(bsdf, wi, wo, cosine=True)
                den += np.where((wi[:, 2] > 0) & (wo[:, 2] > 0), np.maximum(wo[:, 2], 0.0), 0.0)
    values = np.where(den[:, None] > 0, num / np.where(den > 0, den, 1.0)[:, None], 0.0)
    if not np.isfinite(values).all():
        raise FormatError(f"{path}: Mitsuba's measured plugin gave NaN or Inf values")
    out = np.zeros((3,) + dims, dtype=np.float32)
    out[:, above] = values.T
    return out


register_reader(MeasuredFile.kind, resample)
