"""Render the basis of a scene: base.exr (light paths never touching the manifold material), one
<material>.exr per measured material (light paths touching it exactly once) and, by default in
one-pass mode, the full-GI images <material>.gi.exr and the cross terms cross.npz (where the
scene needs them; --components l1 for the L1- basis only).

Several scenes and views (--views) in one call go to OUT/<scene>[-view<j>]/. With
--chunks k each basis is rendered as k chunks of spp/k samples (seeds seed*k+j) and
merged; --executor ray runs the chunks as Ray tasks (a local cluster, or --address).

Ctrl-C stops within a few seconds (at the end of the current render pass); every image
listed in the folder's manifest.json is complete, and the same command resumes.
"""

import argparse
import sys
import time

from ...basis.sampling import DEFAULT_SPP
from .common import ArgumentParser, guarded, parse_indices, parse_list, parse_point


def parse_views(text):
    """'all' or '0,2' -> 'all' or [0, 2]."""
    if text.strip() == "all":
        return "all"
    try:
        views = parse_indices(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"--views takes 'all' or sensor indices like 0,1, got {text!r}"
        ) from None
    twice = sorted({v for v in views if views.count(v) > 1})
    if twice:
        raise argparse.ArgumentTypeError(
            f"--views lists sensor {twice[0]} more than once ({text!r}): each "
            "view is rendered once, into its own folder"
        )
    return views


def check_numbers(args, spp):
    """``--spp`` (``spp``: the most samples per pixel of any basis), ``--chunks``, ``--res``,
    ``--max-depth`` and ``--seed`` (:func:`mitsuba_manifold.basis.sampling.check_sampling`),
    before any folder is made.
    """
    from ...basis.sampling import check_sampling

    check_sampling(spp, args.chunks, args.mode, args.seed, args.res, args.max_depth)


