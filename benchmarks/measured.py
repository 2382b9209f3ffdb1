"""Measured materials: the built-in sets, the importer of Mitsuba ``measured`` files, the disk.

One function per part of the report (each returns a JSON-ready dict; add a part by adding a
function to :data:`PARTS`):

* ``tabulation``: seconds per table of each built-in set at MERL resolution (median over
  networks, the grid's inputs already made) against the 0.2 s target, and the first call's;
* ``positions``: which sample positions reproduce each set's data: the RGL networks against
  the real RGL files read by Mitsuba's ``measured`` plugin, the MERL networks against the SGD
  fits of MERL (cosine-weighted RMS of ``log(1 + rho)`` differences, at bin centres and starts);
* ``fidelity``: a material imported from a ``.bsdf`` and rendered by ``manifold_brdf`` against
  Mitsuba's ``measured`` rendering of the file (image mean ratio, relative MSE over the noise
  of two ``measured`` renders; median over the files);
* ``lean``: the disk a built-in set's cache takes, the float16 cache's error, a fit of all 159
  at MERL resolution (seconds, peak memory, in a subprocess), reading ``.binary`` files against
  reading their bytes.
"""

import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

#: The three real RGL files shipped beside the repository (``../shared/data/rgl``).
RGL_DIR = os.path.abspath(
    os.path.join(os.path.dirname(__file__), "..", "..", "..", "..", "shared", "data", "rgl")
)
TABLE_TARGET_S = 0.2
FIT_TARGET_S = 30.0


def _cos_log_rms(a, b, q):
    d = (np.log1p(np.maximum(a, 0)) - np.log1p(np.maximum(b, 0))) ** 2
    return float(np.sqrt((d * q).sum() / (3 * q.sum())))


def tabulation(dims=(90, 90, 180), per_set=10):
    """Seconds per table of each built-in NBRDF set (see the module docstring)."""
    from mitsuba_manifold.data import nbrdf

    out = {"dims": list(dims), "target_s": TABLE_TARGET_S}
    nbrdf._grid.cache_clear()
    nets = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "merl")
    t0 = time.perf_counter()
    nbrdf.tabulate(nets, nets.names[0], dims)
    out["first_table_s"] = time.perf_counter() - t0
    for name in nbrdf.SETS:
        nets = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, name)
        times = []
        for key in nets.names[:per_set]:
            t0 = time.perf_counter()
            nbrdf.tabulate(nets, key, dims)
            times.append(time.perf_counter() - t0)
        out[name] = {
            "median_s": float(np.median(times)),
            "max_s": float(np.max(times)),
            "tables": len(times),
        }
    out["meets_target"] = all(out[s]["median_s"] <= TABLE_TARGET_S for s in nbrdf.SETS)
    return out


def positions(dims=(90, 90, 180), merl_stride=5, rgl_dir=RGL_DIR):
    """Bin centres against bin starts for the networks of each set (see the module docstring)."""
    from mitsuba_manifold.data import nbrdf, sources
    from mitsuba_manifold.data.database import albedo_weights
    from mitsuba_manifold.render.plugin import measured

    q = albedo_weights(dims)
    near = np.zeros(dims, bool)
    near[: dims[0] // 3] = True  # theta_h below 10 degrees: the highlights
    out = {
        "metric": "cosine-weighted RMS of log(1 + rho) differences",
        "dims": list(dims),
        "chosen": dict(sources.SET_POSITIONS),
        "user_networks": sources.USER_POSITIONS,
    }
    rgl = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "rgl")
    rows = {}
    for f in sorted(os.listdir(rgl_dir)) if os.path.isdir(rgl_dir) else []:
        name = sources.material_name(f)
        if not f.endswith(".bsdf") or name not in rgl.names:
            continue
        truth = measured.resample(os.path.join(rgl_dir, f), dims, samples=1)
        row = {}
        for pos in nbrdf.POSITIONS:
            t = nbrdf.tabulate(rgl, name, dims, pos)
            row[pos] = _cos_log_rms(t, truth, q)
            row[pos + "_highlight"] = _cos_log_rms(t * near, truth * near, q * near)
        rows[name] = row
    out["rgl_against_measured_files"] = rows
    merl_nets = nbrdf.NetworkSet.load(nbrdf.WEIGHTS_PATH, "merl")
    sgd = {s.name: s for s in sources.builtin("sgd")}
    errs = []
    for name in merl_nets.names[::merl_stride]:
        truth = sgd[name].table(dims)
        errs.append(
            [
                _cos_log_rms(nbrdf.tabulate(merl_nets, name, dims, pos), truth, q)
                for pos in nbrdf.POSITIONS
            ]
        )
    errs = np.array(errs)
    out["merl_against_sgd"] = {
        "materials": len(errs),
        "median_centres": float(np.median(errs[:, 0])),
        "median_starts": float(np.median(errs[:, 1])),
        "starts_closer_in": int((errs[:, 1] < errs[:, 0]).sum()),
    }
    return out


