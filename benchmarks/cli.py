"""Benchmarks (not timed tests): each subcommand measures and writes a JSON report.

fit        Gram + optimisation time, final L (Hooke-Jeeves vs L-BFGS), cond(K), peak memory
interp     one full interpolated table, pruned and unpruned
pca        PCA reconstruction error of training tables vs the manifold's exact reproduction
bsdf       manifold_brdf vs roughconductor render time, cdf vs cosine sampling error, construction time
gi         blend vs direct re-rendering: error against run time on sphere.xml and table.xml
gi-targets full-GI bases: bias and error of L1-, full-GI, refined blends and direct renders, basis cost, blend time
stability  cond(K), weights, clamping and precision over stiff and extreme cases
basis      one-pass vs per-material basis rendering
match      inverse rendering on a basis: speed (--basis, a full basis) and accuracy on table/sphere
match-render  inverse rendering through the differentiable x (prb, Adam), 3 views of cbox, no basis
scaling    time and peak memory of every stage against N, table and image resolution, spp
           (each point in a subprocess; makes its own databases), and chunked rendering on Ray
explore    tools/explore.py: request -> encoded image over the websocket (--basis DIR), and a
           screenshot of the page beside the JSON
space      the latent space: held-out fidelity (10-fold), path smoothness, jump, plausibility,
           per configuration (paper, default, levers); --basis adds image-space smoothness
prune      pruning rules: albedo, cosine-weighted and raw table change, materials kept, ms per call;
           --basis: image change
fig9       the paper's Fig. 9: perceptual distances from both ends along paths of 20 steps, per preset
           (--configs default,paper) and path kind (straight, uniform, geodesic, faithful); plots beside
           the JSON
paths      speed of the paths: seconds per path of each kind, the latent graph cold and cached
acquire    a material acquired from one photo (merl manifold), judged in a new view and light:
           relative RMSE against the best single material and a plain NNLS fit, time per photo
           (--part tune|held-out|all; --out: its work folder)
measured-space  by device (--database: a folder of merl/, rgl/, nielsen/ databases): projection
           beyond the data against the nearest material, its plausibility, and Manifold.add
"""

import argparse
import json
import os
import time

from mitsuba_manifold.apps.cli.common import ArgumentParser, guarded, parse_indices, parse_list

from . import NAMES

#: Benchmarks that take a saved manifold (the others fit their own).
WITH_MANIFOLD = (
    "interp",
    "bsdf",
    "gi",
    "gi-targets",
    "stability",
    "basis",
    "match",
    "match-render",
    "explore",
    "prune",
    "acquire",
)
#: Options that only some benchmarks use (option's dest -> those benchmarks): refused elsewhere.
ONLY = {
    "materials": ("fit", "pca", "space", "fig9", "paths"),
    "basis": ("match", "explore", "space", "prune"),
    "res": ("match",),
    "out": ("match", "match-render", "acquire"),
    "part": ("acquire",),
    "configs": ("space", "fig9"),
    "folds": ("space",),
    "browser": ("explore",),
    "driver": ("explore",),
}
#: Library parameters named in the benchmarks' messages -> this tool's options.
ALIASES = {"names": "materials", "presets": "configs", "folder": "database"}


