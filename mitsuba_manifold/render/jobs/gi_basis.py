"""The full-GI part of a one-pass basis: every material's ``touch + L2+`` image
and the cross terms of the pairs blended together, from the paths of the L1- images.

:func:`render_gi` renders them with :meth:`ManifoldPathIntegrator.render_onepass_gi`,
decides what the scene needs (no L2+ where the material cannot see itself: a convex
object alone records no path touching it twice) and writes, beside the L1- images,
``<material>.gi.exr`` (``base + <material>.gi.exr`` is its full-GI image) and
``cross.npz`` (float16 ``C_ij``, :mod:`mitsuba_manifold.basis.crossterms`); the manifest's
``components``, ``left_out`` and ``gi_stats`` say what the basis holds, what it left out
and why, and what was measured (the basis format: :mod:`mitsuba_manifold.basis.folder.manifest`).
"""

import contextlib
import hashlib
import io
import os
import time

import numpy as np

from ..._util.atomic import write_bytes
from ...basis import folder as basis_folder
from ...basis.crossterms import select_pairs
from ...basis.folder.output import image_still_valid
from ...errors import InputError
from ..integrators.multisplats import PairSelection

#: File suffix of a material's full-GI image (``Manifest.gi_images``) and the cross terms' file.
GI_SUFFIX = ".gi.exr"
CROSS_FILE = "cross.npz"


#: L2+ images are left out when their light is below this fraction of the material's.
REST_TOL = 1e-4
#: Default ``levels`` of a full-GI basis whose paths are unbounded (``max_depth`` -1).
MAX_LEVELS = 12


def gi_levels(levels, max_depth):
    """``levels`` of :class:`~.render_basis.FullGI` checked, or by default (None) every
    vertex a path of ``max_depth`` can have (:data:`MAX_LEVELS` for unbounded paths).
    """
    if levels is None:
        return int(max_depth) if int(max_depth) > 0 else MAX_LEVELS
    if isinstance(levels, bool) or not isinstance(levels, (int, np.integer)) or levels < 2:
        raise InputError(
            f"`levels` must be an integer >= 2 (vertices on the material per path), got {levels!r}"
        )
    return int(levels)


def carry_gi(out, manifest):
    """What a resumed full-GI basis keeps of its earlier run: its full-GI images (of materials
    still listed), what it holds and left out, its cross terms, its measurements.
    """
    path = os.path.join(out, basis_folder.MANIFEST)
    if not manifest.images or not os.path.isfile(path):
        return
    old = basis_folder.Manifest.read(out)
    size = tuple(manifest.resolution)  # an image changed since it was written is rendered again
    gi = {
        k: e
        for k, e in (old.gi_images or {}).items()
        if k in manifest.images and image_still_valid(out, e, size)
    }
    if gi:
        manifest.gi_images = gi
    for key in ("components", "left_out", "cross", "gi_stats"):
        if getattr(old, key) is not None:
            setattr(manifest, key, getattr(old, key))


def write_cross(path, pairs, images):
    """Write the cross terms ``images`` (P, H, W, 3; stored as float16) of ``pairs`` to ``path``
    atomically; returns the file's SHA-256, recorded in the manifest so that an edited or
    replaced file is refused when read (:meth:`~mitsuba_manifold.basis.folder.Basis.cross_terms`).
    """
    buf = io.BytesIO()
    np.savez(buf, pairs=np.asarray(pairs, dtype=str), images=np.asarray(images).astype(np.float16))
    data = buf.getvalue()
    write_bytes(path, data)
    return hashlib.sha256(data).hexdigest()


def describe_components(manifest):
    """One line per component: what the basis holds, and what it left out and why."""
    held = ", ".join(manifest.held_components)
    lines = [
        f"basis holds: {held}"
        + (f" (levels <= {manifest.levels})" if manifest.levels is not None else "")
    ]
    for comp, why in (manifest.left_out or {}).items():
        lines.append(f"left out {comp}: {why}")
    return "\n".join(lines)


@contextlib.contextmanager
def progress_bar(desc, enabled, stop):
    """A tqdm bar; yields ``advance(done, total)`` for the renderers' ``progress`` (which also
    honours Ctrl-C through ``stop``).
    """
    from tqdm import tqdm

    with tqdm(desc=desc, unit="step", disable=not enabled) as bar:

        def advance(done, total):
            stop.check()
            bar.total = total
            bar.update(done - bar.n)

        yield advance


def _integrator(paths):
    """A ``manifold_path`` rendering the paths of the scene's integrator (:class:`~.scenes.SceneIntegrator`)."""
    import mitsuba as mi

    return mi.load_dict({"type": "manifold_path", "component": "l1", **paths.path_properties()})


