"""Find the latent point whose full-GI renders best match target images (differentiable rendering,
no basis): what match.py --render runs.

  match.py --render --manifold M.npz --scene cbox.xml --target t.exr [--scene S --target T ...]
           [--mask m.png ...] [--sensor 0 ...] [--basis DIR] [--iterations 30] [--spp 8]
           [--eval-spp 64] [--starts 3] [--scan-spp 16] [--lr L] [--exposure-free] [--max-depth 4]
           [--integrator prb] [--out best.exr] [--plot convergence.png] [--json match.json]

Every manifold_brdf of the scenes shares one latent point x, optimised with mi.ad.Adam on the
relative MSE over the masks (a progress bar shows the loss). Starts: a scan renders every
training material alone (--scan-spp, two independent renders), estimates any blend's error from
them free of the render noise, optimises that estimate and checks the best points with true
renders (moved off a training point, where the weights' gradient is 0); and the basis match
(--basis). Prints the point, its nearest training materials,
its largest weights and the image error; x itself is not identifiable from one image (several
points give near-identical weights). Writes the render at the best point (--out; one file per
view, _1, _2, ... beside the first), a convergence plot (--plot) and everything as JSON (--json).
Nothing is written until the match has succeeded.
"""

import argparse
import json
import os

from .common import ArgumentParser, fail, guarded


def _parser():
    from ...render.match_render import INTEGRATORS

    p = ArgumentParser(
        prog="match.py --render",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        aliases={"manifold_path": "manifold", "views": "target"},
    )
    p.add_argument(
        "--manifold",
        required=True,
        help="the manifold (.npz, or a shipped one by name: merl, rgl, nielsen, all) of the "
        "scenes' manifold_brdf",
    )
    p.add_argument(
        "--scene",
        action="append",
        required=True,
        help="scene XML or a shipped scene's name (repeat: one per --target, or one for all)",
    )
    p.add_argument(
        "--target",
        action="append",
        required=True,
        help="target image (repeat): linear .exr, or 8-bit .png/.jpg (sRGB)",
    )
    p.add_argument(
        "--mask", action="append", help="mask per target (repeat; pixels > 0 are matched)"
    )
    p.add_argument(
        "--sensor", action="append", type=int, help="sensor index per target (repeat; default 0)"
    )
    p.add_argument("--basis", help="also start from the basis match of the first target")
    p.add_argument(
        "--database", help="the manifold's tables (folder or built-in set name), when moved"
    )
    p.add_argument(
        "--iterations", type=int, default=30, help="Adam iterations per start (default 30)"
    )
    p.add_argument(
        "--spp", type=int, default=8, help="samples per pixel of the optimisation (default 8)"
    )
    p.add_argument(
        "--eval-spp",
        type=int,
        default=64,
        help="samples per pixel of the final renders (default 64)",
    )
    p.add_argument("--starts", type=int, default=3, help="starts from the scan (default 3)")
    p.add_argument(
        "--scan-spp",
        type=int,
        default=16,
        help="samples per pixel of each training material's scan renders, split over two (default 16)",
    )
    p.add_argument(
        "--lr", type=float, default=None, help="Adam's step in latent units (default: the data's)"
    )
    p.add_argument(
        "--exposure-free", dest="exposure", action="store_true", help="fit a brightness scale too"
    )
    p.add_argument("--max-depth", type=int, default=4, help="path depth (default 4)")
    p.add_argument(
        "--integrator",
        default="prb",
        help=f"Mitsuba AD integrator: {', '.join(INTEGRATORS)} (default prb)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--out", help="render at the best point (.exr)")
    p.add_argument("--plot", help="convergence plot (.png)")
    p.add_argument("--json", metavar="OUT", help="write the result as JSON")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace existing output files this tool did not write (never read-only ones)",
    )
    return p


def _views(args):
    from ...render.match_render import View

    n = len(args.target)
    for name, values, once in (
        ("--scene", args.scene, True),
        ("--mask", args.mask, False),
        ("--sensor", args.sensor, True),
    ):
        if values is not None and len(values) != n and not (once and len(values) == 1):
            fail(
                f"{name} is given {len(values)} times for {n} targets: give it once per target"
                + (" or once for all" if once else "")
            )
    scenes = args.scene * n if len(args.scene) == 1 else args.scene
    sensors = args.sensor * n if args.sensor and len(args.sensor) == 1 else (args.sensor or [0] * n)
    masks = args.mask or [None] * n
    return [View(s, t, m, i) for s, t, m, i in zip(scenes, args.target, masks, sensors)]


