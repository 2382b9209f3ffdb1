"""The preview sphere's environment: a small procedural HDRI, shipped with the page.

No HDRI file comes with the package (none may be downloaded here), so :func:`studio` makes
one: an equirectangular sky (zenith blue to a warm horizon), a sun, two soft studio panels
and a grey ground, at :data:`WIDTH` x :data:`HEIGHT`. The page lights the sphere with it as
:data:`LIGHTS` directional lights found by median cut (P. Debevec, "A median cut algorithm
for light probe sampling", SIGGRAPH 2005 poster: split the map into regions of equal energy,
one light per region at its energy centroid carrying its whole irradiance), plus the key
light the user drags; the map itself shows behind the sphere. :func:`write` writes
``static/env/studio.json`` (lights, size) and ``studio.f16`` (float16 RGB, top row up);
``tests/apps`` checks that the shipped files are this module's output.

Directions: ``y`` up, ``z`` towards the viewer; pixel ``(i, j)`` is at polar angle
``theta = (i + 0.5) / H * pi`` from ``+y`` and azimuth ``phi = (j + 0.5) / W * 2 pi - pi``
from ``+z`` towards ``+x``.
"""

import json
import os

import numpy as np

WIDTH, HEIGHT = 128, 64
#: Lights of the median cut at rest and while dragging (a software rasteriser keeps up).
LIGHTS = (16, 8)
#: Irradiance on an upward surface (so a white diffuse sphere is lit about as by the old key light).
UP_IRRADIANCE = 0.7 * np.pi
FOLDER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static", "env")


def directions(width=WIDTH, height=HEIGHT):
    """Unit directions ``(H, W, 3)`` of the pixel centres and their solid angles ``(H, 1)``."""
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi - np.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], axis=-1)
    omega = (2 * np.pi / width) * (np.pi / height) * np.sin(theta)[:, None]
    return d, omega


def _panel(d, phi, elevation, half_width, half_height):
    """Mask of a rectangular panel centred at azimuth ``phi``, ``elevation`` (radians)."""
    az = np.arctan2(d[..., 0], d[..., 2])
    el = np.arcsin(np.clip(d[..., 1], -1, 1))
    off = np.angle(np.exp(1j * (az - phi)))
    return (np.abs(off) < half_width) & (np.abs(el - elevation) < half_height)


def studio(width=WIDTH, height=HEIGHT):
    """The environment: linear RGB float32 ``(H, W, 3)`` (see the module doc)."""
    d, omega = directions(width, height)
    up = d[..., 1:2]
    sky = np.where(
        up > 0,
        (1 - up) ** 3 * np.array([1.0, 0.82, 0.62])
        + (1 - (1 - up) ** 3) * np.array([0.32, 0.48, 0.85]),
        0.0,
    )
    ground = np.where(up <= 0, (0.16 + 0.1 * (1 + up)) * np.array([0.55, 0.5, 0.45]), 0.0)
    env = 0.9 * sky + ground
    sun_dir = np.array([np.sin(-0.9) * np.cos(0.62), np.sin(0.62), np.cos(-0.9) * np.cos(0.62)])
    sun = (d @ sun_dir) > np.cos(np.radians(4.0))
    env[sun] = np.array([1.0, 0.93, 0.8]) * 60.0
    env[_panel(d, 1.25, 0.25, 0.35, 0.22)] = (
        np.array([1.0, 0.97, 0.92]) * 3.0
    )  # key panel, front right
    env[_panel(d, np.pi, 0.5, 0.5, 0.15)] = np.array([0.85, 0.92, 1.0]) * 2.0  # rim strip behind
    e_up = float((env[..., 1] * np.clip(up[..., 0], 0, None) * omega).sum())
    return (env * (UP_IRRADIANCE / e_up)).astype(np.float32)


def median_cut(env, count):
    """``count`` (a power of 2) lights of ``env``: directions ``(count, 3)`` and RGB irradiance
    ``(count, 3)`` (the sum of ``L dw`` over each region).
    """
    h, w, _ = env.shape
    d, omega = directions(w, h)
    energy = env.mean(axis=-1) * omega
    sin = np.sin((np.arange(h) + 0.5) / h * np.pi)
    regions = [(0, h, 0, w)]
    while len(regions) < count:
        out = []
        for r0, r1, c0, c1 in regions:
            e = energy[r0:r1, c0:c1]
            wide = (c1 - c0) * sin[r0:r1].max() * 2 > (
                r1 - r0
            ) * 2  # an equirect column is narrower near the poles
            line = np.cumsum(e.sum(axis=0 if wide else 1))
            k = int(np.clip(np.searchsorted(line, line[-1] / 2) + 1, 1, len(line) - 1))
            out += (
                [(r0, r1, c0, c0 + k), (r0, r1, c0 + k, c1)]
                if wide
                else [(r0, r0 + k, c0, c1), (r0 + k, r1, c0, c1)]
            )
        regions = out
    dirs, power = [], []
    for r0, r1, c0, c1 in regions:
        e = energy[r0:r1, c0:c1, None]
        v = (d[r0:r1, c0:c1] * e).sum(axis=(0, 1))
        dirs.append(v / max(np.linalg.norm(v), 1e-12))
        power.append((env[r0:r1, c0:c1] * omega[r0:r1, :, None]).sum(axis=(0, 1)))
    return np.array(dirs), np.array(power)