def needs_rest(paths, touch, rest, tol):
    """``(needed, why)``: whether the L2+ images carry light (their sum above ``tol`` of the
    material's), with the measurement that says so.
    """
    total = int(np.sum(paths))
    twice = int(np.sum(paths[2:]))
    lit = sum(float(np.sum(v)) for v in touch.values()) + sum(
        float(np.sum(v)) for v in rest.values()
    )
    frac = sum(float(np.sum(v)) for v in rest.values()) / lit if lit > 0 else 0.0
    if twice == 0:
        return (
            False,
            (
                f"the material cannot see itself: none of {total} paths touched it twice "
                "(L2+ is exactly 0)"
            ),
            frac,
        )
    if abs(frac) < tol:
        return (
            False,
            (
                f"L2+ is {frac:.2e} of the material's light (below {tol:g}; {twice} of {total} "
                "paths touched it twice or more)"
            ),
            frac,
        )
    return True, "", frac


def render_gi(scene, manifold, todo, o, paths, out, manifest, save, stop):
    """Render every material of ``todo`` (all of the basis's) with full GI from one pass and
    write the images, the cross terms and the manifest's account of them (see the module).
    ``paths``: the scene's integrator settings (:class:`~.scenes.SceneIntegrator`).
    """
    names = [combo[0] for _, combo in todo if combo is not None]
    keys = {combo[0]: key for key, combo in todo if combo is not None}
    pairs, pstats = select_pairs(manifold, names, tol=o.gi.cross_tol)
    products = tuple(pstats.pop("products"))
    select = PairSelection(products, tol=o.gi.cross_light_tol) if o.gi.cross_light_tol else None
    if o.gi.cross_keep is not None:  # a later chunk: the first chunk's pairs
        index = {tuple(p): k for k, p in enumerate(pairs)}
        select = PairSelection(
            products, tol=o.gi.cross_light_tol, keep=tuple(index[tuple(p)] for p in o.gi.cross_keep)
        )
    t0 = time.perf_counter()
    with progress_bar("rendering basis (one pass, full GI)", o.run.progress, stop) as advance:
        kwargs = {
            "progress": advance,
            "cross_fraction": o.gi.cross_fraction,
            "pair_selection": select,
        }
        if o.sampling.chunk_spp:
            kwargs["spp_per_pass"] = o.sampling.chunk_spp
        r = _integrator(paths).render_onepass_gi(
            scene,
            materials=names,
            spp=o.sampling.spp,
            seed=o.sampling.seed,
            sensor=int(o.scene.sensor),
            levels=o.gi.levels,
            pairs=pairs,
            **kwargs,
        )
    seconds = time.perf_counter() - t0
    per = seconds / max(len(todo), 1)
    needed, why, frac = needs_rest(r.paths, r.touch, r.rest, REST_TOL)
    needed = needed or o.gi.cross_keep is not None  # a later chunk: the first chunk stored L2+
    stats = {
        "render_s": round(seconds, 3),
        "levels": int(o.gi.levels),
        "paths_by_touches": [int(v) for v in r.paths],
        "cut_fraction": float(r.paths[-1] / max(1, r.paths.sum())),
        "rest_fraction": frac,
        "pairs": pstats,
        "cross_fraction": float(o.gi.cross_fraction),
        "pair_selection": r.selection,
    }
    images = {keys[n]: np.asarray(r.touch[n], np.float32) for n in names}
    if any(combo is None for _, combo in todo):
        images[basis_folder.BASE] = np.asarray(r.base, np.float32)
    left = {}
    if needed:
        manifest.components = ["l1", "l2+"]
    else:
        manifest.components = ["l1"]
        left["l2+"] = why
        left["cross"] = "no L2+ images"
    manifest.left_out = left
    manifest.gi_stats = stats
    save(images, per)
    if not needed:
        return
    save(
        {keys[n]: np.asarray(r.touch[n] + r.rest[n], np.float32) for n in names},
        per,
        section="gi_images",
        suffix=GI_SUFFIX,
    )
    if r.cross:
        digest = write_cross(
            os.path.join(out, CROSS_FILE), list(r.cross), np.stack([r.cross[p] for p in r.cross])
        )
        manifest.cross = basis_folder.CrossEntry(
            file=CROSS_FILE, pairs=len(r.cross), tol=float(o.gi.cross_tol), sha256=digest
        )
        manifest.components = ["l1", "l2+", "cross"]
    else:
        sel = r.selection or {}
        left["cross"] = (
            f"none of {sel['candidates']} candidate pairs would change its L2+ light by "
            f"{sel['tol']:g} (largest {sel['largest_left_out']:.2g})"
            if sel.get("candidates")
            else f"no pair of materials reaches a weight product of {o.gi.cross_tol:g} in the explored region"
        )
    manifest.write(out)
