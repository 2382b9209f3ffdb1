"""Render the L1- basis of a scene: base.exr (paths never touching the manifold material)
and one <material>.exr per measured material (paths touching it exactly once).

Ctrl-C stops within a few seconds (at the end of the current render pass); every image
listed in the folder's manifest.json is complete, and the same command resumes."""

import os
import time

from .common import ERRORS, ArgumentParser, fail, guarded, parse_floats, parse_list


@guarded
def main(argv=None):
    p = ArgumentParser(description=__doc__)
    p.add_argument("scene", help="Mitsuba scene XML with a manifold_brdf material taking $manifold, or the "
                                  "name of a shipped scene (table, sphere, cbox)")
    p.add_argument("--manifold", default="out/manifold.npz", help="saved manifold (default out/manifold.npz)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    p.add_argument("--materials", type=parse_list, default="all", help="'all' (default) or a,b,...")
    p.add_argument("--near", type=parse_floats, default=None, metavar="X", help="only materials near this latent point")
    p.add_argument("--radius", type=float, default=None, help="radius for --near")
    p.add_argument("--mode", choices=["onepass", "per-material"], default="onepass",
                   help="all materials from one set of paths (default) or one render per material")
    p.add_argument("--res", type=int, default=None, help="square resolution (scenes taking $res)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-depth", type=int, default=None, help="path depth (-1: unbounded; default: the scene's $max_depth)")
    p.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb if usable, else llvm_ad_rgb)")
    p.add_argument("--x", type=parse_floats, default=None, metavar="X",
                   help="the scene's latent point $x (q numbers; default: the first material's point)")
    p.add_argument("--database", default=None, help="folder of the manifold's tables, if it moved")
    p.add_argument("--force", action="store_true", help="overwrite files in --out that no basis listed")
    p.add_argument("--out", required=True, help="output folder")
    args = p.parse_args(argv)
    materials = args.materials if args.materials != ["all"] else "all"
    if args.res is not None and not 1 <= args.res <= 16384:
        fail(f"--res must be from 1 to 16384, got {args.res}")

    from ..render_basis import render_basis
    from ..scenes import scene_path
    t0 = time.perf_counter()
    try:
        scene = args.scene if os.path.isfile(args.scene) else scene_path(args.scene)
        manifest = render_basis(scene, args.manifold, args.out, spp=args.spp, materials=materials,
                               near=args.near, radius=args.radius, mode=args.mode, seed=args.seed,
                               resolution=args.res, max_depth=args.max_depth, variant=args.variant,
                               progress=True, x=args.x, database=args.database, force=args.force)
    except ERRORS as e:
        fail(e)
    n = len(manifest["images"])
    print(f"{n} images in {args.out} ({manifest['resolution'][0]}x{manifest['resolution'][1]}, "
          f"{manifest['spp']} spp, {manifest['mode']}, {manifest['variant']}), {time.perf_counter() - t0:.1f} s")

