"""One-pass basis rendering: the base image and every material's touch image from one set of paths.

For paths scattering once off the target, the material enters only at that vertex
(paper Sec. 5.2): the paths are traced once with a sampling density that
covers every material, that vertex is recorded, and each material's image is a sparse
product ``(pixels x bins) @ (bins x materials)`` of the recorded *splats* with the
tables. :class:`TableSplats` computes it directly (nearest lookups; each splat in every pixel
of its sample's filter footprint, weighted as the film weighs the sample), :class:`FilterSplats`
through image blocks with the film's filter (``linear`` lookups).

:func:`render_onepass_gi` lets the same paths go on after their second vertex on the target:
every vertex there is sampled with the proxy and recorded (:mod:`.records`), and each
material's ``L2+`` image is the sum over splats of ``a prod_j f_i(b_j)`` (:mod:`.multisplats`),
so that ``base + touch_i + rest_i`` is material ``i``'s full-GI image.
"""

import os
import threading
from dataclasses import dataclass
from typing import NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np

from ...errors import InputError
from .common import (
    TracePlan,
    developed_rgb,
    group_carriers,
    is_manifold_bsdf,
    is_plain_twosided,
    target_groups,
)
from .multisplats import MultiSplats
from .proxy import POINT, sampling_proxy, with_point  # noqa: F401 (POINT: re-exported)
from .splats import PACKET, FilterSplats, TableSplats


def _prefetch(path, block=1 << 24):
    """Read ``path`` in a background thread, so that it is in the page cache when needed."""

    def run():
        try:
            buf = bytearray(block)
            with open(path, "rb", buffering=0) as f:
                while f.readinto(buf):
                    pass
        except OSError:
            pass

    threading.Thread(target=run, daemon=True).start()


@dataclass(frozen=True)
class PassSettings:
    """How a one-pass render splits its work into passes and kernels.

    Parameters
    ----------
    chunk : int, optional
        Materials per kernel (default: all of them with the table product, 16
        otherwise).
    max_samples : int
        Most paths traced at once (passes of whole samples per pixel).
    spp_per_pass : int, optional
        Samples per pixel per pass, instead of the most that ``max_samples`` allows.
    """

    chunk: int | None = None
    max_samples: int = 1 << 22
    spp_per_pass: int | None = None


def render_onepass(
    integrator,
    scene,
    materials=None,
    spp=0,
    seed=0,
    sensor=0,
    settings=None,
    progress=None,
):
    """Render the base image and every material's touch image from one set of paths.

    For paths scattering once off the target, the material enters only at that
    vertex. The paths are traced once; on the target they sample a density
    ``q`` that covers every material (the ``manifold_brdf`` sampling density of the
    mixture ``sum_i P_i / |P_i|`` of the per-material densities, plus its cosine
    fraction), and that vertex is recorded (:meth:`ManifoldPathIntegrator.trace_paths`). Its two directions (the
    light connection, the sampled one) become two *splats* per sample, kept where
    they carry light: a pixel, a MERL bin, an RGB amplitude ``a``. A material adds
    ``a * table(bin)`` to the pixel, so the images are a sparse product
    ``(pixels x bins) @ (bins x materials)``.

    With ``nearest`` lookups (the default), that product is
    computed directly: the tables, interleaved by bin (``Database.material_rows``,
    cached beside the database), give all materials' values at a bin in one
    contiguous read; the splats are sorted by bin, so the tables are read in order;
    one Dr.Jit kernel per group of ``chunk`` materials adds ``a * row`` into
    per-pixel sums (scatter-adds into per-thread copies, ``ReduceMode.Expand``),
    over tiles of pixels small enough to bound that memory; a splat goes to every pixel of its
    sample's filter footprint with the filter's weight there (:class:`.splats.FilterTaps`:
    one pixel for the box filter, about 16 for Mitsuba's default Gaussian). With ``linear`` lookups
    each material is evaluated at the splats by the BSDF's own ``eval`` and splatted with the
    film's filter. Either way the images are normalised by the filter weights of all samples, as
    the film does: pixel ``p`` of material ``i`` is ``sum_s r_ps T_is / sum_s r_ps`` (``r_ps``: the
    filter's weight of sample ``s`` at ``p``, ``T_is``: its touch radiance with material ``i``),
    linear in each ``T_is``. Samples are processed in passes of at most ``max_samples`` paths to
    bound memory. Each image is an unbiased estimate of what ``component="touch"`` renders with
    that material alone; the images are correlated (the same paths).

    Parameters
    ----------
    integrator : ManifoldPathIntegrator
        The ``manifold_path`` instance (its ``target``, ``max_depth`` and path tracer).
    scene : mi.Scene
        Its target (``target`` parameter) must be one group of ``manifold_brdf``
        BSDFs on one manifold. The scene's materials are not modified.
    materials : list of str, optional
        Training materials of the manifold to render (default: all).
    spp, seed, sensor :
        As :meth:`render` (``spp=0``: the sensor's sample count).
    settings : PassSettings, optional
        Passes and kernels: materials per kernel, paths per pass (default ``PassSettings()``).
    progress : callable, optional
        Called as ``progress(done, total)`` in work units (one per pass and chunk).

    Returns
    -------
    OnePassImages
        ``base`` (ndarray float32 (H, W, 3): the paths that never scatter off the target)
        and ``images`` (dict of str -> ndarray float32 (H, W, 3): the touch image of each
        material, in the order of ``materials``).
    """
    base, images, _ = _render(integrator, scene, materials, spp, seed, sensor, settings, progress)
    return OnePassImages(base, images)


