"""What the main job does, end to end (``tools/main.py``); the GI benchmark runs the same steps.

1. the database (default: the built-in ``merl``, the 100 MERL measurements as NBRDF fits,
   tables made on demand into the cache; any built-in set or folder :class:`Database` takes),
2. the latent manifold (GPLVM fit, paper Sec. 3) with its summary and plots,
3. the L1- basis of a scene (paper Sec. 5.2, one image per material),
4. blends at a training point, a midpoint and an extrapolated point (Eq. 13), their errors
   against full-GI references, and the error-against-time plot of blending vs re-rendering;
   with ``denoise``, also the blends and the highest-spp direct renders denoised (OIDN guided
   by albedo and normal AOVs that blend like the images, :mod:`denoise`), raw errors kept.

:func:`run_main_job` does all four (settings: :class:`MainJob`); steps 3 and 4 are
:func:`~mitsuba_manifold.apps.gi_comparison.gi_report` (settings:
:class:`~mitsuba_manifold.apps.gi_comparison.GISettings`; also behind ``tools/bench.py gi``).
"""

import json
import os
import time
from dataclasses import dataclass, field, replace

from .._util import ownership
from .._util.atomic import write_bytes
from .._util.memory import peak_rss
from ..data import database
from ..imaging import plots
from ..manifold.model import Manifold
from ..render.scene import scenes as _scenes
from .gi_comparison import gi_report, versus_direct
from .tool_commands import explore_command

__all__ = ["MainJob", "Stages", "run_main_job"]


@dataclass(frozen=True)
class MainJob:
    """The main job's settings (``tools/main.py``'s options; every field is also a keyword of
    :func:`run_main_job`).

    Attributes
    ----------
    out : str
        Output folder.
    resolution : (int, int, int)
        Table bins of the database.
    database : str
        Built-in set (``merl``, ``rgl``, ``nielsen``, ``all``, ``sgd``) or folder of measured tables.
    q, features, preset
        The manifold fit (:meth:`Manifold.fit`; None: the preset's).
    scene : str
        Shipped scene's name or scene XML of the GI part.
    res, spp, ref_spp : int
        Image size, basis and reference samples per pixel.
    mode : {"onepass", "per-material"}
    direct_spp : tuple of int
        Direct renders the blends are compared with.
    denoise : bool
        Also the AOVs and the denoised figures.
    force : bool
        Replace files in ``out`` this job did not write (never read-only ones, nor anything
        but regular files); without it they are refused before anything is computed.
    """

    out: str
    resolution: tuple = (90, 90, 180)
    q: object = None
    features: object = None
    preset: str = "default"
    scene: str = "table"
    res: int = 256
    spp: int = 512
    ref_spp: int = 2048
    mode: str = "onepass"
    direct_spp: tuple = (1, 4, 16, 64, 256)
    denoise: bool = True
    force: bool = False
    database: str = "merl"

    def check(self):
        """Check the settings before anything is computed or written; raises
        :class:`~mitsuba_manifold.errors.InputError` naming the field (in backquotes, which
        ``tools/main.py`` writes as its option), the value and the fix. Returns the scene's path.
        """
        from .._util import checks as validate
        from ..data import merl
        from ..errors import InputError, MitsubaManifoldError
        from ..gp.kernel import MAX_LATENT_DIM

        validate.output_folder("`out`", self.out)
        merl.table_resolution(self.resolution, "`resolution`")
        if self.q is not None:
            validate.positive_int("`q`", self.q, "3", hi=MAX_LATENT_DIM)
        path = _scenes.check_scene("`scene`", self.scene)
        res = self.res
        validate.positive_int("`res`", res, "256")
        try:
            n = len(database.Database(self.database, dims=self.resolution).names)
        except MitsubaManifoldError as e:
            raise InputError(f"`database` {self.database}: {e}") from None
        held = n + 2 if self.mode == "onepass" else 6  # as render_basis holds them
        validate.fits_in_memory(
            "`res`", 2 * held * res * res * 3 * 4, f"{self.mode} basis images of {res}x{res}"
        )
        validate.positive_int("`spp`", self.spp, "512")
        validate.positive_int("`ref_spp`", self.ref_spp, "2048")
        for s in self.direct_spp:
            validate.positive_int("`direct_spp`", s, "64")
        return path