def describe(env):
    """The JSON of :func:`write` for ``env``."""
    h, w, _ = env.shape
    out = {
        "width": w,
        "height": h,
        "format": "float16 RGB, row-major, top row up (studio.f16)",
        "lights": {},
    }
    for n in LIGHTS:
        dirs, power = median_cut(env, n)
        out["lights"][str(n)] = [
            {"dir": [round(float(v), 6) for v in dv], "power": [round(float(v), 6) for v in p]}
            for dv, p in zip(dirs, power)
        ]
    return out


def write(folder=FOLDER):
    """Write ``studio.json`` and ``studio.f16`` into ``folder``; returns their paths."""
    from ..._util.atomic import write_bytes

    env = studio()
    os.makedirs(folder, exist_ok=True)
    paths = os.path.join(folder, "studio.json"), os.path.join(folder, "studio.f16")
    write_bytes(paths[0], (json.dumps(describe(env), indent=1) + "\n").encode())
    write_bytes(paths[1], env.astype("<f2").tobytes())
    return paths


def scene_environment(scene_path, manifold_path, basis):
    """``(float16 RGB bytes, meta)``: the environment light of a basis's scene in the preview
    sphere's frame, as the basis's camera sees it (:meth:`Explorer.environment`): direction
    ``d`` of :func:`directions` is the camera's ``(-d_x, d_y, -d_z)`` (its ``+z`` looks into the
    scene, ``+x`` to the left), the scene's environment emitter evaluated there. Raises
    InputError when the scene has no environment emitter.
    """
    import mitsuba as mi

    from ...errors import InputError
    from ...render.scene.scenes import load_scene, scene_resolution

    loaded = load_scene(
        scene_path,
        manifold_path,
        1,
        scene_resolution(basis.manifest),
        basis.manifest.max_depth,
        None,
        basis.manifest.variant,
        sensor=basis.sensor,
    )
    scene = loaded.scene
    emitter = scene.environment()
    if emitter is None:
        raise InputError(
            f"the scene {os.path.basename(scene_path)} has no environment light (envmap or constant): "
            "light the sphere with the studio environment"
        )
    to_world = np.array(scene.sensors()[basis.sensor].world_transform().matrix, dtype=np.float64)[
        ..., 0
    ]
    rot = to_world[:3, :3]
    d, _ = directions()
    cam = np.stack([-d[..., 0], d[..., 1], -d[..., 2]], axis=-1).reshape(-1, 3)
    world = cam @ rot.T
    world /= np.linalg.norm(world, axis=1, keepdims=True)
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*(-world).T.astype(np.float32))
    rgb = np.array(emitter.eval(si), dtype=np.float32).reshape(3, -1).T.reshape(HEIGHT, WIDTH, 3)
    centre = _targets_centre(loaded)
    lights = []
    for (
        e
    ) in scene.emitters():  # point lights: a direction and the irradiance they give at the material
        params = mi.traverse(e)
        if e.is_environment() or "position" not in params or "intensity.value" not in params:
            continue
        v = np.array(params["position"], dtype=np.float64).reshape(3) - centre
        dist2 = float(v @ v)
        c = np.linalg.solve(rot, v / np.sqrt(dist2))  # in the camera's frame
        intensity = np.array(params["intensity.value"], dtype=np.float64).reshape(3)
        lights.append(
            {
                "dir": [float(-c[0]), float(c[1]), float(-c[2])],
                "irradiance": (intensity / dist2).tolist(),
            }
        )
    meta = {"width": WIDTH, "height": HEIGHT, "emitter": type(emitter).__name__, "lights": lights}
    return np.clip(rgb, 0, 65504).astype("<f2").tobytes(), meta


def _targets_centre(loaded):
    """Centre of the bounding box of the shapes made of the scene's manifold material."""
    targets = {id(b) for b in loaded.targets}
    boxes = [
        s.bbox() for s in loaded.scene.shapes() if s.bsdf() is not None and id(s.bsdf()) in targets
    ]
    if not boxes:
        boxes = [loaded.scene.bbox()]
    lo = np.min([np.array(b.min, dtype=np.float64).reshape(3) for b in boxes], axis=0)
    hi = np.max([np.array(b.max, dtype=np.float64).reshape(3) for b in boxes], axis=0)
    return 0.5 * (lo + hi)


if (
    __name__ == "__main__"
):  # regenerate the shipped files: python3 -m mitsuba_manifold.apps.explore.hdri
    print(*write())