@dataclass
class OnePassGI:
    """:func:`render_onepass_gi`: every material's full-GI image from one set of paths.

    ``base``: paths that never touch the material; ``touch[name]``: exactly once (L1-
    minus base); ``rest[name]``: two to ``levels`` times (``L2+``, those beyond ``levels``
    are cut: ``paths[levels + 1]`` of them); ``base + touch + rest`` is the material's full-GI
    image. ``cross[(a, b)]``: ``C_ab = 4 R_m - 2 R_a - 2 R_b`` (``R_m``: the ``L2+`` image of their midpoint
    material; for two-vertex paths the paper's ``2 L2_ab - L2_aa - L2_bb``, :mod:`.multisplats`).
    ``paths[k]``: paths with ``k`` vertices on the material (``levels + 1``: more).
    """

    base: np.ndarray
    touch: dict
    rest: dict
    cross: dict
    paths: np.ndarray
    levels: int
    selection: dict = None  # what the pair selection measured (``pair_selection``), or None


def render_onepass_gi(
    integrator, scene, materials=None, spp=0, seed=0, sensor=0, levels=5, pairs=(), **options
):
    """Render base, touch, ``L2+`` and cross-term images of every material from one set of paths.

    As :func:`render_onepass`, but paths go on after their second vertex on the target, up
    to ``levels`` vertices (every one sampled with the proxy and recorded, :mod:`.records`),
    and the splats of levels ``2 .. levels`` make each material's ``L2+`` image and, for the
    pairs of material names ``pairs``, the cross terms (:mod:`.multisplats`). Nearest lookups
    (any film filter). ``options``: ``chunk``, ``max_samples``, ``spp_per_pass``,
    ``progress`` of :func:`render_onepass`, and ``cross_fraction`` (the share of the
    splats the cross terms use, each weighted by its inverse; default 1) and ``pair_selection``
    (a :class:`.multisplats.PairSelection`: ``pairs`` are candidates, those whose cross term
    matters are kept, measured on the first pass) and ``point`` (weights, one per material: the
    paths sample their blend, in absolute value, and the blend is rendered too, as :data:`POINT`:
    with the others' ``rest`` from the same paths, the control variate of :mod:`mitsuba_manifold.render.jobs.refine`)
    and ``touch`` (default True; False: no touch images, ``touch`` is empty, for a caller that
    needs only ``rest`` and ``cross``).

    Returns
    -------
    OnePassGI
    """
    if int(levels) < 2:
        raise InputError(
            f"manifold_path: `levels` must be >= 2 (1 is render_onepass), got {levels}"
        )
    fraction = float(options.get("cross_fraction", 1.0))
    if not 0 < fraction <= 1:
        raise InputError(f"manifold_path: `cross_fraction` must be in (0, 1], got {fraction}")
    gi = {
        "levels": int(levels),
        "pairs": [tuple(str(n) for n in p) for p in pairs],
        "cross_fraction": fraction,
        "select": options.get("pair_selection"),
    }
    if options.get("point") is not None:
        point = np.asarray(options["point"], np.float64)
        if (
            point.shape != (len(materials or ()),)
            or not np.isfinite(point).all()
            or not np.abs(point).sum() > 0
        ):
            raise InputError(
                f"manifold_path: `point` must be finite weights, one per material of `materials` "
                f"({len(materials or ())}), not all 0; got shape {point.shape}"
            )
        gi["point"] = point
    gi["touch"] = bool(options.get("touch", True))
    base, touch, extra = _render(
        integrator,
        scene,
        materials,
        spp,
        seed,
        sensor,
        PassSettings(
            options.get("chunk"), options.get("max_samples", 1 << 22), options.get("spp_per_pass")
        ),
        options.get("progress"),
        gi,
    )
    return OnePassGI(
        base, touch, extra["rest"], extra["cross"], extra["paths"], int(levels), extra["selection"]
    )