def _out_paths(args, n):
    if not args.out:
        return []
    stem = args.out[:-4]
    return [args.out] + [f"{stem}_{i}.exr" for i in range(1, n)]


def _check(args):
    if args.out is not None and not args.out.lower().endswith(".exr"):
        fail(f"--out must name an .exr file, got {args.out!r}")
    if args.plot is not None and not args.plot.lower().endswith(".png"):
        fail(f"--plot must name a .png file, got {args.plot!r}")
    if args.json is not None and not args.json.lower().endswith(".json"):
        fail(f"--json must name a .json file, got {args.json!r}")
    from ..._util import ownership

    inputs = {
        os.path.realpath(p) for p in args.target + (args.mask or []) + args.scene + [args.manifold]
    }
    for path in _out_paths(args, len(args.target)) + [p for p in (args.plot, args.json) if p]:
        if os.path.realpath(path) in inputs:
            fail(f"output {path} would overwrite an input; choose another path")
        ownership.check_replaceable(path, args.force, what="output")


def _report(r, manifold):
    print("best latent point: x = " + ", ".join(f"{v:.4f}" for v in r.x))
    print(
        "nearest training materials: " + ", ".join(f"{n} ({d:.3f})" for n, d in r.nearest(manifold))
    )
    print("largest weights: " + ", ".join(f"{n} {w:+.4f}" for n, w in r.top_weights()))
    views = ", ".join(f"{e:.4g}" for e in r.errors)
    print(
        f"image error: relative MSE {r.error:.4g} (per view: {views})"
        + (f", fitted exposure x{r.exposure:.4g}" if r.exposure != 1.0 else "")
    )
    print(
        f"best single training material: {r.single['name']}, relative MSE {r.single['error']:.4g}"
    )
    if r.extra.get("from_start") is None:
        print("the best single material itself is the best point")
    print(
        f"match time: {r.time_s:.1f} s ({len(r.history)} starts, {r.time_per_iteration_s:.3f} s per iteration)"
    )
    print("note: x is not identifiable from one image; compare the weights and the image error")


@guarded
def main(argv=None):
    args = _parser().parse_args(argv)
    _check(args)
    views = _views(args)
    from ...render import scenes

    scenes.use_variant()
    from ...render.match_render import MatchRenderOptions, check_options, check_views, match_render

    opts = MatchRenderOptions(
        iterations=args.iterations,
        spp=args.spp,
        eval_spp=args.eval_spp,
        starts=args.starts,
        scan_spp=args.scan_spp,
        lr=args.lr,
        exposure=args.exposure,
        max_depth=args.max_depth,
        integrator=args.integrator,
        seed=args.seed,
        progress=not args.no_progress,
        plot=args.plot,
    )
    check_options(opts)  # bad settings are refused before anything is created or rendered
    views = check_views(views)
    if args.plot:
        os.makedirs(os.path.dirname(os.path.abspath(args.plot)), exist_ok=True)
    r = match_render(views, args.manifold, opts, basis=args.basis, database=args.database)
    from ...manifold.model import Manifold

    manifold = Manifold.load(args.manifold)
    _report(r, manifold)
    from ..._util import ownership
    from ..._util.atomic import write_bytes
    from ...imaging import io as imageio

    written = [args.plot] if args.plot else []
    for path, img in zip(_out_paths(args, len(views)), r.images):
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        imageio.write_exr(path, img)
        written.append(path)
        print(f"wrote render at the best point: {path}")
    if args.json:
        info = r.to_dict(manifold)
        info.update(
            views=[
                {
                    "scene": os.path.abspath(v.scene),
                    "target": os.path.abspath(v.target),
                    "mask": v.mask and os.path.abspath(v.mask),
                    "sensor": v.sensor,
                }
                for v in views
            ],
            renders=_out_paths(args, len(views)),
        )
        write_bytes(args.json, json.dumps(info, indent=1, default=float) + "\n")
        written.append(args.json)
        print(f"wrote JSON: {args.json}")
    if args.plot:
        print(f"wrote convergence plot: {args.plot}")
    ownership.record(written, "match.py")
    return 0
