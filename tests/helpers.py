"""Small helpers shared by the test modules (Mitsuba is imported only by those that render)."""

import os
import subprocess
import sys
import textwrap

import numpy as np

from mitsuba_manifold.manifold.model import Manifold

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

Z_MAX = 4.5  # |z| above this fails; P(|N(0,1)| > 4.5) ~ 7e-6 per statistic


def chain(exc):
    """The messages of an exception and of those it was raised from (mi.render and plugins wrap them)."""
    out = []
    while exc is not None:
        out.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return " | ".join(out)


def load(name, manifold, material=None, **params):
    """A scene of scenes/, its manifold material set to a training ``material``."""
    import mitsuba as mi

    from mitsuba_manifold.render import integrators
    from mitsuba_manifold.render.scene import scenes

    scene = mi.load_file(
        scenes.scene_path(name), manifold=manifold, **{k: str(v) for k, v in params.items()}
    )
    if material is not None:
        for bsdf in integrators.manifold_bsdfs(scene):
            bsdf.set_material(material)
    return scene


def integrator(**props):
    import mitsuba as mi

    return mi.load_dict({"type": "manifold_path", **props})


def renders(scene, integ, spp, seeds):
    """Images (K, H, W, C) rendered with the given seeds."""
    import mitsuba as mi

    return np.stack([np.array(mi.render(scene, integrator=integ, spp=spp, seed=s)) for s in seeds])


def mean_var(imgs, block=8):
    """Per-block means and the variance of those means, from K independent images.

    Returns arrays (blocks_y, blocks_x, C) and the whole-image mean/variance (C,).
    """
    k, h, w, c = imgs.shape
    m = imgs.mean(0)
    v = imgs.var(0, ddof=1) / k  # variance of each pixel's mean over the K images
    by, bx = h // block, w // block
    bm = m[: by * block, : bx * block].reshape(by, block, bx, block, c).mean((1, 3))
    bv = v[: by * block, : bx * block].reshape(by, block, bx, block, c).sum((1, 3)) / block**4
    return bm, bv, m.mean((0, 1)), v.sum((0, 1)) / (h * w) ** 2


def z_scores(a, b):
    """z-scores of (a - b) for (mean, var) pairs; 0 where both means are exactly equal."""
    (ma, va), (mb, vb) = a, b
    d = ma - mb
    s = np.sqrt(va + vb)
    return np.where(d == 0, 0.0, d / np.where(s > 0, s, 1e-30))


def assert_same_mean(imgs_a, imgs_b, what):
    ba, bva, ga, gva = mean_var(imgs_a)
    bb, bvb, gb, gvb = mean_var(imgs_b)
    zb = z_scores((ba, bva), (bb, bvb))
    zg = z_scores((ga, gva), (gb, gvb))
    assert np.max(np.abs(zb)) < Z_MAX, f"{what}: block z-scores up to {np.max(np.abs(zb)):.2f}"
    assert np.max(np.abs(zg)) < Z_MAX, f"{what}: image means {ga} vs {gb}, z = {zg}"
    return zb, zg


def midpoint(manifold_path, a, b):
    """Latent point halfway between training materials a and b, as the scenes' x string."""
    m = Manifold.load(manifold_path)
    x = 0.5 * (m.latent[m.names.index(a)] + m.latent[m.names.index(b)])
    return ", ".join(repr(float(v)) for v in x)


def two_spheres(
    manifold, a="white-diffuse-bball", b="gold-paint", interpolation="nearest", rfilter="box"
):
    import mitsuba as mi

    return mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "perspective",
                "fov": 40,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]
                ),
                "film": {
                    "type": "hdrfilm",
                    "width": 32,
                    "height": 32,
                    "rfilter": {"type": rfilter},
                },
                "sampler": {"type": "independent", "sample_count": 16},
            },
            "env": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}},
            "a": {
                "type": "manifold_brdf",
                "manifold": manifold,
                "material": a,
                "interpolation": interpolation,
            },
            "b": {
                "type": "manifold_brdf",
                "manifold": manifold,
                "material": b,
                "interpolation": interpolation,
            },
            "grey": {"type": "diffuse"},
            "sa": {
                "type": "sphere",
                "center": [-0.55, 0, 0],
                "radius": 0.5,
                "bsdf": {"type": "ref", "id": "a"},
            },
            "sb": {
                "type": "sphere",
                "center": [0.55, 0, 0],
                "radius": 0.5,
                "bsdf": {"type": "ref", "id": "b"},
            },
            "floor": {
                "type": "rectangle",
                "bsdf": {"type": "ref", "id": "grey"},
                "to_world": mi.ScalarTransform4f()
                .translate([0, -0.5, 0])
                .rotate([1, 0, 0], -90)
                .scale(3),
            },
        }
    )


def write_basis(folder, manifold_path, images, targets=("material",), scene_text="a"):
    """A basis folder holding ``images`` ({key: float32 (H, W, 3)}) and its manifest, for a
    stand-in scene XML written beside them; returns the scene's path."""
    import os

    from mitsuba_manifold.basis import folder as bf
    from mitsuba_manifold.imaging import io as imageio

    os.makedirs(folder, exist_ok=True)
    scene = os.path.join(folder, "scene.xml")
    with open(scene, "w") as f:
        f.write(f'<scene version="3.0.0"><!-- {scene_text} --><shape type="sphere"/></scene>\n')
    entries = {}
    for key, img in images.items():
        file = key.replace("+", "__") + ".exr"
        imageio.write_exr(os.path.join(folder, file), img)
        entries[key] = bf.ImageEntry(file=file, time_s=0.01)
    h, w = next(iter(images.values())).shape[:2]
    manifest = bf.Manifest.new(
        scene,
        manifold_path,
        bf.RenderSettings(
            resolution=(w, h),
            spp=16,
            variant="llvm_ad_rgb",
            seed=0,
            max_depth=8,
            mode="per-material",
        ),
        targets=list(targets),
        images=entries,
    )
    manifest.write(folder)
    return scene


def run_python(code, imports):
    """Run ``code`` (dedented) in a fresh Python process that imports this checkout, after ``import
    os, signal, sys, time`` and ``imports``: ``(returncode, stdout, stderr)``."""
    head = f"import os, signal, sys, time\nsys.path.insert(0, {ROOT!r})\n{imports}\n"
    p = subprocess.run(
        [sys.executable, "-c", head + textwrap.dedent(code)],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return p.returncode, p.stdout, p.stderr
