"""Fit the latent manifold of a folder of MERL tables (paper Sec. 3) and save it."""

import os
import time

from .common import ArgumentParser, guarded, parse_list

def check(args):
    """Everything checked before the (long) fit: values, --out and --plot (:mod:`ownership`)."""
    from ..._util import ownership, checks as validate
    from ...imaging import plots
    from ...errors import InputError

    if args.q is not None and not 1 <= args.q <= 8:
        raise InputError(f"--q must be an integer from 1 to 8, got {args.q}")
    if args.length_scale is not None:
        validate.finite("--length-scale", args.length_scale, 0.0, 1e6, lo_open=True)
    if args.noise is not None:
        validate.finite("--noise", args.noise, 0.0, 1e6, lo_open=True)
    folder, base = os.path.split(args.out)
    if not base.lower().endswith(".npz") or len(base) <= 4:
        fix = os.path.join(folder, (os.path.splitext(base)[0].lstrip(".") or "manifold") + ".npz")
        raise InputError(f"--out must name a .npz file (the manifold is saved as NumPy .npz), got {args.out!r}: "
                         f"use --out {fix}")
    ownership.check_replaceable(args.out, args.force, what="--out")
    if args.plot:
        validate.output_folder("--plot", args.plot)
        for name in plots.FIT_PLOTS:
            ownership.check_replaceable(os.path.join(args.plot, name), args.force, what="--plot file")


@guarded
def main(argv=None):
    p = ArgumentParser(description=__doc__)
    p.add_argument("database", help="folder of <name>.binary MERL tables")
    p.add_argument("--out", required=True, help="output manifold (.npz)")
    p.add_argument("--preset", choices=["default", "paper"], default="default",
                   help="default: the measured best (log features, q=3, convex Shepard weights); paper: the "
                        "paper's exact formulation (raw features, q=2, Hooke-Jeeves, Eq. 4 GP weights). "
                        "The options below override the preset")
    p.add_argument("--q", type=int, default=None, help="latent dimension (1..8)")
    p.add_argument("--materials", type=parse_list, default=None, help="subset of materials (default: all)")
    p.add_argument("--method", choices=["hooke-jeeves", "lbfgs"], default=None)
    p.add_argument("--features", choices=["raw", "log"], default=None, help="fit features")
    p.add_argument("--length-scale", type=float, default=None, help="kernel length scale l")
    p.add_argument("--noise", type=float, default=None, help="kernel noise mu")
    p.add_argument("--plot", metavar="DIR", help="write latent map and convergence PNGs here")
    p.add_argument("--force", action="store_true",
                   help="replace an existing --out (or plot) this tool did not write (never a read-only one)")
    args = p.parse_args(argv)

    from ..._util import ownership
    from ...imaging import plots
    from ...manifold.model import Manifold
    t0 = time.perf_counter()
    check(args)
    m = Manifold.fit(args.database, q=args.q, names=args.materials, method=args.method,
                     length_scale=args.length_scale, noise=args.noise, features=args.features,
                     preset=args.preset, progress=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    m.save(args.out)
    ownership.record([args.out], "fit_manifold.py")
    print(m.summary())
    print(f"time: {time.perf_counter() - t0:.2f} s total (load {m.info['time_load_s']:.2f} s, "
          f"Gram {m.info['time_gram_s']:.2f} s, optimisation {m.info['time_fit_s']:.2f} s)")
    print(f"final L = {m.info['log_likelihood']:.8g}, cond(K) = {m.condition_number():.4g}")
    print(f"saved {args.out}")
    if args.plot:
        paths = plots.write_fit_plots(m, args.plot)
        ownership.record(paths, "fit_manifold.py")
        for path in paths:
            print(f"plot: {path}")