@dataclass
class Stages:
    """The main job's stages as they end, in order: the seconds of each and the process's peak
    memory by the end of each (the stage where it grows holds the new peak).

    Attributes
    ----------
    seconds : dict
        ``"<part>_s"``: seconds (``report.json``'s ``stages``; a stage may time several parts).
    peak_after : dict
        Stage name: the process's peak memory in bytes
        (:func:`~mitsuba_manifold._util.memory.peak_rss`) at its end, None where the system does
        not say (``report.json``'s ``peak_rss_after``).
    """

    seconds: dict = field(default_factory=dict)
    peak_after: dict = field(default_factory=dict)

    def ended(self, stage, **seconds):
        """Record the end of ``stage``: the peak memory now, and ``seconds`` (``part_s=value``)."""
        self.seconds.update(seconds)
        self.peak_after[stage] = peak_rss()

    def peak(self):
        """``(bytes, stage)``: the process's peak memory and the first stage by whose end it was
        reached; ``(None, None)`` where the system does not say.
        """
        known = {k: v for k, v in self.peak_after.items() if v is not None}
        if not known:
            return None, None
        top = max(known.values())
        return top, next(k for k, v in known.items() if v == top)

    def into(self, report):
        """Write the stages into the GI report: ``stages``, ``peak_rss_bytes``, ``peak_rss_after``."""
        report["stages"] = dict(self.seconds)
        report["peak_rss_bytes"] = self.peak()[0]
        report["peak_rss_after"] = dict(self.peak_after)


def run_main_job(job, log=print, **fields):
    """The main job: database, manifold, plots, basis and blends of the scene, ``gi/report.json``.

    ``job``: a :class:`MainJob`, or its output folder with the other fields as keywords
    (``run_main_job("out", res=64, spp=16)``). ``log(text)`` reports progress (stages and
    results). Returns the GI report (with ``report_path``, and the :class:`Stages`' record:
    ``stages``, the measured seconds of each stage, ``peak_rss_bytes``, the process's peak
    memory, and ``peak_rss_after``, that peak at the end of each stage).
    """
    job = replace(job, **fields) if isinstance(job, MainJob) else MainJob(job, **fields)
    job.check()
    with ownership.Outputs("main.py", job.force, folders=_output_folders(job)) as guard:
        for what, path in main_job_outputs(job):  # before anything is computed
            guard.check(path, what)
        return _run(job, log)


def _output_folders(job):
    """Folders whose every file is an output of the job: the plots, and ``gi/`` (whose image
    names depend on the fitted manifold). The database and the basis folders keep their own
    records (``database.json``, ``manifest.json``).
    """
    return [os.path.join(job.out, "plots"), os.path.join(job.out, "gi")]


def main_job_outputs(job):
    """``(what, path)`` of the files the job writes whatever the data: the manifold, the
    latent map and the report (the others are checked as they are written).
    """
    return [
        ("`out`'s manifold", os.path.join(job.out, "manifold.npz")),
        ("`out`'s plot", os.path.join(job.out, "plots", plots.FIT_PLOTS[0])),
        ("`out`'s report", os.path.join(job.out, "gi", "report.json")),
    ]


