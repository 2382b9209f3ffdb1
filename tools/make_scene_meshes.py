"""Write the generated assets of the example scenes: scenes/bowl.ply and scenes/sky.exr.

Usage: python tools/make_scene_meshes.py [--out scenes] [--segments 64] [--profile 56]
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main(argv=None):
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(root, "scenes"), help="output folder")
    ap.add_argument("--segments", type=int, default=64, help="bowl segments around the axis")
    ap.add_argument("--profile", type=int, default=56, help="bowl profile points")
    args = ap.parse_args(argv)

    from mitsuba_manifold import geometry, imageio
    import mitsuba as mi
    mi.set_variant("scalar_rgb")

    v, f = geometry.bowl(n=args.profile, segments=args.segments)
    path = os.path.join(args.out, "bowl.ply")
    geometry.write_ply(path, v, f)
    print(f"{path}: {len(v)} vertices, {len(f)} triangles, volume {geometry.signed_volume(v, f):.4f}")
    path = os.path.join(args.out, "sky.exr")
    imageio.write_exr(path, geometry.sky_envmap())
    print(f"{path}: {geometry.sky_envmap().shape[1]}x{geometry.sky_envmap().shape[0]} sky")


if __name__ == "__main__":
    main()
