"""Helpers shared by the benchmarks: where they ran, memory, timed renders of the sphere scene."""

import os
import platform
import resource
import time

import numpy as np

from mitsuba_manifold.render.scene.scenes import SCENES_DIR, use_variant


def machine():
    """Where a benchmark ran."""
    info = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
    }
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
        with open("/proc/meminfo") as f:
            info["mem_total_gib"] = round(int(f.readline().split()[1]) / 2**20, 1)
    except OSError:
        pass
    return info


def cpu_seconds():
    """CPU time (user + system) of this process and its finished children: what a benchmark
    cost the machine, which its wall time does not say on a shared one.
    """
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def peak_rss_gib():
    """Peak resident memory of this process so far."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def sphere_with(bsdf_xml, spp, res, manifold=None):
    """``scenes/sphere.xml`` with its material block replaced by ``bsdf_xml``."""
    import re

    mi = use_variant()
    with open(os.path.join(SCENES_DIR, "sphere.xml")) as f:
        text = f.read()
    text = re.sub(
        r'<bsdf type="manifold_brdf" id="material">.*?</bsdf>', bsdf_xml, text, flags=re.S
    )
    mi.Thread.thread().file_resolver().prepend(SCENES_DIR)
    params = {"spp": str(spp), "res": str(res)}
    if manifold is not None:
        params["manifold"] = os.path.abspath(manifold)
    return mi.load_string(text, **params)


def time_renders(scenes, repeats):
    """Interleaved timings (seconds) of ``mi.render`` per named scene, after a warm-up render:
    wall time and the process's CPU time (Dr.Jit's worker threads included).
    """
    import drjit as dr
    import mitsuba as mi

    times = {k: [] for k in scenes}
    cpus = {k: [] for k in scenes}
    for s in scenes.values():
        dr.eval(mi.render(s, seed=1000))
    for rep in range(repeats):
        for k, s in scenes.items():
            t0, c0 = time.perf_counter(), time.process_time()
            img = mi.render(s, seed=rep)
            dr.eval(img)
            dr.sync_thread()
            times[k].append(time.perf_counter() - t0)
            cpus[k].append(time.process_time() - c0)
    return {
        k: {
            "min_s": float(np.min(v)),
            "median_s": float(np.median(v)),
            "cpu_min_s": float(np.min(cpus[k])),
            "cpu_median_s": float(np.median(cpus[k])),
        }
        for k, v in times.items()
    }


def interpolated_point(m, a="chrome", b="gold-paint"):
    if a in m.names and b in m.names:
        return 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)]), f"midpoint of {a} and {b}"
    return 0.5 * (m.latent[0] + m.latent[1]), f"midpoint of {m.names[0]} and {m.names[1]}"


def work_manifold(folder, tag="q2"):
    """Where a benchmark keeps the manifold it fits on the database ``folder``: in that
    database's cache, named by the database (a built-in set and its resolution, or the folder)
    and ``tag`` (the fit's settings), so that no other database or fit reuses it.
    """
    import hashlib

    from mitsuba_manifold.data.database import database_cache, split_spec
    from mitsuba_manifold.data.sources import SET_NAMES

    base, dims = split_spec(folder)
    spec = f"{base if base in SET_NAMES else os.path.abspath(base)}@{dims}"
    key = hashlib.sha256(spec.encode()).hexdigest()[:12]
    return os.path.join(database_cache(folder), f"bench_{tag}_{key}.npz")
