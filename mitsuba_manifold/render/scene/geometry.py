"""Geometry and lighting for the project's example scenes: a bowl mesh and a small sky map.

The bowl is a closed, thick-walled surface of revolution around +y, standing on y = 0:
light that enters it bounces on its inner wall several times, which makes it the
concave test object of the shipped scene ``table.xml`` (paths scattering twice or more off the
material, ``L2+``, are visible there). The sky map is a low-resolution latitude-longitude
environment with a bright sun, so that glossy materials show sharp reflections.

``tools/make_scene_meshes.py`` writes both into the shipped scenes folder (``scenes/``).
"""

import os

import numpy as np

from ..._util.atomic import atomic_replace
from ...errors import InputError

# ------------------------------------------------------------------ bowl


def bowl_profile(radius=1.0, height=0.55, thickness=0.06, exponent=2.4, n=56):
    """Closed profile curve of the bowl in the (r, y) half-plane, sampled by arc length.

    The outer wall is ``y = height * (r / radius) ** exponent`` (flat-bottomed for
    ``exponent > 2``), the inner wall is the same curve scaled to ``radius - thickness``
    and lifted by ``thickness``, and a half circle joins them at the rim.

    Returns
    -------
    r, y : ndarray of float64, shape (n,)
        From the outer bottom centre (r = 0, y = 0) over the rim to the inner bottom
        centre (r = 0, y = thickness). Both ends lie on the axis.
    """
    if not (0 < thickness < radius and height > thickness and exponent >= 1 and n >= 8):
        raise InputError(
            f"bowl_profile: need 0 < thickness ({thickness}) < radius ({radius}), "
            f"height ({height}) > thickness, exponent ({exponent}) >= 1, n ({n}) >= 8"
        )
    m = 2000
    t = np.linspace(0.0, 1.0, m)
    r_in = radius - thickness
    outer = np.stack([radius * t, height * t**exponent], 1)
    inner = np.stack([r_in * t, thickness + (height - thickness) * t**exponent], 1)[::-1]
    a = np.linspace(0.0, np.pi, m // 4)[1:-1]
    c, half = radius - thickness / 2, thickness / 2
    rim = np.stack([c + half * np.cos(a), height + half * np.sin(a)], 1)
    curve = np.concatenate([outer, rim, inner])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve, axis=0), axis=1))])
    u = np.linspace(0.0, s[-1], n)
    return np.interp(u, s, curve[:, 0]), np.interp(u, s, curve[:, 1])


def revolve(r, y, segments=64):
    """Triangle mesh of the surface swept by the profile ``(r, y)`` around the y axis.

    The profile must start and end on the axis (``r[0] == r[-1] == 0``); those ends
    become single pole vertices. Triangles are wound so that normals point to the right
    of the profile's direction of travel (out of the solid for :func:`bowl_profile`).

    Returns
    -------
    vertices : ndarray float32 (V, 3)
    faces : ndarray uint32 (F, 3)
    """
    r = np.asarray(r, float)
    y = np.asarray(y, float)
    if r.shape != y.shape or r.ndim != 1 or len(r) < 3:
        raise InputError("revolve: r and y must be 1-D arrays of equal length >= 3")
    if abs(r[0]) > 1e-12 or abs(r[-1]) > 1e-12 or np.any(r[1:-1] <= 0):
        raise InputError(
            "revolve: the profile must start and end on the axis (r = 0) and stay off it in between"
        )
    if segments < 3:
        raise InputError(f"revolve: segments must be >= 3, got {segments}")
    phi = 2 * np.pi * np.arange(segments) / segments
    ring_r, ring_y = r[1:-1], y[1:-1]
    k = len(ring_r)
    ring = np.stack(
        [
            ring_r[:, None] * np.sin(phi),
            np.broadcast_to(ring_y[:, None], (k, segments)),
            ring_r[:, None] * np.cos(phi),
        ],
        -1,
    ).reshape(-1, 3)
    vertices = np.concatenate([[[0.0, y[0], 0.0]], ring, [[0.0, y[-1], 0.0]]])
    first, last = 0, len(vertices) - 1

    def idx(i, j):  # ring i (0..k-1), segment j (wrapped)
        return 1 + i * segments + (j % segments)

    j = np.arange(segments)
    faces = [np.stack([np.full(segments, first), idx(0, j + 1), idx(0, j)], 1)]
    for i in range(k - 1):
        a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j + 1), idx(i + 1, j)
        faces += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    faces.append(np.stack([idx(k - 1, j), idx(k - 1, j + 1), np.full(segments, last)], 1))
    return vertices.astype(np.float32), np.concatenate(faces).astype(np.uint32)