@guarded
def main(argv=None):
    p = ArgumentParser(
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        aliases={"manifold_path": "manifold"},
    )
    p.add_argument(
        "scenes",
        nargs="+",
        metavar="scene",
        help="Mitsuba scene XML(s) with a manifold_brdf material taking $manifold, or the "
        "name of a shipped scene (table, sphere, cbox)",
    )
    p.add_argument(
        "--manifold",
        default="merl",
        help="saved manifold (.npz), or a shipped one by name (default merl: the shipped "
        "manifold of the 100 MERL materials; the main job's is out/manifold.npz)",
    )
    p.add_argument(
        "--spp",
        type=int,
        default=None,
        help="samples per pixel (default: the scene's own, its sampler's sample_count or the "
        f"default of the $spp it takes; {DEFAULT_SPP} where it declares none)",
    )
    p.add_argument("--materials", type=parse_list, default="all", help="'all' (default) or a,b,...")
    p.add_argument(
        "--near",
        type=parse_point,
        default=None,
        metavar="X",
        help="only the materials within --radius of this latent point (q numbers or a material's "
        "name), and those its own blend needs",
    )
    p.add_argument("--radius", type=float, default=None, help="radius for --near")
    p.add_argument(
        "--mode",
        choices=["onepass", "per-material"],
        default="onepass",
        help="all materials from one set of light paths (default) or one render per material",
    )
    p.add_argument(
        "--components",
        choices=["l1", "full"],
        default="full",
        help="full (default, one-pass mode): also every material's full-GI image and the cross terms "
        "of the pairs blended together, left out where the scene does not need them (a convex "
        "object alone); l1: the L1- images only (faster to render: docs/benchmarks.md)",
    )
    p.add_argument("--res", type=int, default=None, help="square resolution (scenes taking $res)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--max-depth",
        type=int,
        default=None,
        help="path depth (-1: unbounded), overriding the scene's integrator; default: the scene's own "
        "(the basis renders what the scene's integrator does: path or direct, its max_depth, "
        "rr_depth and hide_emitters; Mitsuba's default path, unbounded, where it has none)",
    )
    p.add_argument(
        "--variant",
        default=None,
        help="Mitsuba variant (default: cuda_ad_rgb if usable, else llvm_ad_rgb)",
    )
    p.add_argument(
        "--x",
        type=parse_point,
        default=None,
        metavar="X",
        help="the scene's latent point $x (q numbers or a material's name; default: the first "
        "material's point)",
    )
    p.add_argument(
        "--database",
        default=None,
        help="the manifold's tables (folder or built-in set name), if it moved",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="render into an --out holding files but no basis, and overwrite files there that no "
        "basis listed",
    )
    p.add_argument(
        "--views",
        type=parse_views,
        default=[0],
        help="sensor indices to render, or 'all' (default 0)",
    )
    p.add_argument(
        "--chunks",
        type=int,
        default=1,
        help="render each basis as this many chunks, merged (default 1)",
    )
    p.add_argument(
        "--executor",
        choices=["local", "ray"],
        default="local",
        help="where chunks run: one after another in this process (default) or as Ray tasks",
    )
    p.add_argument(
        "--address", default=None, help="Ray cluster address (default: start a local one)"
    )
    p.add_argument(
        "--aovs",
        action="store_true",
        help="also write aovs.npz (albedo and normal guides for denoised blends)",
    )
    p.add_argument("--keep-chunks", action="store_true", help="keep OUT/.chunks after merging")
    p.add_argument("--out", required=True, help="output folder")
    args = p.parse_args(argv)
    materials = args.materials if args.materials != ["all"] else "all"
    if args.spp is not None:
        check_numbers(args, args.spp)  # before the renderer is imported

    from ...render.jobs.chunks import render_view
    from ...render.jobs.executor import make_executor
    from ...render.jobs.render_basis import (
        BasisOptions,
        FullGI,
        RunBehaviour,
        Sampling,
        SceneSetup,
        Selection,
        check_job_folders,
        plan_views,
        view_spp,
    )
    from ...render.scene.scenes import scene_path

    t0 = time.perf_counter()
    scenes = [scene_path(s) for s in args.scenes]  # a scene XML or a shipped scene's name
    jobs = plan_views(scenes, args.views, args.out)
    spp = view_spp(jobs, args.spp)
    check_numbers(args, max(spp.values()))
    check_job_folders(jobs, args.out, args.force)  # every folder, before the first render
    executor = make_executor(args.executor, args.address)
    options = BasisOptions(
        selection=Selection(materials=materials, near=args.near, radius=args.radius),
        sampling=Sampling(spp=DEFAULT_SPP, seed=args.seed, mode=args.mode),  # per view below
        scene=SceneSetup(
            resolution=args.res,
            max_depth=args.max_depth,
            variant=args.variant,
            x=args.x,
            database=args.database,
        ),
        gi=FullGI(components=args.components),
        run=RunBehaviour(force=args.force, progress=True, aovs=args.aovs),
    )
    try:
        for scene, sensor, out in jobs:
            t1 = time.perf_counter()
            view_options = options.updated(sensor=sensor, spp=spp[scene, sensor])
            manifest = render_view(
                scene, args.manifold, out, view_options, args.chunks, executor, args.keep_chunks
            )
            gi = len(manifest.gi_images or {})
            cross = (manifest.cross.pairs or 0) if manifest.cross else 0
            extra = f" (and {gi} full-GI images, {cross} cross terms)" if gi else ""
            width, height = manifest.resolution
            if args.res is not None and (width, height) != (args.res, args.res):
                print(
                    f"note: {scene} fixes its film's other side: --res {args.res} gave "
                    f"{width}x{height} images (it takes $res for one side, or a crop window)",
                    file=sys.stderr,
                )
            print(
                f"{len(manifest.images)} images{extra} in {out} ({width}x{height}, "
                f"{manifest.spp} spp, {manifest.mode}, {manifest.variant}), "
                f"{time.perf_counter() - t1:.1f} s",
                flush=True,
            )
    finally:
        executor.close()
    if len(jobs) > 1:
        print(f"{len(jobs)} bases in {time.perf_counter() - t0:.1f} s")