@guarded
def main(argv=None):
    p = ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter, aliases=ALIASES
    )
    p.add_argument("which", choices=NAMES)
    p.add_argument("--json", required=True, metavar="OUT", help="write the measurements here")
    p.add_argument(
        "--database",
        default=None,
        help="database: a folder of measured tables or a built-in set (merl, rgl, nielsen, all, sgd; "
        "default merl)",
    )
    p.add_argument("--materials", type=parse_list, default=None, help="subset of materials")
    p.add_argument("--manifold", default=None, help=f"saved manifold ({'/'.join(WITH_MANIFOLD)})")
    p.add_argument(
        "--basis",
        default=None,
        help="match: a full basis of --manifold to time the match on; explore: the basis to serve; "
        "space: a basis of the same materials (image smoothness)",
    )
    p.add_argument(
        "--res",
        type=int,
        default=None,
        help="match: resolution of the accuracy renders (default 128)",
    )
    p.add_argument(
        "--out",
        default=None,
        help="match: folder for its bases, manifolds and renders (default: DATABASE/.manifold-cache/bench_match)",
    )
    p.add_argument(
        "--part",
        choices=("all", "tune", "held-out"),
        default=None,
        help="acquire: the materials judged (tune: those its choices were made on; default all)",
    )
    p.add_argument(
        "--browser", action="store_true", help="explore: time the page in headless Chromium (drags)"
    )
    p.add_argument(
        "--compositing",
        choices=("software", "swiftshader"),
        default="software",
        help="explore --browser: how Chromium composites the page (default software, as Chrome "
        "without a GPU; swiftshader: through SwiftShader GL)",
    )
    p.add_argument(
        "--driver",
        choices=("page", "playwright"),
        default=None,
        help="explore --browser: how the drags' pointer moves reach the page (default page: "
        "pointermove events dispatched in the page at 60 Hz after a real press, as a mouse's; "
        "playwright: a Playwright mouse.move per move, a round trip from this process each)",
    )
    p.add_argument(
        "--configs",
        type=parse_list,
        default=None,
        help="space: configurations to compare; fig9: presets (default: default,paper)",
    )
    p.add_argument(
        "--folds", type=parse_indices, default=None, help="space: run only these of the 10 folds"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --json (or its plot) this tool did not write (never a read-only "
        "file, nor anything but a regular file)",
    )
    args = p.parse_args(argv)
    if args.manifold and args.which not in WITH_MANIFOLD:
        p.error(
            f"{args.which} takes no --manifold (it fits its own); --manifold is for {', '.join(WITH_MANIFOLD)}"
        )
    if args.which == "explore" and not args.basis:
        p.error(
            "explore needs --basis DIR (a basis folder, e.g. out/gi/basis_table_256_64_onepass)"
        )
    for dest, takers in ONLY.items():
        if getattr(args, dest) not in (None, False) and args.which not in takers:
            p.error(f"{args.which} takes no --{dest}; --{dest} is for {', '.join(takers)}")
    check_inputs(args)

    from mitsuba_manifold._util import ownership

    with ownership.Outputs("bench.py", args.force) as guard:
        guard.check(args.json, "--json")  # before the benchmark: nothing of the user's is replaced
        if args.which in ("gi", "scaling", "explore"):
            guard.check(os.path.splitext(args.json)[0] + ".png", "--json's plot")
        run(args)


def database_folder(args):
    """The database a benchmark runs on (``explore``: its basis)."""
    return args.basis if args.which == "explore" else args.database or "merl"


def _spec(folder):
    """How the report names the database: a built-in set by its name, a folder by its path."""
    from mitsuba_manifold.data.database import split_spec
    from mitsuba_manifold.data.sources import SET_NAMES

    return folder if split_spec(folder)[0] in SET_NAMES else os.path.abspath(folder)


def check_inputs(args):
    """Refuse bad files and values (one line naming the option) before any database is made."""
    from .inputs import check

    folder = database_folder(args)
    space = args.which == "space" and args.configs is not None
    if space:
        from .space import CONFIGS
    check(
        args.which,
        folder,
        database_given=True,
        manifold=args.manifold,
        basis=args.basis,
        names=args.materials,
        configs=args.configs if space else None,
        config_choices=CONFIGS if space else (),
        presets=args.configs if args.which == "fig9" else None,
        folds=args.folds,
        res=args.res,
    )


def run(args):
    """Run the benchmark ``args.which`` and write its report to ``--json``."""
    import benchmarks as bench
    from mitsuba_manifold._util.atomic import write_bytes

    from .common import cpu_seconds, machine

    explore = args.which == "explore"
    folder = database_folder(args)
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    cpu0 = cpu_seconds()
    kwargs = (
        {"names": args.materials} if args.which in ("fit", "pca", "space", "fig9", "paths") else {}
    )
    if args.which == "fig9":
        kwargs["plot_stem"] = os.path.splitext(args.json)[0]
        if args.configs:
            kwargs["presets"] = tuple(args.configs)
    if args.which == "space":
        kwargs.update(basis=args.basis, configs=args.configs, folds=args.folds)
    if args.manifold:
        kwargs["manifold"] = args.manifold
    if args.which == "match":
        kwargs.update(basis=args.basis, res=args.res or 128, out=args.out)
    if args.which == "prune":
        kwargs["basis"] = args.basis
    if args.which == "match-render":
        kwargs["out"] = args.out or os.path.splitext(args.json)[0] + "_work"
    if args.which == "acquire":
        kwargs.update(
            out=args.out or os.path.splitext(args.json)[0] + "_work", part=args.part or "all"
        )
    if args.which == "gi":
        kwargs["plot"] = os.path.splitext(args.json)[0] + ".png"
    if args.which == "scaling":
        kwargs["out"] = os.path.splitext(args.json)[0] + "_work"
    if explore:
        kwargs.update(
            screenshot_path=os.path.splitext(args.json)[0] + ".png",
            browser=args.browser,
            compositing=args.compositing,
            driver=args.driver or "page",
        )
    result = bench.run(args.which, folder, **kwargs)
    if args.which == "scaling":
        from .scaling import plot

        result["plot"] = plot(result, os.path.splitext(args.json)[0] + ".png")
    report = {
        "benchmark": args.which,
        "basis" if explore else "database": _spec(folder),
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "wall_s": time.perf_counter() - t0,
        "cpu_s": cpu_seconds() - cpu0,
        "load_average": {"start": load0, "end": os.getloadavg()[0]},
        "result": result,
    }
    text = json.dumps(report, indent=1, default=float)
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    write_bytes(args.json, text)
    print(text)