def signed_volume(vertices, faces):
    """Volume enclosed by a closed triangle mesh; positive when its normals point outwards."""
    v = np.asarray(vertices, float)[np.asarray(faces)]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def bowl(radius=1.0, height=0.55, thickness=0.06, exponent=2.4, n=56, segments=64):
    """Vertices and faces of the bowl (see :func:`bowl_profile`, :func:`revolve`)."""
    return revolve(*bowl_profile(radius, height, thickness, exponent, n), segments)


def write_bowl(path, profile=56, segments=64):
    """Write the shipped scenes' bowl (:func:`bowl`, ``profile`` points turned in ``segments``)
    as PLY (:func:`write_ply`, with Mitsuba's ``scalar_rgb`` where no variant is active);
    returns its ``(vertices, faces)``.
    """
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")  # write_ply builds the mesh with Mitsuba
    v, f = bowl(n=profile, segments=segments)
    write_ply(path, v, f)
    return v, f


def write_ply(path, vertices, faces):
    """Write a triangle mesh as binary PLY with smooth vertex normals (Mitsuba computes them).

    Needs an active Mitsuba variant. The file is written to a temporary name and renamed.
    """
    import mitsuba as mi

    vertices = np.asarray(vertices, np.float32)
    faces = np.asarray(faces, np.uint32)
    if not (np.all(np.isfinite(vertices)) and faces.size and faces.max() < len(vertices)):
        raise InputError(f"write_ply({path}): non-finite vertices or face indices out of range")
    mesh = mi.Mesh(os.path.basename(path), len(vertices), len(faces), has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = type(params["vertex_positions"])(vertices.ravel())
    params["faces"] = type(params["faces"])(faces.ravel())
    params.update()
    mesh.recompute_vertex_normals()
    atomic_replace(path, mesh.write_ply)


# ------------------------------------------------------------------ sky


def sky_envmap(
    width=128, height=64, sun_dir=(0.45, 0.62, 0.64), sun_radiance=300.0, sun_radius_deg=3.0
):
    """Latitude-longitude sky in Mitsuba's ``envmap`` convention (y up), float32 (H, W, 3).

    A blue gradient above the horizon, a brownish ground below, a uniform bright sun disk
    of ``sun_radius_deg`` around ``sun_dir`` (world space, normalised here) with a soft halo.
    """
    if width < 8 or height < 4:
        raise InputError(f"sky_envmap: need width >= 8 and height >= 4, got {width}x{height}")
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    phi, theta = np.meshgrid(2 * np.pi * u, np.pi * v)
    # Mitsuba's envmap: direction (sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi)).
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    up = d[..., 1]
    zenith, horizon = np.array([0.25, 0.45, 0.95]), np.array([0.95, 0.95, 1.0])
    ground = np.array([0.25, 0.2, 0.15])
    t = np.clip(up, 0, 1)[..., None] ** 0.5
    img = np.where(up[..., None] >= 0, horizon * (1 - t) + zenith * t, ground)
    s = np.asarray(sun_dir, float)
    s = s / np.linalg.norm(s)
    cos_a = np.clip(d @ s, -1, 1)
    angle = np.degrees(np.arccos(cos_a))
    img = img + (angle < sun_radius_deg)[..., None] * sun_radiance * np.array([1.0, 0.92, 0.8])
    img = img + 2.0 * np.exp(-((angle / 12.0) ** 2))[..., None] * np.array([1.0, 0.9, 0.7])
    return img.astype(np.float32)
