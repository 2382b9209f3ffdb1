"""Make a database folder from built-in sets and folders of measured materials.

Sources (``--from``, repeatable; default ``merl``): the built-in sets ``merl`` (the 100 MERL
materials, NBRDF fits of the measurements), ``rgl`` (51 isotropic RGL-EPFL), ``nielsen`` (8),
``all`` (the 159), ``sgd`` (Shifted-Gamma fits of MERL), or folders of MERL ``.binary`` files,
Mitsuba ``measured`` files (``.bsdf``, isotropic), NBRDF networks (``.h5`` + ``.json``, ``.npz``).
Without ``--export`` the folder only names its sources (``sources.json``) and tables are made
on demand into its cache; ``--export`` writes every material as a ``.binary`` file. A built-in
set needs no folder at all: every tool that takes a database also takes a set's name.
"""

from __future__ import annotations

import os
import time

from .common import ArgumentParser, guarded, parse_list, parse_resolution


@guarded
def main(argv=None) -> None:
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

    from ..._util import checks as validate
    from ...data import database, merl
    from ...data.sources import builtin_set
    from ...errors import InputError

    t0 = time.perf_counter()
    # one rule for set names and folders (sgd where ./sgd exists is ambiguous, builtin:sgd the set)
    sources = [builtin_set(s, what="--from") or s for s in args.sources or ["merl"]]
    if args.materials and len(set(args.materials)) < len(args.materials):
        repeated = sorted({n for n in args.materials if args.materials.count(n) > 1})
        print(f"note: {', '.join(repeated)} repeated in --materials; each table is made once")
        args.materials = list(dict.fromkeys(args.materials))
    validate.finite("--noise", args.noise, 0.0, 10.0)
    validate.seed("--seed", args.seed)
    if sources == ["sgd"] and (args.export or args.materials or args.noise > 0):
        n = len(args.materials) if args.materials else 100
        merl.table_resolution(args.resolution, "--resolution", workers=min(n, os.cpu_count() or 1))
        paths = database.make_database(
            args.out,
            args.resolution,
            args.materials,
            args.noise,
            args.seed,
            progress=True,
            force=args.force,
        )
        print(f"{len(paths)} tables in {args.out} ({time.perf_counter() - t0:.1f} s)")
        return
    if args.noise > 0:
        raise InputError("--noise applies to --from sgd only (noisy copies of the SGD fits)")
    merl.table_resolution(args.resolution, "--resolution")
    export = args.export or args.materials is not None
    db = database.write_database(
        args.out,
        sources,
        args.resolution,
        args.materials,
        export=export,
        progress=True,
        force=args.force,
    )
    what = ".binary files" if export else "materials (tables made on demand)"
    print(
        f"{len(db.names)} {what} in {args.out} from {', '.join(sources)} ({time.perf_counter() - t0:.1f} s)"
    )
