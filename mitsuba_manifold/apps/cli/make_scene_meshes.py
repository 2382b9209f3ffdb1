"""Write the generated assets of the shipped scenes: bowl.ply and sky.exr (in the shipped scenes folder, scenes/).

Usage: python tools/make_scene_meshes.py [--out DIR] [--segments 64] [--profile 56]
"""

import os

from .common import ArgumentParser, guarded


@guarded
def main(argv=None):
    from ...render.scene.scenes import SCENES_DIR

    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", default=SCENES_DIR, help="output folder (default: the package's scenes)"
    )
    ap.add_argument("--segments", type=int, default=64, help="bowl segments around the axis")
    ap.add_argument("--profile", type=int, default=56, help="bowl profile points")
    ap.add_argument(
        "--force",
        action="store_true",
        help="replace a bowl.ply or sky.exr this tool did not write (never a read-only file, nor "
        "anything but a regular file); without it, one of the same content is left as it is",
    )
    args = ap.parse_args(argv)

    from ..._util import checks as validate
    from ..._util import ownership

    validate.positive_int("--segments", args.segments, "64")
    validate.positive_int("--profile", args.profile, "56")
    validate.output_folder("--out", args.out)
    bowl, sky = os.path.join(args.out, "bowl.ply"), os.path.join(args.out, "sky.exr")
    with ownership.Outputs("make_scene_meshes.py", args.force) as guard:
        for path in (bowl, sky):  # the shipped files: refused only if what is written differs
            guard.check(path, "output", identical=True)
        os.makedirs(args.out, exist_ok=True)
        write_assets(args, bowl, sky, guard)


def write_assets(args, bowl, sky, guard):
    """Write the bowl mesh and the sky map (under ``guard``, :class:`ownership.Outputs`)."""
    from ...imaging import io as imageio
    from ...render.scene import geometry

    v, f = geometry.write_bowl(bowl, args.profile, args.segments)
    note = " (unchanged)" if bowl in guard.kept else ""
    print(
        f"{bowl}{note}: {len(v)} vertices, {len(f)} triangles, volume {geometry.signed_volume(v, f):.4f}"
    )
    image = geometry.sky_envmap()
    imageio.write_exr(sky, image)
    note = " (unchanged)" if sky in guard.kept else ""
    print(f"{sky}{note}: {image.shape[1]}x{image.shape[0]} sky")
