"""Acquire a material from photos of a known object under known light (what match.py --render runs).

  match.py --render --manifold M.npz --scene S.xml --image t.exr [--scene S --image T ...]
           [--mask m.png ...] [--sensor 0 ...] [--method plausible|nonneg|convex|latent]
           [--regularisation L] [--spp 64] [--basis-cache DIR] [--bootstrap 16]
           [--out acquired.exr] [--sheet sheet.png] [--snippet material.xml] [--json J.json]

Default (--method plausible): every training material's image in each photo's scene is rendered
once (one pass), the photo is a linear combination of them, and the weights come from a convex
quadratic programme on the relative error over the masks: weights of either sign (combinations
beyond the manifold) with no negative bin and directional albedo at most 1 at every incidence,
a ridge chosen by cross-validation over held-out pixel blocks. --method nonneg keeps every weight
>= 0, convex on the simplex. The report says which outgoing directions and light incidences the
masked pixels show, how much near-equally good answers differ (bootstrap) and warns where the
material is not identifiable. Writes the acquired render (--out; _1, _2, ... for more views), a
contact sheet photo | acquired | best single (--sheet, default beside --out), a manifold_brdf
XML snippet (--snippet) and the result as JSON (--json: `weights` name -> weight, `single`).

--method latent: the paper's search of one latent point (differentiable rendering):
every manifold_brdf of the scenes shares one latent point x, optimised with mi.ad.Adam on the
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

#: Smallest width of a contact sheet's tile: smaller photos are enlarged by whole pixels.
SHEET_TILE = 192


def _parser():
    from ...render.inverse.match_render import INTEGRATORS

    p = ArgumentParser(
        prog="match.py --render",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        aliases={"manifold_path": "manifold", "views": "target", "image": "target"},
        renamed={"--target": "--image"},
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
        help="scene XML or a shipped scene's name (repeat: one per --image, or one for all)",
    )
    p.add_argument(
        "--image",
        "--target",
        dest="target",
        action="append",
        required=True,
        help="an image to match (repeat: one per view): linear .exr, or 8-bit .png/.jpg (sRGB); "
        "--target is its former spelling",
    )
    p.add_argument(
        "--mask", action="append", help="mask per --image (repeat; pixels > 0 are matched)"
    )
    p.add_argument(
        "--sensor", action="append", type=int, help="sensor index per --image (repeat; default 0)"
    )
    p.add_argument("--basis", help="also start from the basis match of the first --image")
    p.add_argument(
        "--database", help="the manifold's tables (folder or built-in set name), when moved"
    )
    p.add_argument(
        "--method",
        default="plausible",
        choices=("plausible", "beyond", "nonneg", "convex", "latent"),
        help="plausible (default): weights >= 0, or beyond them (either sign, no negative bin, "
        "albedo <= 1) where cross-validation says the photo needs it; beyond: always beyond; "
        "nonneg: weights >= 0; convex: on the simplex; latent: the paper's latent-point search",
    )
    p.add_argument(
        "--regularisation",
        type=float,
        default=None,
        help="ridge weight of the acquisition (default: cross-validated)",
    )
    p.add_argument(
        "--basis-cache", help="folder keeping the training materials' images of each scene"
    )
    p.add_argument(
        "--bootstrap",
        type=int,
        default=8,
        help="bootstrap solves of the report's spread (default 8)",
    )
    p.add_argument("--sheet", help="contact sheet photo | acquired | best single (.png)")
    p.add_argument("--snippet", help="Mitsuba XML manifold_brdf of the acquired material (.xml)")
    p.add_argument(
        "--iterations", type=int, default=30, help="Adam iterations per start (default 30)"
    )
    p.add_argument(
        "--spp",
        type=int,
        default=None,
        help="samples per pixel: of the training materials' images (default 64), or of the "
        "latent search's optimisation (default 8)",
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
    p.add_argument(
        "--max-depth",
        type=int,
        default=None,
        help="path depth (latent search: default 4; acquisition: the scene's own)",
    )
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
    from ...render.inverse.match_render import View

    n = len(args.target)
    for name, values, once in (
        ("--scene", args.scene, True),
        ("--mask", args.mask, False),
        ("--sensor", args.sensor, True),
    ):
        if values is not None and len(values) != n and not (once and len(values) == 1):
            fail(
                f"{name} is given {len(values)} times for {n} images to match: give it once per --image"
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
    if args.sheet is not None and not args.sheet.lower().endswith(".png"):
        fail(f"--sheet must name a .png file, got {args.sheet!r}")
    if args.snippet is not None and not args.snippet.lower().endswith(".xml"):
        fail(f"--snippet must name an .xml file, got {args.snippet!r}")
    if args.spp is not None and args.spp < 1:
        fail(f"--spp must be >= 1, got {args.spp}")
    if args.bootstrap < 0:
        fail(f"--bootstrap must be >= 0, got {args.bootstrap}")
    if args.regularisation is not None and not args.regularisation >= 0:
        fail(f"--regularisation must be a number >= 0, got {args.regularisation}")
    from ..._util import ownership

    inputs = args.target + (args.mask or []) + args.scene + [args.manifold]
    extra = [p for p in (args.plot, args.json, _sheet_path(args), args.snippet) if p]
    for path in _out_paths(args, len(args.target)) + extra:
        ownership.check_not_inputs([path], inputs)
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


def _sheet_path(args):
    if args.sheet:
        return args.sheet
    if args.out and args.method != "latent":
        return args.out[:-4] + "_sheet.png"
    return None


def _print_acquisition(r):
    print(
        f"acquired ({r.method}: weights {r.feasible}): relative RMSE {r.error:.4g} over the masks"
    )
    print("largest weights: " + ", ".join(f"{n} {w:+.4f}" for n, w in r.top_weights()))
    print(
        f"best single training material: {r.single['name']}, relative RMSE {r.single['error']:.4g}"
    )
    print(
        f"regularisation: {r.regularisation:.3g}"
        + (" (cross-validated)" if r.cross_validation else "")
    )
    for k, view in enumerate(r.coverage.get("views", [])):
        o = view["theta_o"]
        seen = f"outgoing elevation {o[0]:.0f}-{o[-1]:.0f} deg" if o else "no masked pixel sees it"
        print(f"view {k}: {view['pixels']} pixels, {seen}")
        for light in view["lights"]:
            if "theta_h" in light:
                if light["theta_h"]:
                    print(
                        f"  {light['emitter']}: incidence {light['theta_i'][0]:.0f}-{light['theta_i'][-1]:.0f} deg, "
                        f"half-angle {light['theta_h'][0]:.0f}-{light['theta_h'][-1]:.0f} deg, "
                        f"difference angle {light['theta_d'][0]:.0f}-{light['theta_d'][-1]:.0f} deg"
                    )
                else:
                    print(f"  {light['emitter']}: lights no masked pixel")
            else:
                print(f"  {light['emitter']}: {light['incidence']}")
    if r.spread:
        sp = r.spread
        print(
            f"near-equally good answers ({sp['solutions']} bootstrap solves): albedo "
            + ", ".join(f"{v:.3f}" for v in sp["albedo"])
            + f" (spread {100 * sp['albedo_spread']:.0f}%), specular peak "
            + ", ".join(f"{v:.3g}" for v in sp["peak"])
            + f" (spread {100 * sp['peak_spread']:.0f}%); the photos determine "
            f"{sp['effective_rank']} of {len(r.w)} directions of the weights"
        )
    for w in r.warnings:
        print(f"warning: {w}")
    t = r.timings
    print(
        f"acquisition time: {r.time_s:.1f} s (training images {t.get('training_images_s', 0):.1f} s, "
        f"solve {t.get('solve_s', 0):.1f} s, spread {t.get('spread_s', 0):.1f} s)"
    )


def _acquire(args, views):
    from ..._util import ownership
    from ..._util.atomic import write_bytes
    from ...basis.inverse.acquisition import AcquireOptions
    from ...imaging import io as imageio
    from ...render.inverse.acquire import Photo, acquire

    opts = AcquireOptions(
        method=args.method,
        regularisation=args.regularisation,
        spp=args.spp or 64,
        seed=args.seed,
        max_depth=args.max_depth if args.max_depth_given else None,
        bootstrap=args.bootstrap,
        progress=not args.no_progress,
        basis_cache=args.basis_cache,
    ).check()
    photos = [Photo(v.scene, v.image, v.mask, v.sensor) for v in views]
    got = acquire(photos, args.manifold, opts, database=args.database)
    r = got.result
    _print_acquisition(r)
    written = []
    for path, img in zip(_out_paths(args, len(views)), got.renders):
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        imageio.write_exr(path, img.astype("float32"))
        written.append(path)
        print(f"wrote the acquired material's render: {path}")
    sheet = _sheet_path(args)
    if sheet:
        images, labels = [], []
        for k, (t, a, s) in enumerate(zip(got.photos, got.renders, got.singles)):
            images += [t, a, s]
            labels += [
                f"photo {k}" if len(views) > 1 else "photo",
                f"acquired\n{r.error:.3f}",
                f"{r.single['name']}\n{r.single['error']:.3f}",
            ]
        os.makedirs(os.path.dirname(os.path.abspath(sheet)), exist_ok=True)
        # one tile size for all views, small photos enlarged to be seen
        tiles = imageio.tiles(images, SHEET_TILE)
        imageio.write_contact_sheet(sheet, tiles, labels, columns=3)
        written.append(sheet)
        print(f"wrote contact sheet (photo | acquired | best single): {sheet}")
    if args.snippet:
        write_bytes(args.snippet, r.snippet())
        written.append(args.snippet)
        print(f"wrote the manifold_brdf snippet: {args.snippet}")
    if args.json:
        r.renders = _out_paths(args, len(views))
        r.write(args.json)
        written.append(args.json)
        print(f"wrote JSON: {args.json}")
    ownership.record(written, "match.py")
    return 0


@guarded
def main(argv=None):
    args = _parser().parse_args(argv)
    args.max_depth_given = args.max_depth is not None
    if args.max_depth is None:
        args.max_depth = 4
    _check(args)
    views = _views(args)
    from ...render.scene import scenes

    scenes.use_variant()
    if args.method != "latent":
        for name in ("--plot", "--basis"):
            if getattr(args, name[2:]):
                fail(f"{name} belongs to --method latent")
        return _acquire(args, views)
    from ...render.inverse.match_render import (
        MatchRenderOptions,
        check_options,
        check_views,
        match_render,
    )

    opts = MatchRenderOptions(
        iterations=args.iterations,
        spp=args.spp or 8,
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
                    "target": os.path.abspath(v.image),
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
