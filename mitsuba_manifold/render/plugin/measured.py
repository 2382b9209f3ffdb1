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

from ...data import merl, sources
from ...data.sources import MeasuredFile, material_name, register_reader
from ...errors import FormatError, plugin_message

__all__ = ["evaluate", "load_measured", "resample"]

#: Direction pairs evaluated per call of the plugin.
BLOCK = 1 << 20


def load_measured(path):
    """Mitsuba's ``measured`` BSDF of the file ``path`` in the active variant (an RGB one, see
    :func:`.scenes.use_variant`), after checking the file is an isotropic tensor file.
    """
    from ..scene.variants import use_variant

    path = os.path.abspath(os.fspath(path))
    MeasuredFile(material_name(path), path).check()
    mi = use_variant()
    try:
        return mi.load_dict({"type": "measured", "filename": path})
    except RuntimeError as e:  # Mitsuba raises RuntimeError with its own log text
        raise FormatError(
            f"{path}: Mitsuba's measured plugin cannot read it ({plugin_message(e)})"
        ) from None


def evaluate(bsdf, wi, wo, cosine=False):
    """BRDF values ``(m, 3)`` (1/sr) of a Mitsuba BSDF at local direction pairs ``(m, 3)``:
    ``eval(wi, wo) / cos(theta_o)`` (with ``cosine``: ``eval`` itself), 0 where either direction
    is below the surface.
    """
    import drjit as dr
    import mitsuba as mi

    wi = np.ascontiguousarray(wi, dtype=np.float32)
    wo = np.ascontiguousarray(wo, dtype=np.float32)
    out = np.zeros((len(wi), 3), dtype=np.float32)
    ctx = mi.BSDFContext()
    for s in range(0, len(wi), BLOCK):
        a, b = wi[s : s + BLOCK], wo[s : s + BLOCK]
        si = dr.zeros(mi.SurfaceInteraction3f, len(a))
        si.wi = mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        value = bsdf.eval(ctx, si, mi.Vector3f(b[:, 0], b[:, 1], b[:, 2]))
        out[s : s + BLOCK] = np.array(value, dtype=np.float32).reshape(3, -1).T
    cos_o = wo[:, 2]
    ok = (cos_o > 0) & (wi[:, 2] > 0)
    out[~ok] = 0.0
    if not cosine:
        out[ok] /= cos_o[ok, None]
    return np.maximum(out, 0.0)


def resample(path, dims=merl.MERL_DIMS, samples=None):
    """Reflectance table ``(3,) + dims`` float32 of the measured file ``path`` (0 below the horizon).

    A bin's value is the ratio ``sum eval(wi, wo) / sum cos(theta_o)`` over ``samples^3`` points
    spread evenly over the bin (in the grid's ``(sqrt(theta_h), theta_d, phi_d)`` coordinates,
    ``phi_h = 0``; default :data:`~mitsuba_manifold.data.sources.MEASURED_SAMPLES`): the BRDF whose
    cosine-weighted value, looked up in that bin, has the plugin's mean there. It stays finite
    where the bin's centre grazes the horizon (a ratio at one point would divide by a cosine near
    0), and a sharp highlight narrower than a bin keeps its energy.
    """
    dims = tuple(int(v) for v in dims)
    samples = sources.MEASURED_SAMPLES if samples is None else int(samples)
    bsdf = load_measured(path)
    above = merl.above_horizon(dims)
    idx = [
        g[above].astype(np.float64)
        for g in np.meshgrid(*(np.arange(n) for n in dims), indexing="ij")
    ]
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


# ------------------------------------------------------------------- fidelity


def _sphere_scene(bsdf, res, spp, seed):
    """The shipped sphere scene (sky map and point light, :file:`scenes/sphere.xml`) as a dict
    with ``bsdf`` on the sphere; the sphere sees nothing but the lights.
    """
    from ..scene.files import scene_path

    sky = os.path.join(os.path.dirname(scene_path("sphere")), "sky.exr")
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": {
            "type": "perspective",
            "fov": 32,
            "to_world": _lookat(),
            "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
            "film": {
                "type": "hdrfilm",
                "width": res,
                "height": res,
                "pixel_format": "rgb",
                "rfilter": {"type": "box"},
            },
        },
        "object": {"type": "sphere", "center": [0, 0, 0], "radius": 1.0, "bsdf": bsdf},
        "sky": {"type": "envmap", "filename": sky},
        "lamp": {
            "type": "point",
            "position": [-3, 4, 3],
            "intensity": {"type": "rgb", "value": [20, 20, 20]},
        },
    }


def _lookat():
    import mitsuba as mi

    return mi.ScalarTransform4f().look_at(origin=[0, 0.6, 5], target=[0, 0, 0], up=[0, 1, 0])


def fidelity(path, manifold, name=None, res=64, spp=256, seed=0, interpolation="nearest"):
    """How a material imported from the measured file ``path`` renders against the file itself.

    Renders the sphere scene (:func:`_sphere_scene`) with Mitsuba's ``measured`` plugin twice
    (seeds ``seed`` and ``seed + 1``) and with ``manifold_brdf`` showing the material ``name``
    (default: named after the file) of the saved ``manifold`` once (seed ``seed + 2``), with
    its table looked up by ``interpolation``.

    Returns
    -------
    dict
        ``mean_ratio``: mean of the ``manifold_brdf`` image over the first ``measured`` one;
        ``rel_mse``: its relative MSE against that image; ``noise_rel_mse``: the relative MSE
        of the second ``measured`` render against the first (the noise of one render);
        ``ratio_to_noise``: ``rel_mse / noise_rel_mse``.
    """
    from ...imaging.metrics import rel_mse
    from ..scene.variants import use_variant

    mi = use_variant()
    path = os.path.abspath(os.fspath(path))
    name = name or material_name(path)
    measured = {"type": "measured", "filename": path}
    ours = {
        "type": "manifold_brdf",
        "manifold": os.path.abspath(os.fspath(manifold)),
        "material": name,
        "interpolation": interpolation,
    }

    def render(bsdf, s):
        scene = mi.load_dict(_sphere_scene(bsdf, res, spp, s))
        return np.array(mi.render(scene, spp=spp, seed=s), dtype=np.float64)

    ref, again, image = render(measured, seed), render(measured, seed + 1), render(ours, seed + 2)
    noise, err = rel_mse(again, ref), rel_mse(image, ref)
    return {
        "material": name,
        "res": res,
        "spp": spp,
        "mean_ratio": float(image.mean() / ref.mean()),
        "rel_mse": err,
        "noise_rel_mse": noise,
        "ratio_to_noise": err / noise,
    }