def _check_counts(**counts):
    """InputError for a count (``spp_per_pass``, ``chunk``) that is given and below 1."""
    for name, value in counts.items():
        if value is not None and int(value) < 1:
            raise InputError(f"manifold_path: `{name}` must be >= 1, got {value}")


def _multi_splats(gi, splat, names, dims, levels):
    """The L2+ splats of :func:`render_onepass_gi` (``gi``: its levels and pairs) over the table
    product of ``splat`` (:class:`TableSplats`: the manifold_brdf's nearest lookups).
    """
    if not isinstance(splat, TableSplats):
        raise InputError(
            "manifold_path: the L2+ images need the manifold_brdf's nearest lookups (the table "
            'product): give it interpolation="nearest" (its default), or render the L1- basis'
        )
    index = {n: k for k, n in enumerate(names)}
    bad = [p for p in gi["pairs"] if len(p) != 2 or p[0] not in index or p[1] not in index]
    if bad:
        raise InputError(
            f"manifold_path: `pairs` must name two rendered materials each, got {bad[0]!r}"
        )
    return MultiSplats(
        splat.rows,
        splat.n_pad,
        names,
        dims,
        splat.pixels,
        levels,
        [(index[a], index[b]) for a, b in gi["pairs"]],
        gi.get("cross_fraction", 1.0),
        gi.get("select"),
    )


def _blocks(film, spp, rows, names, chunks, db, target, dims, several_passes):
    """The film's block of the base image and the splats of the material images: the table
    product (:class:`TableSplats`) where ``rows`` hold the tables, else the BSDF's own lookups
    (:class:`FilterSplats`).
    """
    film.prepare([])
    base_block = film.create_block()
    base_block.set_coalesce(base_block.coalesce() and spp >= 4)
    if rows is None:
        splat = FilterSplats(
            film, base_block, names, chunks, db, target.path, target.options(), several_passes
        )
    else:
        splat = TableSplats(base_block, rows, names, chunks, dims, film.rfilter())
    return base_block, splat


