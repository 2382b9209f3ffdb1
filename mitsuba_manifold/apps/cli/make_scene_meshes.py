"""Write the generated assets of the shipped scenes: bowl.ply and sky.exr (in the shipped scenes folder, scenes/).

Usage: python tools/make_scene_meshes.py [--out DIR] [--segments 64] [--profile 56]
"""

import os

from .common import ArgumentParser, guarded


@guarded
def main(argv=None):
    from ...render.scenes import SCENES_DIR
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=SCENES_DIR, help="output folder (default: the package's scenes)")
    ap.add_argument("--segments", type=int, default=64, help="bowl segments around the axis")
    ap.add_argument("--profile", type=int, default=56, help="bowl profile points")
    args = ap.parse_args(argv)

    import mitsuba as mi

    from ...render import geometry
    from ...imaging import io as imageio
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")  # write_ply builds the mesh with Mitsuba
    v, f = geometry.bowl(n=args.profile, segments=args.segments)
    path = os.path.join(args.out, "bowl.ply")
    geometry.write_ply(path, v, f)
    print(f"{path}: {len(v)} vertices, {len(f)} triangles, volume {geometry.signed_volume(v, f):.4f}")
    path = os.path.join(args.out, "sky.exr")
    sky = geometry.sky_envmap()
    imageio.write_exr(path, sky)
    print(f"{path}: {sky.shape[1]}x{sky.shape[0]} sky")
