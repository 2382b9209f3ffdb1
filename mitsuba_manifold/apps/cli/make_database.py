"""Make a database folder from built-in sets and folders of measured materials.

Sources (``--from``, repeatable; default ``merl``): the built-in sets ``merl`` (the 100 MERL
materials, NBRDF fits of the measurements), ``rgl`` (51 isotropic RGL-EPFL), ``nielsen`` (8),
``all`` (the 159), ``sgd`` (Shifted-Gamma fits of MERL), or folders of MERL ``.binary`` files,
Mitsuba ``measured`` files (``.bsdf``, isotropic), NBRDF networks (``.h5`` + ``.json``, ``.npz``).
Without ``--export`` the folder only names its sources (``sources.json``) and tables are made
on demand into its cache; ``--export`` writes every material as a ``.binary`` file. A built-in
set needs no folder at all: every tool that takes a database also takes a set's name.
"""

import time

from .common import ArgumentParser, guarded, parse_list, parse_resolution


@guarded
def main(argv=None):
    p = ArgumentParser(description=__doc__)
    p.add_argument("--out", required=True, help="output folder (created or completed)")
    p.add_argument(
        "--from",
        dest="sources",
        action="append",
        default=None,
        metavar="NAME_OR_PATH",
        help="built-in set (merl, rgl, nielsen, all, sgd; builtin:NAME where the current folder "
        "holds a NAME of its own) or folder of measured files (./NAME for a folder named like a "
        "set); repeatable (default: merl)",
    )
    p.add_argument(
        "--export", action="store_true", help="write every material as a MERL .binary file"
    )
    p.add_argument(
        "--resolution",
        type=parse_resolution,
        default=(90, 90, 180),
        help="theta_h,theta_d,phi_d bins (default 90,90,180 as MERL)",
    )
    p.add_argument(
        "--materials",
        type=parse_list,
        default=None,
        help="comma-separated names to export (default: all; implies --export)",
    )
    p.add_argument(
        "--noise",
        type=float,
        default=0.0,
        help="multiplicative log-normal noise sigma (--from sgd only; default 0)",
    )
    p.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    p.add_argument("--force", action="store_true", help="overwrite files this tool did not make")
    args = p.parse_args(argv)

    from ...data.database import DatabaseRequest, build_database

    t0 = time.perf_counter()
    if args.materials and len(set(args.materials)) < len(args.materials):
        repeated = sorted({n for n in args.materials if args.materials.count(n) > 1})
        print(f"note: {', '.join(repeated)} repeated in --materials; each table is made once")
    request = DatabaseRequest(
        out=args.out,
        sources=tuple(args.sources or ["merl"]),
        resolution=args.resolution,
        materials=None if args.materials is None else tuple(args.materials),
        export=args.export,
        noise=args.noise,
        seed=args.seed,
        force=args.force,
    ).checked()
    count = build_database(request)
    if request.sgd_copies:
        print(f"{count} tables in {args.out} ({time.perf_counter() - t0:.1f} s)")
        return
    what = (
        ".binary files"
        if request.export or request.materials is not None
        else ("materials (tables made on demand)")
    )
    print(
        f"{count} {what} in {args.out} from {', '.join(request.sources)} "
        f"({time.perf_counter() - t0:.1f} s)"
    )