def _render(
    integrator,
    scene,
    materials,
    spp,
    seed,
    sensor,
    settings,
    progress,
    gi=None,
):
    """:func:`render_onepass` (``gi`` None) or :func:`render_onepass_gi` (``gi``: levels, pairs);
    ``settings``: a :class:`PassSettings` (None: the defaults).
    """
    settings = PassSettings() if settings is None else settings
    chunk, max_samples, spp_per_pass = settings.chunk, settings.max_samples, settings.spp_per_pass
    target = one_target(scene, integrator.target)
    names = _material_names(target.manifold, target.path, materials)
    _check_counts(spp_per_pass=spp_per_pass, chunk=chunk)
    if isinstance(sensor, int):
        sensor = scene.sensors()[sensor]
    film = sensor.film()
    db = target.manifold.open_database(target.database, names)
    dims = tuple(int(d) for d in db.dims)
    # The table product needs nearest lookups and tables addressable with 32-bit indices.
    n_pad = -(-len(names) // PACKET) * PACKET
    rows = None
    if target.interpolation == "nearest" and int(np.prod(dims)) * 3 * n_pad < 1 << 32:
        rows = db.material_rows(names, pad=PACKET)
        if isinstance(rows, np.memmap):  # a cached file (a built-in set's rows are made in memory)
            _prefetch(rows.filename)  # read while the paths are traced
    point = gi.get("point") if gi else None
    if point is not None and rows is not None:  # the point's own material as one more column
        rows, names, proxy = with_point(target, db, names, rows, point)
    else:
        proxy = sampling_proxy(target, db, names, rows)

    if any(is_plain_twosided(c) for c in group_carriers(scene, target.groups)[0]):
        proxy = (proxy, mi.load_dict({"type": "twosided", "bsdf": proxy}))  # the back side mirrored
    levels = gi["levels"] if gi else 1
    touch = gi.get("touch", True) if gi else True
    spp = int(spp) or sensor.sampler().sample_count()
    # the records of every level of every path are held at once (60 bytes per path and level): fewer
    # paths per pass, but not below 3/5 of ``max_samples`` (each pass costs its cross terms' sums)
    passes = _passes(
        film, spp, max(1, int(max_samples) * 3 // max(3, min(levels, 5))), spp_per_pass
    )
    chunk = int(chunk) if chunk else (len(names) if rows is not None else 16)
    chunks = [(i, min(len(names), i + chunk)) for i in range(0, len(names), chunk)]
    alpha = mi.has_flag(film.flags(), mi.FilmFlags.Alpha)
    hits = group_carriers(scene, target.groups)
    plan = TracePlan(
        groups=target.groups,
        select=1,
        keep=3 if levels == 1 else 7,
        aovs=[],
        hits=hits,
        mirror=[c for c in hits[0] if is_plain_twosided(c)],
    )

    base_block, splat = _blocks(film, spp, rows, names, chunks, db, target, dims, len(passes) > 1)
    multi = _multi_splats(gi, splat, names, dims, levels) if gi else None

    done, total = 0, len(passes) * len(chunks)
    # Mitsuba's own sampler seeding and primary rays (they use nothing of their instance).
    rays = mi.ad.integrators.common.ADIntegrator
    with dr.suspend_grad():
        for p, n_spp in enumerate(passes):
            pass_seed = (int(seed) * len(passes) + p) & 0xFFFFFFFF  # Mitsuba's seeds are 32-bit
            sampler, _ = rays.prepare(integrator, sensor, pass_seed, n_spp, [])
            ray, weight, pos = rays.sample_rays(integrator, scene, sensor, sampler)
            L, valid, _, rec = integrator.trace_paths(
                scene, sampler, ray, mi.Bool(True), plan, levels, proxy
            )
            L = L * weight
            head = [L.x, L.y, L.z] + ([dr.select(valid, 1.0, 0.0)] if alpha else [])
            base_block.put(pos, head + [mi.Float(1.0)])
            if touch:
                splat.prepare(rec, rec["beta"] * weight, pos)
            if multi is not None:
                multi.prepare(rec, weight, splat.taps(pos), pass_seed)
            del sampler, ray, L, valid, rec, head
            for c in range(len(chunks)):
                splat.add(c)
                done += 1
                if progress is not None:
                    progress(done, total)
            splat.release()
            if multi is not None:
                multi.add()
                multi.release()
                if progress is not None:
                    progress(done, total)  # the L2+ splats took a while: let the caller stop
            # the buffers of a pass differ in size from the next one's (as many as its paths made
            # splats): Dr.Jit's cache of freed buffers would grow with every pass, not be reused
            dr.flush_malloc_cache()
    film.prepare([])
    film.put_block(base_block)
    film.develop()
    base = developed_rgb(film)  # RGB whatever the film's pixel format
    images = splat.images(film) if touch else {}
    if multi is None:
        return base, images, None
    rest, cross = multi.images(splat.scale(), base.shape)
    return (
        base,
        images,
        {"rest": rest, "cross": cross, "paths": multi.counts, "selection": multi.selection},
    )


class OnePassImages(NamedTuple):
    """:func:`render_onepass`: the base image and each material's touch image."""

    base: np.ndarray
    images: dict


@dataclass(frozen=True)
class OnePassTarget:
    """The one target group of a one-pass render and what its ``manifold_brdf`` BSDFs share."""

    groups: list
    manifold: object
    path: str
    database: object
    interpolation: str
    sampling: str

    def options(self):
        """``manifold_brdf`` parameters that make a BSDF look tables up as the target does."""
        out = {"interpolation": self.interpolation}
        if self.database is not None:
            out["database"] = self.database
        return out


def one_target(scene, target):
    """The single target group of ``scene`` for the integrator's ``target`` parameter, checked."""
    groups = target_groups(scene, target)
    if len(groups) != 1:
        raise InputError(
            f"manifold_path: one-pass rendering handles one target group, the target "
            f"{target!r} gives {len(groups)} ({[g[0] for g in groups]}); render "
            "several targets material by material"
        )
    bsdfs = groups[0][1]  # manifold_brdf instances: target_groups only returns those
    for carrier in group_carriers(scene, groups)[0]:
        if not is_manifold_bsdf(carrier) and not is_plain_twosided(carrier):
            name = (
                carrier.class_name() if hasattr(carrier, "class_name") else type(carrier).__name__
            )
            raise InputError(
                f"manifold_path: the manifold_brdf is held by a {name} BSDF ({carrier.id()!r}); one-pass rendering "
                "records the material's own vertices (it alone, or inside twosided): render material by "
                "material (`mode` 'per-material', L1- images), or give the shape the manifold_brdf itself"
            )
    first = bsdfs[0]
    for b in bsdfs[1:]:
        same = (
            os.path.samefile(b.manifold_path, first.manifold_path)
            and b.interpolation == first.interpolation
            and b.database == first.database
        )
        if not same:
            raise InputError(
                f"manifold_path: target BSDFs {first.id()!r} and {b.id()!r} differ in "
                "manifold, database or interpolation; one-pass rendering needs them alike"
            )
    return OnePassTarget(
        groups,
        first.manifold,
        first.manifold_path,
        first.database,
        first.interpolation,
        first.sampling,
    )


def _material_names(manifold, path, materials):
    names = list(manifold.names) if materials is None else [str(n) for n in materials]
    unknown = [n for n in names if n not in manifold.names]
    if unknown or not names or len(set(names)) != len(names):
        raise InputError(
            f"manifold_path: materials must be distinct names of the manifold {path}; "
            f"unknown: {unknown or 'none'} (it has {', '.join(manifold.names[:8])}, ...)"
        )
    return names


def _passes(film, spp, max_samples, spp_per_pass):
    """Samples per pixel of each pass: at most ``max_samples`` paths (or ``spp_per_pass``) at once."""
    size = film.crop_size()
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    pixels = int(size[0]) * int(size[1])
    pass_spp = int(spp_per_pass) if spp_per_pass else int(max_samples) // max(pixels, 1)
    pass_spp = max(1, min(spp, pass_spp))
    if pixels * pass_spp > 2**32:
        raise InputError(
            f"manifold_path: {pixels * pass_spp} samples in one wavefront exceed 2^32; "
            "use fewer samples per pixel per pass (`spp_per_pass`)"
        )
    return [pass_spp] * (spp // pass_spp) + ([spp % pass_spp] if spp % pass_spp else [])