def _run(job, log):
    """:func:`run_main_job` once its outputs are checked (and watched)."""
    t_start = time.perf_counter()
    stages = Stages()
    db_dir, manifold_path = _database_and_manifold(job, log, stages)
    log(
        f"\n== basis of {job.scene} and blends ({job.res}x{job.res}, {job.spp} spp basis, "
        f"{job.ref_spp} spp references)"
    )
    t0 = time.perf_counter()
    report = gi_report(
        db_dir,
        manifold=manifold_path,
        scenes=(job.scene,),
        out=os.path.join(job.out, "gi"),
        res=job.res,
        basis_spp=job.spp,
        ref_spp=job.ref_spp,
        mode=job.mode,
        direct_spp=job.direct_spp,
        save_images=True,
        progress=True,
        denoise=job.denoise,
        refine_spp=max(1, max(job.direct_spp) // 8),
    )  # a control-variate sample costs more than a direct one (docs/benchmarks.md)
    t_gi = time.perf_counter() - t0
    sc = report["scenes"][job.scene]
    references = sum(r["reference_time_s"] for r in sc["points"])
    direct = sum(d["time_s"] for r in sc["points"] for d in r["direct"])
    stages.seconds.update(
        basis_s=sc["basis_time_s"],
        references_s=references,
        direct_renders_s=direct,
        blends_images_plot_s=t_gi - sc["basis_time_s"] - references - direct,
    )
    stages.peak_after.update(sc["peak_rss_after"])
    log(
        f"basis: {sc['basis_images']} images in {sc['basis_time_s']:.1f} s"
        + (f" (AOVs {sc['aovs_time_s']:.1f} s)" if "aovs_time_s" in sc else "")
    )
    _log_points(sc["points"], max(job.direct_spp), log)
    report_path = os.path.join(job.out, "gi", "report.json")
    stages.ended("end", total_s=time.perf_counter() - t_start)
    stages.into(report)
    write_bytes(report_path, json.dumps(report, indent=1))
    log(f"plot: {report['plot']}\nreport: {report_path}\nimages: {os.path.join(job.out, 'gi')}")
    parts = ", ".join(f"{k[:-2]} {v:.1f} s" for k, v in stages.seconds.items() if k != "total_s")
    log(f"stages: {parts}")
    top, reached = stages.peak()
    if top is not None:
        log(f"peak memory: {top / 2**30:.2f} GiB (reached by the end of: {reached})")
    log(
        f"\nexplore the manifold in the browser:\n  {explore_command(sc['basis_folder'], manifold_path)}"
    )
    log(f"\nmain job done in {time.perf_counter() - t_start:.0f} s")
    report["report_path"] = report_path
    return report


def _database_and_manifold(job, log, stages):
    """Steps 1 and 2 of the main job: the database, the fitted manifold and its plots; returns
    their paths and records each stage's end in ``stages`` (:class:`Stages`).
    """
    manifold_path = os.path.join(job.out, "manifold.npz")
    os.makedirs(job.out, exist_ok=True)
    log(f"\n== database: {job.database}")
    t0 = time.perf_counter()
    db = database.Database(job.database, dims=job.resolution)
    db_dir = db.folder
    stages.ended("tabulate", tabulate_s=time.perf_counter() - t0)
    log(
        f"{len(db.names)} materials, {'x'.join(map(str, db.dims))} bins "
        f"({stages.seconds['tabulate_s']:.1f} s)"
    )
    log(
        f"\n== manifold: preset {job.preset}"
        + (f", q={job.q}" if job.q else "")
        + (f", features={job.features}" if job.features else "")
    )
    m = Manifold.fit(db, q=job.q, features=job.features, preset=job.preset, progress=True)
    m.save(manifold_path)
    timings = m.record.timings
    stages.ended("fit", load_s=timings.load_s, gram_s=timings.gram_s, fit_s=timings.fit_s)
    log(m.summary())
    log(
        f"load {m.record.timings.load_s:.1f} s, Gram {m.record.timings.gram_s:.1f} s, "
        f"optimisation {m.record.timings.fit_s:.1f} s; saved {manifold_path}"
    )
    t0 = time.perf_counter()
    for path in plots.write_fit_plots(m, os.path.join(job.out, "plots")):
        log(f"plot: {path}")
    stages.ended("plots", plots_s=time.perf_counter() - t0)
    return db_dir, manifold_path


def _beside(label, r, took=""):
    """An indented line of :func:`_log_points`: another image of the point, its error and bias."""
    return f"{'':>12s} {label}: {took}rel. MSE {r['rel_mse']:.3g}, bias {100 * r['relative_bias']:+.2f}%"


def _log_points(points, top, log):
    """One line per point of the GI report (two when denoised), with its targets against the
    direct render at ``top`` spp (added to each row as ``versus_direct``).
    """
    for row in points:
        b = row["blend"]
        d = next(r for r in row["direct"] if r["spp"] == top)
        v = row["versus_direct"] = versus_direct(row, top)
        log(
            f"{row['point']:>12s} ({row['x_is']}): blend {1e3 * b['time_s']:.1f} ms, rel. MSE {b['rel_mse']:.3g}, "
            f"PSNR {b['psnr']:.1f} dB, bias {100 * b['relative_bias']:+.2f}% | direct {top} spp "
            f"{d['time_s']:.2f} s, rel. MSE {d['rel_mse']:.3g} | blend {v['speedup']:.0f}x faster, "
            f"{'lower' if v['meets_error_target'] else 'HIGHER'} error"
        )
        if "blend_summed" in row:
            r = row["blend_summed"]
            log(
                _beside(
                    "L2+ as summed (--l2 raw; the explorer while dragging)",
                    r,
                    f"{1e3 * r['time_s']:.1f} ms, ",
                )
            )
        if "blend_l1" in row:
            log(_beside("L1- blend (no L2+)", row["blend_l1"]))
        if "refined" in row:
            r = row["refined"]
            log(
                _beside(
                    f"refined ({r['spp']} spp)",
                    r,
                    f"{r['time_s']:.2f} s at a new point ({r['time_cold_s']:.2f} s from nothing), ",
                )
            )
        if "denoised" in b:
            log(
                f"{'':>12s} whole image denoised (OIDN, albedo+normal): blend "
                f"{1e3 * b['denoised']['time_s']:.0f} ms, "
                f"rel. MSE {b['denoised']['rel_mse']:.3g} (before: {b['rel_mse']:.3g}) | direct {top} spp "
                f"rel. MSE {d['denoised']['rel_mse']:.3g} (before: {d['rel_mse']:.3g})"
            )
