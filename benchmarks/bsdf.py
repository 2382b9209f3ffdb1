"""BSDF benchmark: manifold_brdf against roughconductor, cdf against cosine sampling, construction time."""

import os
import time

import numpy as np

from mitsuba_manifold._util.timing import median_time
from mitsuba_manifold.manifold.model import Manifold
from mitsuba_manifold.render.scene.scenes import use_variant

from .common import interpolated_point, sphere_with, time_renders, work_manifold


def run(
    folder,
    manifold=None,
    spp=64,
    res=256,
    repeats=7,
    mse_res=96,
    mse_spp=32,
    ref_spp=2048,
    materials=("chrome", "steel", "gold-metallic-paint", "red-fabric"),
):
    """manifold_brdf against roughconductor, cdf against cosine sampling, construction time.

    Targets: render time at most 1.5x roughconductor at equal spp; relative MSE at least
    5x lower with ``cdf`` than with ``cosine`` for the spiky metals. The ratio of CPU times
    (``ratio_cpu_min``) is the one a loaded machine disturbs least.
    """
    from mitsuba_manifold.imaging import metrics
    from mitsuba_manifold.render.plugin.sampling import sampling_cache_path

    mi = use_variant()
    m = Manifold.load(manifold) if manifold else None
    if m is None:
        manifold = work_manifold(folder)
        m = Manifold.fit(folder, q=2)
        m.save(manifold)
    x, where = interpolated_point(m)
    xs = ", ".join(repr(float(v)) for v in x)
    out = {"variant": mi.variant(), "x": x.tolist(), "x_is": where, "n_materials": m.n}

    # construction of an interpolated material, with and without the sampling cache
    db = m.open_database()
    keep, _, _ = m.prune(m.weights(x)[1])
    for i in keep:
        path = sampling_cache_path(db, m.names[i])
        if os.path.exists(path):
            os.remove(path)
    spec = {"type": "manifold_brdf", "manifold": os.path.abspath(manifold), "x": xs}
    t0 = time.perf_counter()
    mi.load_dict(spec)
    out["construct_without_cache_s"] = time.perf_counter() - t0
    out["construct_with_cache_s"] = median_time(lambda: mi.load_dict(spec), 3)[0]
    out["construct_materials_used"] = int(len(keep))
    out["table_dims"] = list(db.dims)

    # render time against roughconductor
    scenes = {
        "manifold_brdf": sphere_with(
            f'<bsdf type="manifold_brdf" id="material"><string name="manifold" '
            f'value="$manifold"/><string name="x" value="{xs}"/></bsdf>',
            spp,
            res,
            manifold,
        ),
        "roughconductor": sphere_with(
            '<bsdf type="roughconductor" id="material"><string name="material" '
            'value="Cr"/><float name="alpha" value="0.05"/></bsdf>',
            spp,
            res,
        ),
    }
    t = time_renders(scenes, repeats)
    ratio = t["manifold_brdf"]["min_s"] / t["roughconductor"]["min_s"]
    out["render"] = {
        "spp": spp,
        "resolution": res,
        "times": t,
        "ratio_min": ratio,
        "ratio_median": t["manifold_brdf"]["median_s"] / t["roughconductor"]["median_s"],
        "ratio_cpu_min": t["manifold_brdf"]["cpu_min_s"] / t["roughconductor"]["cpu_min_s"],
        "ratio_target": 1.5,
        "meets_target": ratio <= 1.5,
    }

    # relative MSE at equal spp, cdf against cosine
    rows = []
    for name in materials:
        if name not in m.names:
            continue
        sc = {
            mode: sphere_with(
                f'<bsdf type="manifold_brdf" id="material"><string name="manifold" '
                f'value="$manifold"/><string name="material" value="{name}"/>'
                f'<string name="sampling" value="{mode}"/></bsdf>',
                mse_spp,
                mse_res,
                manifold,
            )
            for mode in ("cdf", "cosine")
        }
        ref = np.mean(
            [np.array(mi.render(sc["cdf"], spp=ref_spp // 4, seed=100 + k)) for k in range(4)],
            axis=0,
        )
        err = {
            mode: float(
                np.mean(
                    [metrics.rel_mse(np.array(mi.render(sc[mode], seed=k)), ref) for k in range(4)]
                )
            )
            for mode in sc
        }
        spiky = name in ("chrome", "steel")
        rows.append(
            {
                "material": name,
                "rel_mse_cdf": err["cdf"],
                "rel_mse_cosine": err["cosine"],
                "cosine_over_cdf": err["cosine"] / err["cdf"],
                **(
                    {"target_ratio": 5.0, "meets_target": err["cosine"] / err["cdf"] >= 5.0}
                    if spiky
                    else {}
                ),
            }
        )
    out["sampling"] = {
        "spp": mse_spp,
        "resolution": mse_res,
        "reference_spp": ref_spp,
        "rows": rows,
    }
    return out