def fidelity(res=64, spp=256, rgl_dir=RGL_DIR, work=None):
    """Imported ``.bsdf`` files rendered by ``manifold_brdf`` against Mitsuba's ``measured``."""
    from mitsuba_manifold.manifold.model import Manifold
    from mitsuba_manifold.render.plugin import measured

    files = (
        sorted(f for f in os.listdir(rgl_dir) if f.endswith(".bsdf"))
        if os.path.isdir(rgl_dir)
        else []
    )
    if not files:
        return {"skipped": f"no .bsdf files in {rgl_dir}"}
    work = work or tempfile.mkdtemp(prefix="bench-measured-")
    folder = os.path.join(work, "bsdf")
    os.makedirs(folder, exist_ok=True)
    for f in files:
        if not os.path.exists(os.path.join(folder, f)):
            os.symlink(os.path.join(rgl_dir, f), os.path.join(folder, f))
    t0 = time.perf_counter()
    m = Manifold.fit(folder, q=1)
    path = os.path.join(work, "manifold.npz")
    m.save(path)
    import_s = time.perf_counter() - t0
    rows = [measured.fidelity(os.path.join(rgl_dir, f), path, res=res, spp=spp) for f in files]
    ratio = float(np.median([r["ratio_to_noise"] for r in rows]))
    worst_mean = float(max(abs(r["mean_ratio"] - 1) for r in rows))
    return {
        "res": res,
        "spp": spp,
        "materials": rows,
        "import_and_fit_s": import_s,
        "median_ratio_to_noise": ratio,
        "worst_mean_error": worst_mean,
        "meets_target": ratio <= 3.0 and worst_mean <= 0.01,
        "target": "image mean within 1%, median rel. MSE <= 3x the noise of two measured renders",
    }


def _du(folder):
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(folder) for f in fs)


def lean(dims=(90, 90, 180), fit=True, binary_files=10):
    """Disk, precision, fit time and memory, reading ``.binary`` files (see the module docstring)."""
    from mitsuba_manifold.data import merl, nbrdf
    from mitsuba_manifold.data.database import MADE_DTYPE, Database, write_database

    out = {"dims": list(dims), "cache_dtype": np.dtype(MADE_DTYPE).name}
    work = tempfile.mkdtemp(prefix="bench-lean-")
    env = {**os.environ, "MITSUBA_MANIFOLD_CACHE": os.path.join(work, "cache")}
    try:
        os.environ["MITSUBA_MANIFOLD_CACHE"], before = (
            env["MITSUBA_MANIFOLD_CACHE"],
            os.environ.get("MITSUBA_MANIFOLD_CACHE"),
        )
        db = Database(
            "merl" if tuple(dims) == merl.MERL_DIMS else f"merl@{'x'.join(map(str, dims))}"
        )
        worst = 0.0
        t0 = time.perf_counter()
        for name in db.names:
            cached = db.reflectance(name)
            exact = nbrdf.tabulate(
                db.sources[name].networks, name, dims, db.sources[name].positions
            )
            big = exact > 1e-3
            worst = max(worst, float(np.max(np.abs(cached[big] - exact[big]) / exact[big])))
        out["merl_cache_bytes"] = _du(os.path.join(work, "cache"))
        out["merl_tables_made_s"] = time.perf_counter() - t0
        out["cache_max_relative_error"] = worst
        exported = os.path.join(work, "exported")
        names = db.names[:binary_files]
        write_database(exported, ["merl"], dims, materials=names, export=True)
        t0 = time.perf_counter()
        for n in names:
            np.fromfile(os.path.join(exported, n + ".binary"), dtype=np.uint8)
        raw_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        Database(exported).stack()
        first_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        Database(exported).stack()
        out["binary_files"] = {
            "files": len(names),
            "bytes": _du(exported) - _du(os.path.join(exported, ".manifold-cache")),
            "read_bytes_s": raw_s,
            "first_load_s": first_s,
            "cached_load_s": time.perf_counter() - t0,
        }
        if fit:
            tool = os.path.join(
                os.path.dirname(__file__), "..", "..", "..", "tools", "fit_manifold.py"
            )
            for run in ("cold", "warm"):
                t0 = time.perf_counter()
                r = subprocess.run(
                    [
                        sys.executable,
                        os.path.abspath(tool),
                        "all",
                        "--out",
                        os.path.join(work, f"all_{run}.npz"),
                    ],
                    env=env,
                    capture_output=True,
                    text=True,
                    check=False,
                )
                wall = time.perf_counter() - t0
                if r.returncode:
                    out[f"fit_all_{run}"] = {"error": r.stderr.strip().splitlines()[-1:]}
                    continue
                out[f"fit_all_{run}"] = {
                    "s": wall,
                    "meets_target": wall <= FIT_TARGET_S,
                    "peak_rss_children_gb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
                    / 2**20,
                    "log": [ln for ln in r.stdout.splitlines() if ln.startswith("time:")],
                }
            out["all_cache_bytes"] = _du(os.path.join(work, "cache"))
    finally:
        if before is None:
            os.environ.pop("MITSUBA_MANIFOLD_CACHE", None)
        else:
            os.environ["MITSUBA_MANIFOLD_CACHE"] = before
        shutil.rmtree(work, ignore_errors=True)
    return out


#: The parts of the report, in order: ``{name: function}``.
PARTS = {"tabulation": tabulation, "positions": positions, "fidelity": fidelity, "lean": lean}


def run(folder=None, parts=None, **kwargs):
    """The report of ``parts`` (default all of :data:`PARTS`); ``folder`` is not used (the
    benchmark uses the built-in sets and the RGL files).
    """
    report = {}
    for name in parts or PARTS:
        t0 = time.perf_counter()
        report[name] = PARTS[name](**kwargs.get(name, {}))
        report[name]["bench_s"] = time.perf_counter() - t0
    return report
