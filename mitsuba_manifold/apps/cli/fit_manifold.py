"""Fit the latent manifold of a database of measured materials (paper Sec. 3) and save it."""

from __future__ import annotations

import os
import time
from typing import TYPE_CHECKING

from .common import ArgumentParser, guarded, parse_list

if TYPE_CHECKING:
    from ...manifold.presets import FitOptions


def options(args) -> FitOptions:
    """The :class:`~mitsuba_manifold.manifold.presets.FitOptions` of the command line."""
    from ...manifold.presets import FitOptions

    return FitOptions(
        preset=args.preset,
        q=args.q,
        names=args.materials,
        method=args.method,
        features=args.features,
        length_scale=args.length_scale,
        noise=args.noise,
        stress=args.stress,
    )


def _saved_manifold(args):
    """Whether DATABASE is a saved manifold (``.npz``) to add materials to."""
    return os.path.isfile(args.database) and args.database.lower().endswith(".npz")


def check(args, guard=None) -> None:
    """Everything checked before the (long) fit: values, --out and --plot (``guard``: the run's
    :class:`ownership.Outputs`, which then watches them; default: checked only).
    """
    from ..._util import checks as validate
    from ..._util import ownership
    from ...errors import InputError
    from ...imaging import plots
    from ...manifold.adding import check_additions
    from ...manifold.file.io import check_save_path

    check_additions(args.add, args.name)
    fit = options(args)
    if _saved_manifold(args):
        if not args.add:
            raise InputError(
                f"{args.database} is a saved manifold, not a database: add materials to it with "
                "--add PATH, or give a database folder or built-in name to fit"
            )
        if fit.given():
            raise InputError(
                f"{', '.join(fit.given())} set how a manifold is fitted; {args.database} is fitted "
                "already (--add keeps its points): drop them, or fit a database instead"
            )
    fit.check()
    check_save_path(args.out)
    guard = guard or ownership.Outputs("fit_manifold.py", args.force)
    guard.check(args.out, "--out")
    if args.plot:
        validate.output_folder("--plot", args.plot)
        for name in plots.FIT_PLOTS:
            guard.check(os.path.join(args.plot, name), "--plot file")


@guarded
def main(argv=None) -> None:
    p = ArgumentParser(description=__doc__, aliases={"names": "materials"})
    p.add_argument(
        "database",
        help="built-in database (merl, rgl, nielsen, all, sgd; NAME@NHxNDxNP for another "
        "resolution; builtin:NAME where the current folder holds a NAME of its own) or folder "
        "of measured tables (.binary, .bsdf, .h5, .npz; ./NAME for a folder named like a set)",
    )
    p.add_argument("--out", required=True, help="output manifold (.npz)")
    p.add_argument(
        "--preset",
        choices=["default", "paper"],
        default="default",
        help="default: the measured best (log features, q=4 with a stress term towards the "
        "materials' perceptual distances, convex Shepard weights); paper: the "
        "paper's exact formulation (raw features, q=2, Hooke-Jeeves, Eq. 4 GP weights). "
        "The options below override the preset",
    )
    p.add_argument("--q", type=int, default=None, help="latent dimension (1..8)")
    p.add_argument(
        "--materials", type=parse_list, default=None, help="subset of materials (default: all)"
    )
    p.add_argument(
        "--method",
        choices=["hooke-jeeves", "lbfgs", "newton"],
        default=None,
        help="optimiser: newton (trust-region Newton, the default preset's), lbfgs, or "
        "hooke-jeeves (the paper's)",
    )
    p.add_argument("--features", choices=["raw", "log"], default=None, help="fit features")
    p.add_argument("--length-scale", type=float, default=None, help="kernel length scale l")
    p.add_argument("--noise", type=float, default=None, help="kernel noise mu")
    p.add_argument(
        "--stress",
        type=float,
        default=None,
        help="weight of the layout's stress term towards the materials' perceptual distances "
        "(0: none; needs --method newton or lbfgs when > 0)",
    )
    p.add_argument("--plot", metavar="DIR", help="write latent map and convergence PNGs here")
    p.add_argument(
        "--add",
        action="append",
        default=[],
        metavar="PATH",
        help="add this material after the fit without refitting (repeatable): a .binary, .bsdf "
        "(Mitsuba measured), .h5 or .npz (NBRDF) file or SET:NAME of a built-in database; "
        "with a saved manifold .npz as DATABASE, add to it instead of fitting",
    )
    p.add_argument(
        "--name",
        action="append",
        default=[],
        metavar="N",
        help="name of the --add material of the same position (default: its file name)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out (or plot) this tool did not write (never a read-only one)",
    )
    args = p.parse_args(argv)

    from ..._util import ownership

    t0 = time.perf_counter()
    group = None if args.plot is None else "plots:" + os.path.abspath(args.plot)
    with ownership.Outputs("fit_manifold.py", args.force, group=group) as guard:
        check(args, guard)
        fit_and_save(args, guard, t0)


def fit_and_save(args, guard, t0) -> None:
    """The fit, the manifold and the plots (each recorded as written, under ``guard``);
    plots an earlier fit wrote into ``--plot`` and this one does not (another ``q``) are removed.
    """
    from ...imaging import plots
    from ...manifold.model import Manifold

    if args.add and _saved_manifold(args):
        m = Manifold.load(args.database)
    else:
        fit = options(args)
        m = Manifold.fit(
            args.database,
            q=fit.q,
            names=fit.names,
            method=fit.method,
            length_scale=fit.length_scale,
            noise=fit.noise,
            features=fit.features,
            preset=fit.preset,
            stress=fit.stress,
            progress=True,
        )
    for k, path in enumerate(args.add):
        info = m.add(path, args.name[k] if k < len(args.name) else None)
        print(
            f"added {info.name} at {info.x.round(4).tolist()} (closest material {info.nearest}) "
            f"in {info.time_s:.2f} s"
        )
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    m.save(args.out)
    print(m.summary())
    print(
        f"time: {time.perf_counter() - t0:.2f} s total; the fit's: load {m.record.timings.load_s:.2f} s, "
        f"Gram {m.record.timings.gram_s:.2f} s, optimisation {m.record.timings.fit_s:.2f} s"
    )
    print(f"final L = {m.record.log_likelihood:.8g}, cond(K) = {m.condition_number():.4g}")
    print(f"saved {args.out}")
    if args.plot:
        for path in plots.write_fit_plots(m, args.plot):
            print(f"plot: {path}")
        for path in guard.remove_stale(args.plot, names=plots.FIT_PLOTS):
            print(f"removed {path} (an earlier fit's plot; this one has no such plot)")
